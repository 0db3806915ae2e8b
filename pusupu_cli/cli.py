"""The ``pusupu`` command (host-side; an application of the core, like ``tune``, ``experiments`` and ``hw_bridge``).

    pusupu analyze [--params FILE] [--mode imc|pid|pid_ff] [--json] [--plot PNG]
    pusupu analyze --identify-T0 [--params FILE] [--kin-error SEED] [--json] [--plot PNG]
    pusupu sim --plant axis --trajectory step|ramp|sine [--mode imc|pid|pid_ff] [--params FILE]
               [--duration S] [--json] [--plot PNG]
    pusupu sim --plant mjx --trajectory arc|p2p|circle|tilt|FILE [--mode imc|pid|pid_ff|hybrid] [--params FILE]
               [--kin-error SEED] [--json] [--plot PNG]

    pusupu tune [--config FILE] [--out DIR] [--quick] [--fresh] [--json]
    pusupu batch JOB.yaml [--out DIR] [--ray [--address ADDR] [--workers N]] [--fresh] [--json]
    (analyze and sim also take --gains FILE, a gain file written by tune; analyze, sim and tune
    take --imc-form full|printed, sim takes --start rest|zero)

Errors in the input print one line ``pusupu: error: ...`` and exit with status 2: a ParameterError, and a ValueError,
OverflowError or FloatingPointError raised while the inputs are read and checked (:func:`_checking`).  Any other
exception, or one raised in the work, is a bug and keeps its traceback.
"""

from __future__ import annotations

import argparse
import contextlib
import functools
import json
import signal
import sys
import threading
import time
import warnings

import numpy as np

from pusupu_jax.cascade import AXIS_MODES, GAIN_FILE_MODES, Mode
from pusupu_jax.inputs import one_line
from pusupu_jax.metrics import Metric
from pusupu_jax.params import IMC_FORMS, N_AXES, ParameterError

from . import bridge as bridge_cli
from .common import check_plot_path, checking, machine_of


class _Parser(argparse.ArgumentParser):
    def error(self, message):
        _fail(message)


def _say(message: str) -> None:
    """Print ``message`` on stderr as one line (:func:`pusupu_jax.inputs.one_line`: escaped, cut): every error line
    of the command goes through here, so that no input is echoed raw or whole."""
    print(one_line(message), file=sys.stderr)


def _fail(message: str):
    _say(f"pusupu: error: {message}")
    sys.exit(2)


