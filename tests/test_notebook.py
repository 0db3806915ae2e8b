"""What a notebook sees: experiments/explore.ipynb run from top to bottom in a fresh kernel, the short reprs of the
results it shows, and a matplotlib backend that importing the packages leaves alone."""

import dataclasses
import importlib.util
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from pusupu_jax import AxisLoad, LoopRates, ServoParams, simulate
from pusupu_jax.params import stack
from pusupu_jax.trajectories import axis_reference

ROOT = Path(__file__).resolve().parent.parent
NOTEBOOK = ROOT / "experiments" / "explore.ipynb"
# s per cell: from an empty compile cache the tuner's gradient compiles for about 4.5 min on this 2-core machine,
# and a CI machine is 2.5x slower; with a warm cache the whole notebook takes 55-90 s
CELL_TIMEOUT = 1800
MAX_REPR = 2800  # characters: one short line per field (37 fields of ServoParams), not the arrays' reprs


def _backend_for_the_test() -> str:
    """A backend other than Agg that loads without a display."""
    return "module://matplotlib_inline.backend_inline" if importlib.util.find_spec("matplotlib_inline") else "svg"


def test_importing_the_packages_leaves_the_matplotlib_backend_alone():
    """Probe: pusupu_jax.plots and pusupu_jax.tune.job called matplotlib.use("Agg") on import, so a notebook lost its
    inline
    backend.  A fresh interpreter with MPLBACKEND set keeps it after importing every layer that plots."""
    backend = _backend_for_the_test()
    code = (
        "import matplotlib, pusupu_jax, pusupu_jax.plots, pusupu_jax.tune, pusupu_jax.tune.run, pusupu_jax.tune.job, "
        "pusupu_jax.tune.batchjob, pusupu_jax.experiments, pusupu_jax.experiments.arc, pusupu_jax.cli.cli; "
        "print(matplotlib.get_backend())"
    )
    out = subprocess.run(
        [sys.executable, "-c", code],
        env=dict(os.environ, MPLBACKEND=backend),
        capture_output=True,
        text=True,
        timeout=300,
        check=True,
    )
    assert out.stdout.strip() == backend, out.stderr[-2000:]


