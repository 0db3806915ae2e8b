"""Shared set-up: float64, JAX's persistent compilation cache (in .jax_cache/ unless PUSUPU_JAX_CACHE is set), and
XLA's backend (LLVM) optimisation level 1 for every program the suite compiles, in this process and in the commands
it runs.

The suite compiles some hundred MJX programs from an empty cache, and compiling is much of its time; the rest is
running them.  Below XLA's default level (3) the same programs (XLA's own passes unchanged) compile faster; at level
0, with LLVM's optimisation off, they also run several times slower, which the suite's longer runs feel.  On the
2-core CPU, from an empty cache, one file after another alone: the quick experiments and the objective terms'
gradient check (``tests/test_experiments.py tests/test_mjx_plant.py -k "quick or every_objective"``) 310 s at level
0 against 253 s at level 1; ``tests/test_batch.py``, mostly compiling, 303 s against 302 s.  The whole suite from a
clean clone, as CI runs it, the same day: 20 min 46 s of tests at level 0 (37.6 min of user CPU for the whole run)
and 20 min 39 s at level 1 (39.0 min), within the machine's own spread.  Earlier, the whole suite took 41 min 21 s
at level 3 against 36 min 35 s at 0.  The suite passes at every level.  A user's
programs keep XLA's default (3); to run the suite at another, set ``XLA_FLAGS=--xla_backend_optimization_level=N`` (a
level set there is kept)."""

import json
import os
import time

if "--xla_backend_optimization_level" not in os.environ.get("XLA_FLAGS", ""):  # before JAX starts its backend
    os.environ["XLA_FLAGS"] = f"{os.environ.get('XLA_FLAGS', '')} --xla_backend_optimization_level=1".strip()

from collections import Counter  # noqa: E402
from pathlib import Path  # noqa: E402

import pytest  # noqa: E402

from pusupu_jax.runtime import setup_jax  # noqa: E402

CACHE = setup_jax(os.environ.get("PUSUPU_JAX_CACHE") or Path(__file__).resolve().parent.parent / ".jax_cache")
os.environ["PUSUPU_JAX_CACHE"] = str(CACHE)  # the CLI subprocesses share it


# The order in which pytest-xdist hands out the test files (``--dist loadfile --no-loadscope-reorder``, pyproject.toml).
# Each worker runs one file and has the next one queued behind it.  xdist's own order (most tests first) left the
# heaviest files of few tests to the end: from an empty cache on a 2-core Intel Xeon, the user's machine end to end (one
# test, 189 s) started at minute 18, and the last 2 min 20 s ran on one worker (the batch file's Ray test, then the
# loop-match file queued behind it), the other two done.  So the files that take minutes go first (the batch's after
# the CLI's, whose tune compiles the programs that the batch's comparison with lone tunes loads), and the rest follow,
# most tests first, as xdist would hand them out.  From an empty cache there, the three workers then ended within 9 s
# of each other (1187 to 1196 s).
HEAVY_FIRST = (
    "test_cli.py",
    "test_mjx_plant.py",
    "test_experiments.py",
    "test_user_machine.py",
    "test_contact_experiments.py",
    "test_batch.py",
    "test_loop_match.py",
    "test_identify.py",
)


def pytest_addoption(parser):
    parser.addoption(
        "--compile-profile",
        metavar="FILE",
        help="append a JSON line per test to FILE (one file per xdist worker: FILE.gw0, ...): its wall and process "
        "CPU seconds, the CPU seconds of the commands it ran as processes of their own and waited for, and the seconds "
        "JAX spent in this process tracing, lowering and XLA compiling, with the count of each (jax.monitoring's "
        "duration events)",
    )