def _parser() -> argparse.ArgumentParser:
    p = _Parser(prog="pusupu", description="Servo cascade simulator and analysis for the 6PUS-UPU manipulator.")
    p.add_argument("--version", action="version", version=f"pusupu {_version()}")
    sub = p.add_subparsers(dest="command", required=True, parser_class=_Parser)
    a = sub.add_parser("analyze", help="crossover, margins and bandwidth of every loop of every axis")
    a.add_argument("--params", metavar="FILE", help="parameter YAML (default: Table 1 and documented choices)")
    a.add_argument(
        "--mode",
        choices=[str(m) for m in AXIS_MODES],
        default=str(Mode.IMC),
        help="position controller: 2-DOF IMC, PID, or PID with velocity feedforward (default imc)",
    )
    a.add_argument("--json", action="store_true", help="print JSON instead of a table")
    a.add_argument(
        "--plot",
        metavar="PNG",
        help="write Bode and step plots of axis 0 (with --identify-T0: the machine's step responses and their fits)",
    )
    a.add_argument(
        "--identify-T0",
        action="store_true",
        help="identify each branch's velocity-loop time constant T0 from velocity steps of the MJX "
        "machine (x and y platform motions from home) instead of the loop analysis",
    )
    a.add_argument(
        "--kin-error",
        type=_seed,
        metavar="SEED",
        help="with --identify-T0: the machine gets seeded kinematic errors (0.5 mm std)",
    )
    s = sub.add_parser("sim", help="simulate the cascade against a plant and print tracking metrics")
    s.add_argument(
        "--plant",
        choices=("axis", "mjx"),
        default="axis",
        help="axis: six single-axis plants; mjx: the 6PUS-UPU mechanism in MJX (default axis)",
    )
    s.add_argument(
        "--trajectory",
        metavar="NAME|FILE",
        help="step|ramp|sine for the axis plant (default step); for mjx (default arc) arc|p2p|circle|tilt "
        "or a path file: waypoints (.yaml, .yml) or a pose table (.csv) (docs/paths.md)",
    )
    s.add_argument(
        "--kin-error",
        type=_seed,
        metavar="SEED",
        help="mjx: the simulated machine gets seeded kinematic errors (0.5 mm std)",
    )
    s.add_argument(
        "--mode",
        choices=[str(m) for m in GAIN_FILE_MODES],
        default=str(Mode.IMC),
        help="imc, pid or pid_ff (PID with velocity feedforward) on every branch, or hybrid (mjx only: "
        "branches 1-5 IMC, branch 6 force control, eq. 10-14; gains from the params file's hybrid "
        "section) (default imc)",
    )
    s.add_argument(
        "--start",
        choices=("rest", "zero"),
        default="rest",
        help="rest: the machine held still by its drives at t = 0 (currents and integrators preloaded); "
        "zero: every controller state zero, so it sags until the integrators catch up (default rest)",
    )
    s.add_argument("--params", metavar="FILE", help="parameter YAML")
    s.add_argument("--duration", type=float, metavar="S", help="seconds (default per trajectory)")
    s.add_argument("--json", action="store_true", help="print JSON instead of a table")
    s.add_argument("--plot", metavar="PNG", help="write reference, error and current plots of axis 0")
    t = sub.add_parser("tune", help="the main job: tune the gains on the machine, export gains.yaml and a report")
    t.add_argument(
        "--config",
        metavar="FILE",
        help="tuning configuration YAML (default: the embedded one, see tune/config.py and docs/tuning.md)",
    )
    t.add_argument("--out", metavar="DIR", default="tune_out", help="output folder (default tune_out)")
    t.add_argument("--quick", action="store_true", help="a short smoke run (under 2 min): one path, 5 iterations")
    t.add_argument("--fresh", action="store_true", help="ignore (delete) a checkpoint in DIR instead of resuming")
    t.add_argument("--json", action="store_true", help="print the report as JSON instead of a table")
    b = sub.add_parser(
        "batch",
        help="tune many robots and scenarios from a job file: vmapped on one device, "
        "sharded over local devices, or as Ray tasks",
    )
    b.add_argument(
        "job", metavar="JOB.yaml", help="the job file (docs/batch.md, tune/schemas/pusupu-batch.schema.json)"
    )
    b.add_argument("--out", metavar="DIR", default="batch_out", help="output folder (default batch_out)")
    b.add_argument("--ray", action="store_true", help="run the shards as Ray tasks (the cluster extra)")
    b.add_argument("--address", metavar="ADDR", help="join this Ray cluster instead of starting a local one")
    b.add_argument("--workers", type=int, metavar="N", help="CPUs of the local Ray instance (default: all)")
    b.add_argument("--fresh", action="store_true", help="delete DIR's checkpoints and job results instead of resuming")
    b.add_argument("--json", action="store_true", help="print the summary as JSON instead of a table")
    g = sub.add_parser(
        "gains", help="read, compare, check or re-sign a gain file; export it for ROS 2 and see what ROS would run"
    )
    actions = g.add_subparsers(dest="action", required=True, parser_class=_Parser)
    g_show = actions.add_parser("show", help="the gains as a table: sections, values, units, what was tuned")
    g_show.add_argument("file", metavar="FILE")
    g_show.add_argument("--json", action="store_true", help="print the checked document as JSON")
    g_diff = actions.add_parser("diff", help="the values two gain files disagree on")
    g_diff.add_argument("file", metavar="FILE")
    g_diff.add_argument("other", metavar="OTHER")
    g_check = actions.add_parser("check", help="validate a gain file (exit 0 when it passes every check)")
    g_check.add_argument("file", metavar="FILE")
    g_sign = actions.add_parser("sign", help="re-sign a deliberately edited gain file once its gains validate")
    g_sign.add_argument("file", metavar="FILE")
    g_migrate = actions.add_parser(
        "migrate", help="rewrite a version 2 gain file as version 3 (its plant section must be the built-in plant)"
    )
    g_migrate.add_argument("file", metavar="FILE")
    g_migrate.add_argument("--out", metavar="FILE", help="write the version 3 file here (default: FILE, in place)")
    g_export = actions.add_parser(
        "export-ros", help="write the ROS 2 pid_controller and joint trajectory controller parameter files"
    )
    g_export.add_argument("file", metavar="FILE")
    g_export.add_argument("--out", metavar="DIR", default=".", help="output folder (default .)")
    g_export.add_argument(
        "--joints", metavar="J1,...,J6", help="the six slider joints' names (default slide_1,...,slide_6)"
    )
    g_ros = actions.add_parser(
        "check-ros",
        help="simulate what ROS's PID would run with the exported gains on the "
        "machine, beside the full pusupu controller",
    )
    g_ros.add_argument("file", metavar="FILE")
    g_ros.add_argument(
        "--trajectory",
        metavar="NAME|FILE",
        default="both",
        help="both (arc and p2p), a named path or a path file (docs/paths.md) (default both)",
    )
    g_ros.add_argument("--seconds", type=float, metavar="S", help="only the first S seconds of each path")
    g_ros.add_argument("--json", action="store_true", help="print JSON instead of a table")
    for sp in (g_show, g_diff, g_check, g_sign, g_migrate, g_export, g_ros):
        _floors_arguments(sp)
    m = sub.add_parser(
        "machine",
        help="write, check and describe a machine file: what the robot is (geometry, drives, friction, payload)",
    )
    m_actions = m.add_subparsers(dest="action", required=True, parser_class=_Parser)
    m_init = m_actions.add_parser("init", help="write the built-in machine as a commented template to edit")
    m_init.add_argument(
        "--out", metavar="FILE", default="machine.yaml", help="default machine.yaml (an existing file is not replaced)"
    )
    m_check = m_actions.add_parser("check", help="validate a machine file and its workspace (exit 0 when it passes)")
    m_check.add_argument("file", metavar="FILE")
    m_check.add_argument(
        "--trajectory",
        action="append",
        default=[],
        metavar="PATH",
        help="also check this path against the machine (repeatable; default arc and p2p)",
    )
    m_check.add_argument("--json", action="store_true", help="print the findings as JSON")
    m_actions.add_parser("schema", help="print the machine file's JSON Schema (for editors)")
    e = sub.add_parser("experiment", help="reproduce one of the paper's claims: runs, figures, JSON and a table")
    e.add_argument(
        "name",
        metavar="NAME",
        help="arc (Fig. 7), p2p (section 4, Table 2), hybrid_grid (hybrid "
        "stability across lambda2), timing (every step halved), servo "
        "(each loop: Bode, step, load-torque step, margins), tuned "
        "(Table 1 vs pusupu tune's gains on arc and p2p, every mode), "
        "peg_in_hole (Fig. 9a), surface_tracking (Fig. 9b) or loop_match (the "
        "MJX machine's loop gains against the linear model)",
    )
    e.add_argument("--out", metavar="DIR", default="experiments_out", help="output folder (default experiments_out)")
    e.add_argument("--quick", action="store_true", help="a short version (a few seconds of the paths, fewer seeds)")
    e.add_argument("--json", action="store_true", help="print the metrics as JSON instead of the table")
    e.add_argument(
        "--gains",
        metavar="FILE",
        help="servo and tuned only: a gain file written by pusupu tune, "
        "compared with Table 1 (tuned without it runs the tuner)",
    )
    for sp in (a, s):
        sp.add_argument(
            "--gains",
            metavar="FILE",
            help="a gain file written by pusupu tune (replaces the servo gains, hybrid gains and rates of --params)",
        )
        _floors_arguments(sp)
    t.add_argument(
        "--start-gains",
        metavar="FILE|table1|derived",
        help="where tuning starts: a gain file tuned on the same machine, Table 1, or gains derived for the "
        "machine by the paper's method (docs/machine.md); default table1 on the built-in machine, "
        "derived on any other",
    )
    for sp in (a, s, t, g_show, g_check, g_sign, g_export, g_ros, e):
        sp.add_argument(
            "--machine",
            metavar="FILE",
            help="the machine file (pusupu machine init; default: the "
            "built-in machine)" + ("; loop_match only" if sp is e else ""),
        )
    for sp in (a, s, t):
        sp.add_argument(
            "--imc-form",
            choices=IMC_FORMS,
            help="form of the IMC prefilter C1: full (reference response (3 l1 s+1)/(l1 s+1)^3, what "
            "section 2.2 describes) or printed (eq. 9 as printed); default: the params or gain "
            "file's servo.imc_form, else full (docs/imc.md)",
        )
    bridge_cli.add_parsers(sub)
    return p


