"""``pusupu tune``: the main job, from configuration to gain file, report and plots (host-side).

1. Build the problem (:class:`pusupu_jax.tune.run.Problem`) from the configuration on the machine (a machine
   file, or the built-in machine); the start (:func:`start_gains`) is Table 1 with the default hybrid
   gains on the built-in machine, gains derived for the machine otherwise, or a gain file.
2. Optimise (:meth:`pusupu_jax.tune.run.Problem.tune`: :func:`pusupu_jax.tune.optimise.optimise` with the config's
   settings) on training windows spread over the whole paths, checkpointing to ``DIR/checkpoint.npz`` (arrays and
   JSON, never a pickle); a run that finds a checkpoint of the same configuration continues from it.
   ``DIR`` is locked while a run uses it.
3. Evaluate the start and the result on the whole paths with the problem's own forward pass
   (no second compile), and the baselines (``cfg.baselines``: PID and PID with velocity
   feedforward, the start gains) with :func:`pusupu_jax.machine.simulate_scenarios`.
4. Write ``DIR/gains.yaml`` (only if the tuned gains pass every check: :mod:`pusupu_jax.gains`),
   the ROS 2 parameter files ``DIR/ros2_pid_controller.yaml`` and
   ``DIR/ros2_joint_trajectory_controller.yaml`` (:mod:`pusupu_jax.ros2`), the plots
   ``objective.png``, ``path_<scenario>.png``, ``forces_<scenario>.png``, and last ``DIR/report.json``.
"""

from __future__ import annotations

import contextlib
import fcntl
import hashlib
import json
import os
import socket
import stat
import sys
import time
from pathlib import Path

import matplotlib.pyplot as plt
import numpy as np

from pusupu_jax import devices, gains, inputs, machine_file, ros2, stability
from pusupu_jax.files import check_output, check_output_folder, write_atomic, write_files
from pusupu_jax.hybrid import HybridGains
from pusupu_jax.machine import Scenario, simulate_scenarios
from pusupu_jax.machine_file import Machine
from pusupu_jax.params import AxisLoad, ParameterError, ServoParams
from pusupu_jax.plots import save_atomic
from pusupu_jax.runtime import require_x64
from pusupu_jax.start_gains import derive

from .config import TuneConfig
from .checkpoint import CHECKPOINT
from .progress import progress_reporter
from .report import Export, GainFileRef, TuneReport, metrics_json
from .run import Problem, check_work, scenario_list
from .state import Evaluation


def evaluate_baselines(cfg: TuneConfig, rates, specs=None, servo: ServoParams | None = None) -> dict:
    """``{mode: {scenario: (MachineRun, arrays)}}`` of every baseline mode on the whole paths of ``specs`` (default: the
    configuration's on the built-in machine), with the start gains ``servo`` (default Table 1)."""
    specs = scenario_list(cfg) if specs is None else specs
    servo = ServoParams.table1() if servo is None else servo
    scenarios = [Scenario(spec.path(rates), spec.options, spec.name, spec.geometry, spec.drives) for spec in specs]
    return {
        mode: {sc.name: out for sc, out in zip(scenarios, simulate_scenarios(servo, scenarios, mode=mode, rates=rates))}
        for mode in cfg.baselines
    }


def start_gains(machine: Machine, start=None, stream=None) -> tuple[ServoParams, HybridGains, dict]:
    """Where tuning ``machine`` starts: ``start`` 'table1', 'derived' (:func:`pusupu_jax.start_gains.derive`, said on
    ``stream`` when given) or a :class:`~pusupu_jax.gains.GainFile`; None: Table 1 on the built-in machine, derived on
    any other.  Returns the servo gains on the machine, the hybrid gains and what the report says of them."""
    if start is None:
        start = "table1" if machine_file.is_builtin(machine) else "derived"
    if isinstance(start, gains.GainFile):
        return machine.servo(start.servo), start.hybrid, {"source": "gain file", "checksum": start.document["checksum"]}
    if start == "table1":
        return machine.servo(ServoParams.table1()), HybridGains(), {"source": "table1"}
    if start == "derived":
        if stream is not None:
            print(
                f"tune: deriving start gains for machine {machine.name!r} (docs/machine.md; T0 identified on the "
                "MJX machine)",
                file=stream,
                flush=True,
            )
        servo, derivation = derive(machine)
        return servo, HybridGains(), {"source": "derived"} | derivation
    raise ParameterError(f"--start-gains: expected a gain file, table1 or derived, got {start!r}")