@pytest.mark.slow
def test_the_command_selects_agg_itself(tmp_path):
    """The ``pusupu`` command writes its figures with Agg whatever MPLBACKEND says (here a backend it must not keep)."""
    code = (
        "import sys, matplotlib; from pusupu_jax.cli.cli import main; "
        "status = main(['sim', '--plant', 'axis', '--trajectory', 'step', '--duration', '0.05', "
        f"'--plot', {str(tmp_path / 'step.png')!r}]); "
        "print(matplotlib.get_backend().lower(), status, file=sys.stderr)"
    )
    out = subprocess.run(
        [sys.executable, "-c", code],
        env=dict(os.environ, MPLBACKEND=_backend_for_the_test()),
        capture_output=True,
        text=True,
        timeout=300,
        check=True,
    )
    assert out.stderr.strip().splitlines()[-1] == "agg 0", out.stderr[-2000:]
    assert (tmp_path / "step.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_plot_helpers_return_figures_and_write_files_only_when_asked(tmp_path):
    from matplotlib.figure import Figure

    from pusupu_jax import plots

    servo, load = ServoParams.table1(), AxisLoad.default()
    fig = plots.plot_loops(servo, load)
    assert isinstance(fig, Figure) and len(fig.axes) == 9
    assert not list(tmp_path.iterdir())
    png = tmp_path / "loops.png"
    assert isinstance(plots.plot_loops(servo, load, png), Figure)
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_parameter_sets_show_as_a_short_table_per_axis_with_units():
    p = ServoParams.table1()
    p = p.replace(Kv=np.array([0.015, 0.015, 0.015, 0.015, 0.015, 0.0234]), lambda2=np.full(6, 0.1234))
    text = repr(p)
    assert len(text) < MAX_REPR, len(text)
    assert text.startswith("ServoParams: 6 axes, imc_form='full'")
    kv = next(line for line in text.splitlines() if line.split()[0] == "Kv")
    assert kv.split()[1:] == ["A/(rad/s)", "0.015", "0.015", "0.015", "0.015", "0.015", "0.0234"]
    lambda2 = next(line for line in text.splitlines() if line.split()[0] == "lambda2")
    assert lambda2.split()[1:] == ["s", "0.1234", "(every", "axis)"]
    assert "|---|---|" in p._repr_markdown_() and "| Kv | A/(rad/s) | 0.015 |" in p._repr_markdown_()
    # every axis different: still one line per field
    spread = p.replace(**{f: np.linspace(1.0, 1.5, 6) * getattr(p, f) for f in ("lambda1", "T0", "Tv", "Ki", "R")})
    assert len(repr(spread).splitlines()) == len(text.splitlines())
    batch = repr(stack([p, p.replace(Kv=p.Kv * 2)]))
    assert "a batch of 2 sets" in batch and "0.015..0.03" in batch and len(batch) < MAX_REPR
    load = repr(AxisLoad.default())
    assert "mass" in load and "kg" in load and len(load) < 600


def test_a_trace_shows_its_duration_shapes_and_per_axis_peaks():
    """The 0.5 s step of ``pusupu sim`` (a shape the suite compiles anyway): a few lines, not 15k characters of
    arrays."""
    servo = ServoParams.table1()
    trace = simulate(servo, axis_reference("step", LoopRates(), 0.5))
    text = repr(trace)
    assert len(text) < MAX_REPR, len(text)
    assert text.startswith("Trace: 0.5 s, 500 periods of 1 ms, 6 axes") and "(500, 6)" in text
    peak = float(np.abs(np.asarray(trace.current)).max(axis=0)[0])
    assert f"{peak:.4g}" in next(line for line in text.splitlines() if "peak current" in line)
    assert "| peak current | A |" in trace._repr_markdown_()


def test_an_experiment_result_shows_its_name_and_top_level_metrics():
    from pusupu_jax.experiments import Result

    metrics = {
        "rms_tracking_error_mm": {"pid": 0.9181234, "imc": 0.4081234},
        "branch_rms_error_mm": [0.1] * 6,
        "seeds": list(range(500)),
        "note": "x" * 5000,
    }
    text = repr(Result("arc", metrics, {"t": np.zeros(100_000)}))
    assert len(text) < MAX_REPR, len(text)
    assert text.startswith("Result 'arc'") and "pid: 0.9181" in text and "branch_rms_error_mm" in text
    assert "series ['t']" in text and "array" not in text and "..." in text  # the long metrics cut, no arrays


def test_the_tuners_results_show_as_summaries():
    import jax
    import jax.numpy as jnp

    from pusupu_jax.metrics import MachineMetrics
    from pusupu_jax.tune.report import Export, GainFileRef, TuneReport
    from pusupu_jax.tune.state import Evaluation
    from pusupu_jax.tune.optimise import optimise

    def vg(z):
        return jax.value_and_grad(lambda z: (jnp.sum((z["lambda1"] - 1.0) ** 2), None), has_aux=True)(z)

    result = optimise(vg, {"lambda1": jnp.zeros(6)}, lambda z: z, iterations=40, learning_rate=0.1)
    text = repr(result)
    assert len(text) < MAX_REPR and text.startswith("OptimiseResult: objective 6 at the start")
    assert "41 evaluations over 1 start(s)" in text and "lambda1 " in text
    assert set(result.z) == {"lambda1"} and len(result.history) == 41 and result.objective < 1e-3
    six = [1.0] * 6
    run = {"p2p": MachineMetrics(3.0, 0.02, 0.04, six, [None] * 6, six, [64.0] + six[1:], 0.001, 1e-6)}
    report = TuneReport(
        config={},
        config_hash="0" * 16,
        machine={"name": "built-in"},
        start_gains={"source": "table1"},
        tuned_fields=["lambda1"],
        start={"lambda1": [0.018] * 6},
        result={"lambda1": [0.0147] * 6},
        objective_before=1.1,
        objective_after=0.79,
        history=[Evaluation(0, k, 1.0) for k in range(999)],
        before=run,
        after=run,
        baselines={},
        margins_before={},
        optimise_wall_s=50.0,
        export=Export(
            {}, [], GainFileRef(None, not_written="a phase margin below 45 deg"), "a phase margin below 45 deg"
        ),
        plots=[],
        wall_s=57.0,
    )
    text = repr(report)
    assert len(text) < MAX_REPR and "objective 1.1000 -> 0.7900 in 999 evaluations" in text
    assert "lambda1  0.018 -> 0.0147" in text and "NOT EXPORTED: a phase margin below 45 deg" in text
    # report.json's content reads back as the same record
    assert TuneReport.from_json(json.loads(json.dumps(report.to_json()))) == report
    # exported, with ROS's PID short of the floors: the report keeps the warning tune printed
    short = "ROS's PID with these gains keeps less than 45 deg and 6 dB"
    warned = dataclasses.replace(
        report, export=Export({}, ["gains.yaml"], GainFileRef("gains.yaml", "0" * 64), ros_warning=short)
    )
    assert warned.to_json()["ros_warning"] == short and f"warning: {short}" in repr(warned)
    assert "NOT EXPORTED" not in repr(warned) and "ros_warning" not in report.to_json()
    assert TuneReport.from_json(json.loads(json.dumps(warned.to_json()))) == warned


@pytest.mark.slow
def test_the_notebook_runs_in_a_fresh_kernel_with_its_figures_inline():
    """experiments/explore.ipynb, stored without outputs, runs without an error in a kernel that inherits this
    process's environment (PUSUPU_JAX_CACHE: the suite's compile cache), and shows its figures inline (PNG)."""
    nbformat = pytest.importorskip("nbformat")
    nbclient = pytest.importorskip("nbclient")
    nb = nbformat.read(NOTEBOOK, as_version=4)
    code = [c for c in nb.cells if c.cell_type == "code"]
    assert all(not c.outputs and c.execution_count is None for c in code), "store the notebook without outputs"
    client = nbclient.NotebookClient(
        nb, timeout=CELL_TIMEOUT, kernel_name="python3", resources={"metadata": {"path": str(NOTEBOOK.parent)}}
    )
    t0 = time.perf_counter()
    client.execute()  # raises CellExecutionError, naming the cell, on an error
    wall = time.perf_counter() - t0
    outputs = [o for c in code for o in c.outputs]
    assert not [o for o in outputs if o.output_type == "error"]
    images = [o for o in outputs if o.output_type == "display_data" and "image/png" in o.data]
    assert len(images) >= 4, [o.output_type for o in outputs]
    text = "".join(o.get("text", "") for o in outputs if o.output_type == "stream")
    assert f"compile cache: {os.environ['PUSUPU_JAX_CACHE']}" in text  # the kernel got the suite's cache
    assert "x faster: no compile" in text
    shown = "".join(o.data.get("text/plain", "") for o in outputs if o.output_type == "execute_result")
    assert "ServoParams: 6 axes" in shown and "OptimiseResult: objective" in shown and "GainFile: pusupu-gains" in shown
    print(f"notebook: {wall:.0f} s")