def _seed(text: str) -> int:
    if not text.isdigit():
        raise argparse.ArgumentTypeError(f"expected a non-negative integer seed, got {text!r}")
    return int(text)


def _floors_arguments(parser):
    parser.add_argument(
        "--min-pm",
        type=float,
        metavar="DEG",
        help="accept gain files with at least DEG of phase margin instead of 45 (said on stderr)",
    )
    parser.add_argument(
        "--min-gm",
        type=float,
        metavar="DB",
        help="accept gain files with at least DB of gain margin instead of 6 (said on stderr)",
    )


def _floors(args):
    """The stability floors for loading gain files: 45 deg and 6 dB, or the user's explicit, logged override."""
    from pusupu_jax.gains import FLOORS

    floors = (FLOORS[0] if args.min_pm is None else args.min_pm, FLOORS[1] if args.min_gm is None else args.min_gm)
    if floors != FLOORS:
        import math

        if not all(math.isfinite(v) and v >= 0 for v in floors):
            raise ParameterError(f"--min-pm/--min-gm: expected finite non-negative margins, got {floors}")
        print(
            f"pusupu: accepting gain files down to {floors[0]:g} deg and {floors[1]:g} dB of margin (default "
            f"{FLOORS[0]:g} deg, {FLOORS[1]:g} dB)",
            file=sys.stderr,
        )
    return floors


def _version() -> str:
    from pusupu_jax import __version__

    return __version__


def main(argv=None) -> int:
    args = _parser().parse_args(argv)
    _file_backend()
    commands = {
        "analyze": _analyze,
        "sim": _sim,
        "tune": _tune,
        "batch": _batch,
        "experiment": _experiment,
        "gains": _gains,
        "machine": _machine_command,
        "bridge": bridge_cli.run_bridge,
        "sim-robot": bridge_cli.run_sim_robot,
    }
    try:
        args.floors = _floors(args) if hasattr(args, "min_pm") else None
        with _counted_interrupts() as interrupts:
            status = commands[args.command](args)
        if interrupts:  # a Ctrl-C whose KeyboardInterrupt Python dropped (see _counted_interrupts)
            raise KeyboardInterrupt
        return status
    except (ParameterError, FloatingPointError) as e:  # bad input; a tuning run that went non-finite
        _fail(str(e))
    except OSError as e:  # a full disk, a folder that vanished: the old files are intact (atomic writes)
        _fail(f"{e.filename + ': ' if e.filename else ''}{e.strerror or e}")
    except KeyboardInterrupt:
        kept = {"tune": "the checkpoint in {} keeps", "batch": "the checkpoints in {} keep"}.get(args.command)
        where = f" ({kept.format(args.out)} the run: the same command resumes it)" if kept else ""
        _say(f"pusupu: interrupted{where}")
        return 130


def _quiet_dropped_interrupt(hook, interrupts, unraisable) -> None:
    """Leave out Python's 'Exception ignored in ...' traceback for a dropped Ctrl-C that ``interrupts`` counted (the
    command ends with one line and 130); pass every other dropped exception on to ``hook``."""
    if not (interrupts and isinstance(unraisable.exc_value, KeyboardInterrupt)):
        hook(unraisable)