def _plots(out: Path, history: list[Evaluation], before, after, baselines) -> list[str]:
    files = []
    fig, ax = plt.subplots(figsize=(6, 4))
    for k in sorted({h.start for h in history}):
        pts = [(h.iteration, h.objective) for h in history if h.start == k]
        ax.plot(*zip(*pts), marker=".", label=f"start {k + 1}")
    ax.set_xlabel("iteration")
    ax.set_ylabel("objective (1 = start, lower is better)")
    ax.grid(True, alpha=0.3)
    ax.legend()
    files.append(str(save_atomic(fig, out / "objective.png")))
    for name in before:
        (_, tb), (_, ta) = before[name], after[name]
        fig = plt.figure(figsize=(12, 5))
        ax = fig.add_subplot(1, 2, 1)
        ax.plot(tb["reference"][:, 0] * 1e3, tb["reference"][:, 1] * 1e3, "k--", label="reference")
        ax.plot(tb["platform"][:, 0] * 1e3, tb["platform"][:, 1] * 1e3, label="before (Table 1)")
        ax.plot(ta["platform"][:, 0] * 1e3, ta["platform"][:, 1] * 1e3, label="after (tuned)")
        for mode, runs in baselines.items():
            ax.plot(
                runs[name][1]["platform"][:, 0] * 1e3,
                runs[name][1]["platform"][:, 1] * 1e3,
                lw=0.8,
                label=f"baseline {mode}",
            )
        ax.set_xlabel("x [mm]")
        ax.set_ylabel("y [mm]")
        ax.axis("equal")
        ax.legend()
        ax2 = fig.add_subplot(1, 2, 2)
        curves = [("before", tb), ("after", ta)] + [
            (f"baseline {mode}", runs[name][1]) for mode, runs in baselines.items()
        ]
        for label, tr in curves:
            ax2.plot(tr["t"], np.linalg.norm(tr["platform"] - tr["reference"], axis=1) * 1e3, label=label, lw=0.9)
        ax2.set_yscale("log")
        ax2.set_xlabel("time [s]")
        ax2.set_ylabel("platform position error [mm]")
        ax2.grid(True, alpha=0.3)
        ax2.legend()
        fig.suptitle(f"{name}: reference vs tracked path")
        fig.tight_layout()
        files.append(str(save_atomic(fig, out / plot_file("path", name))))
        fig, axes = plt.subplots(2, 1, figsize=(9, 6), sharex=True, sharey=True)
        for ax, (label, tr) in zip(axes, (("before (Table 1)", tb), ("after (tuned)", ta))):
            for b in range(6):
                ax.plot(tr["t"], tr["branch_force"][:, b], lw=0.8, label=f"branch {b + 1}")
            ax.set_ylabel(f"{label}\nbranch force [N]")
            ax.grid(True, alpha=0.3)
        axes[0].legend(ncol=6, fontsize=7)
        axes[1].set_xlabel("time [s]")
        fig.suptitle(f"{name}: branch forces")
        fig.tight_layout()
        files.append(str(save_atomic(fig, out / plot_file("forces", name))))
    return files


def plot_file(kind: str, scenario: str) -> str:
    """The name of a run's ``kind`` plot (path, forces) of ``scenario``."""
    return f"{kind}_{scenario.replace('/', '_')}.png"


def run_files(scenarios) -> tuple:
    """The files a run with ``scenarios`` (names) writes into its folder, besides its checkpoint."""
    return (
        "gains.yaml",
        *ros2.FILES,
        "report.json",
        "objective.png",
        *(plot_file(kind, name) for name in scenarios for kind in ("path", "forces")),
    )


def prepare_output(out: Path, files=()) -> Path:
    """Check ``out`` before any work: a folder that exists or can be made, writable, holding no pickled checkpoint,
    in which each of ``files`` (names) is a regular file or absent (:func:`pusupu_jax.files.check_output`)."""
    check_output_folder(out)
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise ParameterError(f"--out: cannot write in {str(out)!r} ({e.strerror})") from None
    legacy = out / "checkpoint.pkl"
    if legacy.exists():
        raise ParameterError(
            f"{legacy}: a pickled checkpoint (an older pusupu_jax's, or someone else's) is never read, "
            "since loading a pickle can run code; delete it or choose another --out"
        )
    for name in files:
        check_output(out / name)
    return out