class _CompileProfile:
    """JAX's compile-time events summed per test: what ``--compile-profile`` writes."""

    EVENTS = {
        "/jax/core/compile/jaxpr_trace_duration": "trace",
        "/jax/core/compile/jaxpr_to_mlir_module_duration": "lower",
        "/jax/core/compile/backend_compile_duration": "compile",
    }

    def __init__(self, path: Path):
        import jax.monitoring

        self.path, self.seconds, self.counts = path, Counter(), Counter()
        self.started: dict[str, tuple[float, float, float, Counter, Counter]] = {}
        jax.monitoring.register_event_duration_secs_listener(self._event)

    def _event(self, event: str, seconds: float, **_) -> None:
        if event in self.EVENTS:
            self.seconds[self.EVENTS[event]] += seconds
            self.counts[self.EVENTS[event]] += 1

    @pytest.hookimpl
    def pytest_runtest_logstart(self, nodeid, location):
        self.started[nodeid] = (
            time.perf_counter(),
            time.process_time(),
            _children_cpu(),
            self.seconds.copy(),
            self.counts.copy(),
        )

    @pytest.hookimpl
    def pytest_runtest_logfinish(self, nodeid, location):
        wall, cpu, children, seconds, counts = self.started.pop(nodeid)
        record = {
            "test": nodeid,
            "wall_s": time.perf_counter() - wall,
            "cpu_s": time.process_time() - cpu,
            "commands_cpu_s": _children_cpu() - children,
        }
        for name in self.EVENTS.values():
            record[f"{name}_s"] = self.seconds[name] - seconds[name]
            record[f"{name}_count"] = self.counts[name] - counts[name]
        with self.path.open("a") as f:
            f.write(json.dumps(record) + "\n")


def _children_cpu() -> float:
    """User and system CPU seconds of this process's ended children (the commands a test ran and waited for)."""
    import resource

    usage = resource.getrusage(resource.RUSAGE_CHILDREN)
    return usage.ru_utime + usage.ru_stime


def pytest_configure(config):
    path = config.getoption("--compile-profile")
    worker = os.environ.get("PYTEST_XDIST_WORKER")
    if path and (worker or not config.getoption("numprocesses", None)):  # the workers run the tests, not xdist's main
        config.pluginmanager.register(_CompileProfile(Path(f"{path}.{worker}" if worker else path)))


def pytest_collection_modifyitems(items):
    count = Counter(item.path.name for item in items)
    rank = {name: k for k, name in enumerate(HEAVY_FIRST)}
    items.sort(key=lambda item: (rank.get(item.path.name, len(rank)), -count[item.path.name]))  # stable per file


@pytest.fixture
def refused(capsys):
    """``refused(*args, alone=True)``: the error line of ``pusupu ARGS`` run in this process (``cli.main``), which must
    refuse its input: exit status 2 (SystemExit, or returned by a command that prints its findings first) and
    ``pusupu: error: ...`` as the last line on stderr (with ``alone``, the only one); what the command printed on
    stdout is then ``refused.stdout``.  A command of its own costs 2.4 to 3.9 s of CPU to start; the refusals that a
    real process must show (nothing else on stderr, no traceback) have subprocess tests (tests/test_cli.py)."""
    from pusupu_jax.cli.cli import main

    def run(*args, alone: bool = True) -> str:
        capsys.readouterr()
        try:
            status = main([str(a) for a in args])  # a command that prints its findings first returns its status
        except SystemExit as e:
            status = e.code
        captured = capsys.readouterr()
        run.stdout, err = captured.out, captured.err
        lines = err.strip().splitlines()
        assert status == 2 and lines and lines[-1].startswith("pusupu: error: "), (status, err)
        assert len(lines) == 1 or not alone, err
        return lines[-1]

    return run


@pytest.fixture(scope="session")
def in_process():
    """``in_process(*args) -> stdout``: ``pusupu ARGS`` run in this process (``cli.main``), which must succeed (status
    0).  For a command whose programs this worker has in memory already (a tuning run and what reads its gain file):
    a process of its own would start Python and JAX and load every program again (from an empty cache on the 2-core
    CPU, the killed and resumed tiny tune took 53 s of CPU with its resumed run as a process, 34 s in this one)."""
    import contextlib
    import io

    from pusupu_jax.cli.cli import main

    def run(*args) -> str:
        out = io.StringIO()
        with contextlib.redirect_stdout(out):
            status = main([str(a) for a in args])
        assert status == 0, (args, status)
        return out.getvalue()

    return run


@pytest.fixture(scope="session")
def table1():
    from pusupu_jax import ServoParams

    return ServoParams.table1()


@pytest.fixture(scope="session")
def linear_load():
    """The default single-axis load (mass, no gravity along a level rail): linear."""
    from pusupu_jax import AxisLoad

    return AxisLoad.default()


@pytest.fixture(scope="session")
def table1_linear():
    """Table 1 without the drive train's Coulomb friction: the plant is then linear, so python-control models it
    exactly."""
    import numpy as np

    from pusupu_jax import ServoParams

    return ServoParams.table1().replace(coulomb=np.zeros(6))