@contextlib.contextmanager
def _counted_interrupts():
    """Yield a list that counts Ctrl-C; each still raises KeyboardInterrupt, as Python's own handler does.

    Python drops an exception raised inside a garbage-collector callback (JAX registers one), so a
    Ctrl-C landing there was lost and the command ran on to exit 0; the count lets it end with 130
    once the command returns, and Python's report of the dropped exception is left out.  Where
    SIGINT is ignored or handled by someone else, or off the main thread, nothing changes.
    """
    seen = []
    if (
        threading.current_thread() is not threading.main_thread()
        or signal.getsignal(signal.SIGINT) is not signal.default_int_handler
    ):
        yield seen
        return

    def on_sigint(signum, frame):
        seen.append(signum)
        raise KeyboardInterrupt

    previous, unraisable = signal.signal(signal.SIGINT, on_sigint), sys.unraisablehook
    sys.unraisablehook = functools.partial(_quiet_dropped_interrupt, unraisable, seen)
    try:
        yield seen
    finally:
        signal.signal(signal.SIGINT, previous)
        sys.unraisablehook = unraisable


def _file_backend() -> None:
    """The command's figures are files: matplotlib's Agg backend (importing the packages leaves the backend alone)."""
    import matplotlib

    matplotlib.use("Agg")


def _tune(args) -> int:
    from pathlib import Path

    from pusupu_jax.runtime import setup_jax

    setup_jax()
    from pusupu_jax.tune.config import TuneConfig
    from pusupu_jax.tune.job import run_job, table

    if not args.out:
        raise ParameterError("--out: expected a folder, got an empty name")
    cfg = TuneConfig.quick() if args.quick else TuneConfig()
    if args.config:
        with checking(f"--config {args.config}"):
            cfg = TuneConfig.load(args.config, base=cfg)
    if args.imc_form:
        cfg = cfg.replace(imc_form=args.imc_form)
    out = Path(args.out)
    machine = machine_of(args)
    start = args.start_gains
    if start not in (None, "table1", "derived"):
        from pusupu_jax import gains

        with checking(f"--start-gains {start}"):
            start = gains.load(start, machine=machine)
    report, status = run_job(cfg, out, fresh=args.fresh, machine=machine, start=start)
    if args.json:
        print(json.dumps({k: v for k, v in report.items() if k != "history"}, indent=2))
    else:
        print(table(report))
        print(f"wrote: {', '.join(report['exported'] + report['plots'] + [str(out / 'report.json')])}")
    if status:
        _say(f"pusupu: error: {report['export_error']}")
    return status


def _batch(args) -> int:
    from pathlib import Path

    from pusupu_jax.runtime import setup_jax

    setup_jax()
    from pusupu_jax.tune.batchjob import run_batch

    if (args.address or args.workers) and not args.ray:
        raise ParameterError("--address and --workers need --ray")
    if args.workers is not None and args.workers < 1:
        raise ParameterError(f"--workers: expected a positive number of CPUs, got {args.workers}")
    summary, status = run_batch(
        args.job, args.out, ray=args.ray, address=args.address, workers=args.workers, fresh=args.fresh
    )
    if args.json:
        print(json.dumps(summary, indent=2))
    else:
        print(Path(args.out, "summary.md").read_text(), end="")
        print(
            f"{summary['ok']} of {summary['jobs']} job(s) exported gains; wrote {args.out}/summary.csv, "
            f"summary.md, summary.json, summary.png and jobs/<job>/"
        )
    for name in summary["failed"]:
        row = next(r for r in summary["rows"] if r["job"] == name)
        _say(f"pusupu: job {name}: {row['status']}: {row['error']}")
    return status


def _experiment(args) -> int:
    from pathlib import Path

    from pusupu_jax.runtime import setup_jax

    out = Path(args.out)
    if out.exists() and not out.is_dir():
        raise ParameterError(f"--out: expected a folder, got the file {args.out!r}")
    setup_jax()
    from pusupu_jax import experiments

    experiments.get(args.name)  # an unknown name fails before any work
    with checking(f"--gains {args.gains}"):  # refused for another experiment, or a bad file: before any work
        g = experiments.gain_file(args.name, args.gains)
    machine = machine_of(args) if args.machine else None
    experiments.check_machine(args.name, machine)
    print(
        f"experiment {args.name}{' (quick)' if args.quick else ''}: running (the first runs compile for about "
        "20 s per control mode)",
        file=sys.stderr,
        flush=True,
    )
    t0 = time.perf_counter()
    result, files = experiments.run_experiment(args.name, out, quick=args.quick, gains=g, machine=machine)
    if args.json:
        print(json.dumps(result.metrics, indent=2))
    else:
        print(experiments.get(args.name).table(result))
        print(f"wrote: {', '.join(str(f) for f in files)} ({time.perf_counter() - t0:.0f} s)")
    return 0