class OutputLock:
    """An exclusive lock on an output folder (``DIR/.pusupu.lock``, held by this process until it exits).

    The lock file is opened without following a symlink and without truncating it, and must be a regular file of one
    link: a symlink, FIFO, device or hard link planted there is refused (one line) and whatever it names is never
    opened or written.  Only once the lock is held is the file emptied and given this holder's pid.
    """

    def __init__(self, out: Path):
        self.path = out / ".pusupu.lock"
        check_output(self.path)  # refused before it is opened: opening a device can act on it
        try:
            fd = os.open(self.path, os.O_RDWR | os.O_CREAT | os.O_NOFOLLOW | os.O_NONBLOCK | os.O_CLOEXEC, 0o666)
        except OSError as e:  # ELOOP: a symlink put there since the check
            raise ParameterError(f"{self.path}: cannot open the lock file ({e.strerror})") from None
        st = os.fstat(fd)
        if not stat.S_ISREG(st.st_mode) or st.st_nlink != 1:
            os.close(fd)
            found = inputs.file_kind(st.st_mode) if not stat.S_ISREG(st.st_mode) else f"{st.st_nlink} hard links"
            raise ParameterError(f"{self.path}: expected a lock file of one link, found {found}; left as it is")
        self.file = os.fdopen(fd, "r+")
        try:
            fcntl.flock(self.file, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            self.file.seek(0)
            holder = self.file.read(200).strip() or "unknown"
            self.file.close()
            raise ParameterError(
                f"--out: {out} is in use by another pusupu tune ({holder}); wait for it or choose another --out"
            ) from None
        self.file.seek(0)
        self.file.truncate()
        self.file.write(f"pid {os.getpid()} on {socket.gethostname()}")
        self.file.flush()

    def release(self, refused_in_new_folder: bool = False):
        """Unlock; ``refused_in_new_folder``: the run that made the folder refused its input before writing anything,
        so the lock file goes, and the folder too where nothing else is in it."""
        fcntl.flock(self.file, fcntl.LOCK_UN)
        self.file.close()
        if refused_in_new_folder:
            self.path.unlink(missing_ok=True)
            with contextlib.suppress(OSError):  # not empty: left as it is
                self.path.parent.rmdir()


def run_job(
    cfg: TuneConfig, out: Path, fresh: bool = False, stream=sys.stderr, machine: Machine | None = None, start=None
) -> tuple[TuneReport, int]:
    """Run the whole job on ``machine`` (default: the built-in one) from ``start`` (:func:`start_gains`); returns
    ``(report, exit status)`` (1 when the tuned gains fail a check).  The work it implies
    (:func:`pusupu_jax.tune.run.check_work`) and the output folder are checked before anything is built.

    The outputs of one run are written gains first, report last; the report names the gain
    file it describes by its checksum (or says that none was written and why).  JAX must compute in float64
    (:func:`pusupu_jax.runtime.setup_jax`): a RuntimeError says so before anything runs, where float32 would tune
    for minutes and then fail the export's check.
    """
    require_x64("pusupu tune's gradients and the stability check of the gains it exports")
    machine = Machine.default() if machine is None else machine
    specs = scenario_list(cfg, machine)
    check_work(cfg, specs)
    new_folder = not out.exists()
    prepare_output(out, (*run_files(s.name for s in specs), CHECKPOINT))
    lock, refused = OutputLock(out), False
    try:
        return _run(cfg, out, fresh, stream, machine, specs, start)
    except ParameterError:  # a value checked once the problem is built (bounds, a path's reach): one line, no folder
        refused = True
        raise
    finally:
        lock.release(refused_in_new_folder=refused and new_folder)


def _run(cfg: TuneConfig, out: Path, fresh: bool, stream, machine: Machine, specs, start) -> tuple[TuneReport, int]:
    checkpoint = out / CHECKPOINT
    if fresh and checkpoint.exists():
        checkpoint.unlink()
    t0 = time.perf_counter()
    servo0, hybrid0, start_report = start_gains(machine, start, stream)
    digest = hashlib.sha256(
        json.dumps(
            [
                cfg.digest(),
                machine_file.digest(machine),
                {f: np.asarray(v).tolist() for f, v in vars(servo0).items() if not isinstance(v, str)},
            ]
        ).encode()
    ).hexdigest()
    problem = Problem(cfg, servo0, hybrid0, specs, digest=digest, machine=machine)
    devices.announce(stream)
    extent = "whole path" if cfg.path_s is None else f"path cut to {cfg.path_s:g} s"
    print(
        f"tune: {len(problem.scenarios.names)} scenario(s) ({', '.join(problem.scenarios.names)}), "
        f"{cfg.windows} windows of {cfg.window_s:g} s spread over each {extent}, "
        f"tuning {', '.join(problem.space.fields)}; compiling the forward pass and the gradient "
        "(about 1.5 min cold on 2 CPU cores)",
        file=stream,
        flush=True,
    )
    result = problem.tune(checkpoint=checkpoint, progress=progress_reporter(cfg.starts, stream))
    servo0 = problem.space.servo0
    servo1, hybrid1 = problem.space.host_values(result.z)
    t_opt = time.perf_counter() - t0
    print(
        "tune: evaluating the start and the result on the whole paths"
        + (f", and the baselines ({', '.join(cfg.baselines)}, start gains)" if cfg.baselines else ""),
        file=stream,
        flush=True,
    )
    before, after = problem.path_metrics(problem.space.z0()), problem.path_metrics(result.z)
    baselines = evaluate_baselines(cfg, problem.rates, specs, servo0)
    objective_before = result.history[0].objective
    metrics_after = {n: r for n, (r, _) in after.items()}
    provenance = {
        "config_hash": cfg.digest(),
        "objective_before": objective_before,
        "objective_after": result.objective,
        "floors": [cfg.pm_min, cfg.gm_min],
        "metrics_after": metrics_json(metrics_after),
    }
    outcome = export(out, cfg, servo1, hybrid1, problem.rates, problem.space.fields, provenance, machine, problem.loads)
    if outcome.ros_warning is not None:
        print(f"tune: warning: {outcome.ros_warning}", file=stream, flush=True)
    report = TuneReport(
        config=cfg.to_json(),
        config_hash=cfg.digest(),
        machine=machine_file.reference(machine),
        start_gains=start_report,
        tuned_fields=list(problem.space.fields),
        start=problem.space.json_values(problem.space.z0()),
        result=problem.space.json_values(result.z),
        objective_before=objective_before,
        objective_after=result.objective,
        history=[h.without_point() for h in result.history],
        before={n: r for n, (r, _) in before.items()},
        after=metrics_after,
        baselines={mode: {n: r.metrics for n, (r, _) in runs.items()} for mode, runs in baselines.items()},
        margins_before=gains.margins_report(servo0, mode=cfg.mode, machine=machine),
        optimise_wall_s=t_opt,
        export=outcome,
        plots=_plots(out, result.history, before, after, baselines),
        wall_s=time.perf_counter() - t0,
    )
    write_atomic(out / "report.json", json.dumps(report.to_json(), indent=2))
    return report, 0 if outcome.error is None else 1


def export(
    out: Path,
    cfg: TuneConfig,
    servo,
    hybrid,
    rates,
    tuned,
    provenance: dict,
    machine: Machine | None = None,
    loads: dict[str, AxisLoad] | None = None,
) -> Export:
    """Write ``gains.yaml`` and the ROS 2 files if the gains pass every check, with each of ``loads``
    (:func:`pusupu_jax.machine_file.margin_loads` of the tuned paths; default the machine's at home), which the gain
    file's ``provenance`` records (``margin_loads_kg``: each slider's mass [kg]); the report's entries about them.

    All or nothing: every file's text is made (the gains checked, the joint names too) and every path checked before
    the first is written (:func:`pusupu_jax.files.write_files`), so that a refusal leaves the earlier files as they
    were.  ``gains_file`` names the gain file the report describes (path and sha256), or says that none was written
    and why, and which earlier ``gains.yaml`` (if any) was left as it was: a report never silently describes gains
    that are not in ``gains.yaml``.
    """
    gains_path = out / "gains.yaml"
    loads = loads or {"home": machine_file.axis_load(machine or Machine.default())}
    provenance = provenance | {"margin_loads_kg": {name: load.mass.tolist() for name, load in loads.items()}}
    try:
        margins = stability.check_loads(
            servo, hybrid, rates, cfg.mode, (cfg.pm_min, cfg.gm_min), loads, along="the tuned paths"
        ).margins()
        texts = {
            gains_path: gains.document(
                servo,
                hybrid,
                rates,
                mode=cfg.mode,
                tuned=tuned,
                provenance=provenance,
                floors=(cfg.pm_min, cfg.gm_min),
                machine=machine,
            )
        }
        texts |= {
            out / name: text
            for name, text in ros2.files(servo, cfg.mode, rates, source=str(gains_path), joints=cfg.ros_joints).items()
        }
        written = write_files(texts)
    except ParameterError as e:
        left = {"path": str(gains_path), "sha256": _sha256(gains_path)} if gains_path.is_file() else None
        return Export(
            gains.margins_report(servo, cfg.mode, machine),
            [],
            GainFileRef(None, not_written=str(e), left_as_it_was=left),
            error=str(e),
        )
    # the ROS files are written whatever ROS's PID keeps (docs/gains.md); the report says where it keeps less
    short = ros2.short_of_floors(servo, cfg.mode, machine or Machine.default(), (cfg.pm_min, cfg.gm_min))
    return Export(
        margins, [str(p) for p in written], GainFileRef(str(gains_path), _sha256(gains_path)), ros_warning=short
    )


def _sha256(path: Path) -> str:
    return hashlib.sha256(inputs.read_bytes(path, "gain file", ParameterError)).hexdigest()