def _load(args, check: bool = True):
    """The params file (or defaults) with a gain file's gains and rates in place, on the machine of ``--machine``,
    checked by :func:`pusupu_jax.stability.check` for ``args.mode`` (``check=False``: bounds only, for a diagnosis).
    With ``--machine``, the params file may set controller fields only: the drives are the machine's."""
    from pathlib import Path

    from pusupu_jax import machine_file, stability
    from pusupu_jax.files import read_yaml_mapping
    from pusupu_jax.params_file import SECTIONS, load_params_file
    from pusupu_jax.runtime import setup_jax

    setup_jax()  # the checks' compiled programs come from the persistent cache after the first run
    machine = machine_of(args)
    with checking(f"--params {args.params}" if args.params else "the default parameters"):
        loaded = load_params_file(args.params)
        sections = read_yaml_mapping(Path(args.params), "section", SECTIONS) if args.params else {}
        # the linear model's load: a params file's load section, else the machine's (machine_file.axis_load)
        args.linear_load = loaded.load if sections.get("load") else machine_file.axis_load(machine)
        if args.machine:
            servo = sections.get("servo") or {}
            clash = [name for name in servo if name in machine.drives]
            if clash:
                raise ParameterError(
                    f"--params {args.params}: servo.{clash[0]}: expected controller fields only with "
                    f"--machine (the drives are the machine file's), got the drive field {clash[0]}"
                )
    if getattr(args, "gains", None):
        from pusupu_jax import gains

        with checking(f"--gains {args.gains}"):
            g = gains.load(args.gains, args.floors, check_stability=False, machine=machine)
        loaded = loaded._replace(servo=g.servo, hybrid=g.hybrid, rates=g.rates)
    elif args.machine and not args.params and not machine_file.is_builtin(machine):
        from pusupu_jax.start_gains import derive

        print(
            f"pusupu: no --gains: the start gains derived for machine {machine.name!r} (docs/machine.md; T0 "
            "identified on the MJX machine, about 30 s)",
            file=sys.stderr,
            flush=True,
        )
        with checking(f"--machine {args.machine}"):
            loaded = loaded._replace(servo=derive(machine, loaded.rates)[0])
    with checking(f"--machine {args.machine}" if args.machine else "the built-in machine"):
        loaded = loaded._replace(servo=machine.servo(loaded.servo))
    if args.imc_form:
        loaded = loaded._replace(servo=loaded.servo.replace(imc_form=args.imc_form))
    if check:
        try:
            stability.check(loaded.servo, loaded.hybrid, loaded.rates, args.mode, args.floors, load=args.linear_load)
        except ParameterError as e:
            raise ParameterError(f"{args.gains or args.params or 'the defaults'}: {e}") from None
    else:
        stability.check_values(loaded.servo, loaded.hybrid, loaded.rates)
    return loaded


def _machine_command(args) -> int:
    from pathlib import Path

    from pusupu_jax import machine_file

    if args.action == "schema":
        print(machine_file.schema_text(), end="")
        return 0
    if args.action == "init":
        from pusupu_jax.files import write_atomic

        out = Path(args.out)
        if out.exists() or out.is_symlink():
            raise ParameterError(f"--out {args.out}: expected a new file, found one there (left as it is)")
        write_atomic(out, machine_file.template())
        print(f"wrote {out}: the built-in machine, every field commented; edit it, then pusupu machine check {out}")
        return 0
    from pusupu_jax.runtime import setup_jax

    setup_jax()
    args.machine = args.file
    machine = machine_of(args)
    from pusupu_jax.params import LoopRates
    from pusupu_jax.paths import check_path, platform_path_from

    paths = []
    for name in args.trajectory or ["arc", "p2p"]:
        with checking(f"--trajectory {name}"):
            paths.append((name, platform_path_from(name, machine.geometry.home, LoopRates())))
    from pusupu_jax.start_gains import derive

    with checking(args.file):
        found = machine_file.check(machine, paths)
        servo, report = derive(machine, identify=False)  # the drives' limits: speed_max, Kt I_peak
        for name, poses in paths:
            check_path(
                poses,
                servo,
                LoopRates().dt_position,
                geom=machine.geometry,
                options=machine.options(),
                where=f"--trajectory {name}",
            )
    mass = np.asarray(report["carried_mass_kg"])
    result = {
        "file": args.file,
        "name": machine.name,
        "digest": machine_file.digest(machine),
        "carried_mass_kg": mass.tolist(),
        "workspace": found,
    }
    if args.json:
        print(json.dumps(result, indent=2))
        return 0
    print(
        f"{args.file}: valid {machine_file.FORMAT} v{machine_file.VERSION}, machine {machine.name!r} "
        f"(digest {result['digest'][:12]})"
    )
    for name, extremes in found.items():
        lo, hi = min(extremes["slider_min_m"]), max(extremes["slider_max_m"])
        print(
            f"  {name:<12} sliders {lo * 1e3:.1f} to {hi * 1e3:.1f} mm, Jacobian condition number at most "
            f"{extremes['cond_max']:.3g} (limit {machine_file.COND_MAX:g}), "
            f"UPU leg {extremes['upu_leg_m'][0] * 1e3:.0f} to {extremes['upu_leg_m'][1] * 1e3:.0f} mm"
        )
    print(f"  mass each slider carries at home: {', '.join(f'{m:.1f}' for m in mass)} kg")
    return 0


def _gains(args) -> int:
    from pathlib import Path

    from pusupu_jax import gains
    from pusupu_jax.runtime import setup_jax

    setup_jax()  # the checks' compiled programs come from the persistent cache after the first run
    floors = args.floors
    machine = machine_of(args) if hasattr(args, "machine") else None
    if args.action == "sign":  # the checks of load() less the checksum, then the derived blocks written anew
        with checking(args.file):
            gains.sign(args.file, floors, machine)
        print(f"{args.file}: its gains pass every check on machine {machine.name!r}; re-signed")
        return 0
    if args.action == "migrate":
        with checking(args.file):
            path = gains.migrate(args.file, args.out, floors)
        print(f"{path}: {gains.SCHEMA} v{gains.VERSION}, migrated (tuned on the built-in machine)")
        return 0
    with checking(args.file):
        g = gains.load(args.file, floors, machine=machine)
    if args.action == "show":
        print(json.dumps(g.document, indent=2) if args.json else gains.show(g.document))
    elif args.action == "diff":
        with checking(args.other):
            other = gains.load(args.other, floors)
        lines = gains.diff(g.document, other.document)
        print("\n".join(lines) if lines else "no difference in gains, rates or mode")
    elif args.action == "check":
        from pusupu_jax import machine_file

        print(
            f"{args.file}: valid {gains.SCHEMA} v{g.document['version']}, mode {g.mode}, tuned on machine "
            f"{g.machine['name']!r} (digest {g.machine['digest'][:12]}); on machine {machine.name!r} (digest "
            f"{machine_file.digest(machine)[:12]}) every loop is stable at the file's rates and has at least "
            f"{floors[0]:g} deg and {floors[1]:g} dB"
        )
        if not g.tuned_on(machine):
            _say(
                f"pusupu: warning: {args.file} was tuned on another machine ({g.machine['name']!r}) than "
                f"{machine.name!r}"
            )
    elif args.action == "export-ros":
        from pusupu_jax import ros2

        joints = ros2.JOINTS if not args.joints else tuple(args.joints.split(","))
        out = Path(args.out)
        if not out.is_dir():
            raise ParameterError(f"--out: expected an existing folder, got {args.out!r}")
        for path in ros2.write_files(out, g.servo, g.mode, g.rates, source=args.file, joints=joints):
            print(f"wrote {path}")
    else:
        return _check_ros(args, g)
    return 0


def _check_ros(args, g) -> int:
    from pusupu_jax.runtime import setup_jax

    setup_jax()
    from pusupu_jax import gains, inputs, paths, ros2, workload
    from pusupu_jax.cascade import control_mode
    from pusupu_jax.machine import Scenario, machine_rates, simulate_scenarios

    kinds = ("arc", "p2p") if args.trajectory == "both" else (paths.check_spec(args.trajectory, "--trajectory"),)
    if args.seconds is not None:
        inputs.number(args.seconds, "--seconds", ParameterError, low=0.0, low_open=True)
    seconds = sum(
        paths.path_seconds(k) if args.seconds is None else min(args.seconds, paths.path_seconds(k)) for k in kinds
    )
    workload.check_run(
        f"gains check-ros ({' and '.join(kinds)}, two controllers)",
        2 * seconds,
        machine_rates(rates=g.rates),
        machine=True,
    )
    machine = machine_of(args)
    poses = {k: paths.platform_path_from(k, machine.geometry.home, g.rates) for k in kinds}
    if args.seconds is not None:
        poses = {k: p[: max(3, int(args.seconds / g.rates.dt_position))] for k, p in poses.items()}
    for k, p in poses.items():
        paths.check_path(
            p, g.servo, g.rates.dt_position, geom=machine.geometry, options=machine.options(), where=f"--trajectory {k}"
        )
    scenarios = [
        Scenario(p, machine.options(), name=paths.path_label(k), geometry=machine.geometry) for k, p in poses.items()
    ]
    print(
        f"simulating {', '.join(kinds)} with the full pusupu controller ({g.mode}) and with what ROS's PID runs "
        "(two compiles of about 20 s)",
        file=sys.stderr,
    )
    ros_servo = ros2.as_ros_servo(g.servo, g.mode)
    runs = {
        "pusupu": simulate_scenarios(
            g.servo, scenarios, mode=g.mode, rates=g.rates, hybrid=g.hybrid if control_mode(g.mode).hybrid else None
        ),
        "ros": simulate_scenarios(ros_servo, scenarios, mode=Mode.ROS_PID, rates=g.rates),
    }
    margins = {
        "pusupu": gains.margins_report(g.servo, g.mode, machine),
        "ros": gains.margins_report(ros_servo, Mode.ROS_PID, machine),
    }
    result = {
        "mode": g.mode,
        "ros_gains": {k: v.tolist() for k, v in ros2.ros_gains(g.servo, g.mode).items()},
        "paths": {},
        "position_margins": {},
    }
    for who in runs:
        for sc, (r, _) in zip(scenarios, runs[who]):
            result["paths"].setdefault(sc.name, {})[who] = {
                k: r[k] for k in (Metric.RMS_TRACKING_ERROR_MM, Metric.MAX_TRACKING_ERROR_MM)
            } | {"highest_branch_force_peak_n": max(r[Metric.BRANCH_FORCE_PEAK_N])}
        m = margins[who]["position"]
        result["position_margins"][who] = {
            "phase_margin_deg": float(min(m["phase_margin_deg"])),
            "gain_margin_db": float(min(m["gain_margin_db"])),
        }
    if args.json:
        print(json.dumps(result, indent=2))
        return 0
    print(f"{'path':<6} {'metric':<28} {'pusupu (' + g.mode + ')':>18} {'ROS PID':>12}")
    for name, per in result["paths"].items():
        for key in (Metric.RMS_TRACKING_ERROR_MM, Metric.MAX_TRACKING_ERROR_MM, "highest_branch_force_peak_n"):
            print(f"{name:<6} {key:<28} {per['pusupu'][key]:>18.4g} {per['ros'][key]:>12.4g}")
    for key in ("phase_margin_deg", "gain_margin_db"):
        print(
            f"{'':<6} {'position loop ' + key:<28} {result['position_margins']['pusupu'][key]:>18.4g} "
            f"{result['position_margins']['ros'][key]:>12.4g}"
        )
    return 0


def _analyze(args) -> int:
    from pusupu_jax import analysis

    servo, _, rates, hybrid = _load(args, check=False)  # analysed as a diagnosis, then checked
    load = args.linear_load  # the machine's (or the params file's load section)
    if args.plot:
        check_plot_path(args.plot)
    if args.identify_T0:
        return _identify(args, servo, load, rates)
    if args.kin_error is not None:
        raise ParameterError("--kin-error: only with --identify-T0 (the loop analysis uses the single-axis load)")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        # the check of the values: every axis's closed loops can be built (0.1 s), with numpy's overflow, invalid and
        # divide-by-zero raising; what python-control or numpy cannot use ends in one line here, not in the analysis
        with (
            checking(
                " and ".join(f"--{k} {getattr(args, k)}" for k in ("params", "gains") if getattr(args, k)) or "Table 1"
            ),
            np.errstate(over="raise", invalid="raise", divide="raise"),
        ):
            for axis in range(N_AXES):
                analysis.closed_loops(servo, load, axis, mode=args.mode)
        result = analysis.loop_metrics(servo, load, args.mode)
        if args.plot:
            from pusupu_jax.plots import plot_loops

            plot_loops(servo, load, args.plot, mode=args.mode)
    if args.json:
        print(json.dumps(result, indent=2))
        return _refuse_unstable(args, servo, hybrid, rates, load)
    print(f"position mode: {args.mode}")
    cols = [
        ("crossover_hz", "crossover Hz", 13),
        ("phase_margin_deg", "PM deg", 8),
        ("gain_margin_db", "GM dB", 8),
        ("bandwidth_hz", "bandwidth Hz", 13),
        ("rise_time_s", "rise s", 9),
        ("settling_time_s", "settle s", 9),
        ("overshoot_pct", "overshoot %", 12),
    ]
    print(f"{'axis':>4} {'loop':<9} " + " ".join(f"{title:>{w}}" for _, title, w in cols))
    for k, row in enumerate(result["axes"]):
        for name, m in row.items():
            print(f"{k:>4} {name:<9} " + " ".join(f"{_num(m[key]):>{w}}" for key, _, w in cols))
    if args.plot:
        print(f"plot: {args.plot}")
    return _refuse_unstable(args, servo, hybrid, rates, load)


def _refuse_unstable(args, servo, hybrid, rates, load) -> int:
    """After ``analyze`` printed its diagnosis: 0 if the gains pass :func:`pusupu_jax.stability.check`, else its
    reason on stderr and 2."""
    from pusupu_jax import stability

    problem = stability.check(servo, hybrid, rates, args.mode, args.floors, raise_error=False, load=load).problem()
    if problem is None:
        return 0
    print(f"pusupu: error: gains: {problem}", file=sys.stderr)
    return 2


def _identify(args, servo, load, rates) -> int:
    import numpy as np

    from pusupu_jax.runtime import setup_jax

    setup_jax()
    from pusupu_jax.analysis import identify_T0
    from pusupu_jax.identify import identify_T0_machine
    from pusupu_jax.plant.model import ModelOptions

    print(
        "identifying T0 on the MJX machine (velocity steps along x and y from home); the first run compiles "
        "for about 20 s",
        file=sys.stderr,
    )
    machine = machine_of(args)
    result = identify_T0_machine(
        servo, machine.options(ModelOptions(kin_error_seed=args.kin_error)), rates=rates, geom=machine.geometry
    )
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        axis_model = identify_T0(servo, load)
    out = {
        "T0_s": result["T0"],
        "fit_rms_rad_s": result["fit_rms"],
        "directions": result["directions"],
        "T0_servo_s": np.asarray(servo.T0).tolist(),
        "T0_axis_model_s": axis_model,
        "kin_error_seed": args.kin_error,
    }
    if args.plot:
        from pusupu_jax.plots import plot_identification

        plot_identification(
            result,
            args.plot,
            title="velocity steps of the machine"
            + (f", kinematic errors seed {args.kin_error}" if args.kin_error is not None else ""),
        )
    if args.json:
        print(json.dumps(out, indent=2))
        return 0
    print(
        f"T0 identified on the machine (velocity steps along {', '.join(result['directions'])} from home); "
        f"single-axis model: {axis_model * 1e3:.2f} ms"
    )
    print(f"{'branch':>6} {'T0 ms':>8} {'servo T0 ms':>12} {'fit rms rad/s':>14}")
    for b in range(6):
        print(
            f"{b + 1:>6} {result['T0'][b] * 1e3:>8.2f} {out['T0_servo_s'][b] * 1e3:>12.2f} "
            f"{result['fit_rms'][b]:>14.3g}"
        )
    if args.plot:
        print(f"plot: {args.plot}")
    return 0


def _num(x, none="inf"):
    """A table cell: 4 significant digits; ``none`` where the value is None (infinite margin, unsettled step)."""
    return none if x is None else f"{x:.4g}"


def _sim(args) -> int:
    from pusupu_jax.runtime import setup_jax

    axis_kinds = ("step", "ramp", "sine")
    args.trajectory = args.trajectory or ("step" if args.plant == "axis" else "arc")
    if args.plant == "axis" and args.trajectory not in axis_kinds:
        raise ParameterError(f"--trajectory: expected one of {axis_kinds} with --plant axis, got {args.trajectory!r}")
    if args.plant == "axis" and args.kin_error is not None:
        raise ParameterError("--kin-error: only the mjx plant has kinematic errors")
    servo, load, rates, hybrid = _load(args)
    if args.plot:
        check_plot_path(args.plot)
    setup_jax()
    if args.plant == "mjx":
        return _sim_machine(args, servo, rates, hybrid)
    from pusupu_jax.cascade import control_mode

    if control_mode(args.mode).hybrid:
        raise ParameterError("--mode hybrid: needs the mechanism (--plant mjx); the axis plant has no redundant branch")
    import jax

    from pusupu_jax import metrics
    from pusupu_jax.sim import simulate
    from pusupu_jax.trajectories import axis_reference

    ref = axis_reference(args.trajectory, rates, args.duration)
    t0 = time.perf_counter()
    trace = jax.block_until_ready(simulate(servo, ref, load=load, rates=rates, mode=args.mode, start=args.start))
    wall = time.perf_counter() - t0
    result = {
        "plant": args.plant,
        "trajectory": args.trajectory,
        "mode": args.mode,
        "imc_form": servo.imc_form,
        "start": args.start,
        "duration_s": float(trace.t[-1] + rates.dt_position),
        "wall_s": wall,
        **metrics.summary(trace, servo),
    }
    if args.trajectory == "step":
        result |= metrics.step_summary(trace, servo)
    if args.plot:
        from pusupu_jax.plots import plot_trace

        plot_trace(trace, servo, args.plot, title=f"{args.trajectory}, {args.mode} mode, axis 0")
    if args.json:
        print(json.dumps(result, indent=2))
        return 0
    print(
        f"{args.trajectory} on the {args.plant} plant, {args.mode} mode (IMC form {servo.imc_form}, start "
        f"{args.start}), {result['duration_s']:.3g} s "
        f"simulated in {wall:.2f} s (compile included)"
    )
    keys = [k for k in result if isinstance(result[k], list)]
    print(f"{'axis':>4} " + " ".join(f"{k:>16}" for k in keys))
    for a in range(len(result[keys[0]])):
        print(f"{a:>4} " + " ".join(f"{_num(result[k][a], 'not settled'):>16}" for k in keys))
    if args.plot:
        print(f"plot: {args.plot}")
    return 0


def _sim_machine(args, servo, rates, hybrid) -> int:
    from pusupu_jax import workload
    from pusupu_jax.machine import machine_rates, simulate_machine
    from pusupu_jax.paths import check_path, check_spec, path_seconds, platform_path_from
    from pusupu_jax.plant.model import ModelOptions

    check_spec(args.trajectory, "--trajectory with --plant mjx")
    if args.duration is not None:
        raise ParameterError("--duration: the mjx paths have their own timing (velocity and acceleration limits)")
    machine = machine_of(args)
    options = machine.options(ModelOptions(kin_error_seed=args.kin_error))
    workload.check_run(
        f"--trajectory {args.trajectory}", path_seconds(args.trajectory), machine_rates(options, rates), machine=True
    )
    path = platform_path_from(args.trajectory, machine.geometry.home, rates)
    check_path(
        path, servo, rates.dt_position, geom=machine.geometry, options=options, where=f"--trajectory {args.trajectory}"
    )
    print(
        f"simulating {len(path) * rates.dt_position:.1f} s of the {args.trajectory} path on the MJX machine "
        f"({args.mode} mode); the first run compiles for about 15 s",
        file=sys.stderr,
    )
    result, trace = simulate_machine(
        servo,
        path,
        mode=args.mode,
        options=options,
        rates=rates,
        hybrid=hybrid,
        start=args.start,
        geom=machine.geometry,
    )
    result = {"plant": "mjx", "trajectory": args.trajectory} | result
    if args.plot:
        from pusupu_jax.plots import plot_platform_path

        plot_platform_path(
            trace,
            args.plot,
            title=f"{args.trajectory}, {args.mode} mode"
            + (f", kinematic errors seed {args.kin_error}" if args.kin_error is not None else ""),
        )
    if args.json:
        print(json.dumps(result, indent=2))
        return 0
    print(
        f"{args.trajectory} on the MJX machine {machine_of(args).name!r}, {args.mode} mode "
        f"(IMC form {servo.imc_form}, start {args.start}), "
        f"{result['duration_s']:.3g} s simulated "
        f"in {result['wall_s']:.2f} s (compile included)"
    )
    for key in (
        Metric.RMS_TRACKING_ERROR_MM,
        Metric.MAX_TRACKING_ERROR_MM,
        Metric.SYNC_ERROR_RHO,
        Metric.LOOP_CLOSURE_RESIDUAL_MAX_MM,
    ):
        print(f"  {key:<30} {_num(result[key])}")
    for key, value in result.get("hybrid", {}).items():
        print(f"  hybrid {key:<23} {value if isinstance(value, str) else _num(value)}")
    keys = (
        Metric.BRANCH_RMS_ERROR_MM,
        Metric.BRANCH_REVERSAL_ERROR_MM,
        Metric.MOTOR_TORQUE_PEAK_NM,
        Metric.BRANCH_FORCE_PEAK_N,
    )
    print(f"{'branch':>6} " + " ".join(f"{k:>24}" for k in keys))
    for b in range(6):  # a branch whose reference never reverses: no reversal error
        print(f"{b + 1:>6} " + " ".join(f"{_num(result[k][b], none='-'):>24}" for k in keys))
    if args.plot:
        print(f"plot: {args.plot}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
