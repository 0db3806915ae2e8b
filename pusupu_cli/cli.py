"""The ``pusupu`` command's parser and ``main`` (host-side; an application of the core).  Each command's handler is
in its own module: ``analyze``, ``sim``, ``tuning`` (tune, batch), ``experiment``, ``gain_files`` (gains),
``machine``, ``bridge`` (bridge, sim-robot); ``common`` holds what they share.

    pusupu analyze [--params FILE] [--mode imc|pid|pid_ff] [--trajectory PATH] [--coupled] [--json] [--plot FIG]
    pusupu analyze --identify-T0 [--params FILE] [--kin-error SEED] [--json] [--plot FIG]
    pusupu sim --plant axis --trajectory step|ramp|sine [--mode imc|pid|pid_ff] [--params FILE]
               [--duration S] [--json] [--plot FIG]
    pusupu sim --plant mjx --trajectory arc|p2p|circle|tilt|FILE [--mode imc|pid|pid_ff|hybrid] [--params FILE]
               [--kin-error SEED] [--json] [--plot FIG]

    pusupu tune [--config FILE] [--out DIR] [--quick] [--fresh] [--json]
    pusupu batch JOB.yaml [--out DIR] [--ray [--address ADDR] [--workers N] [--cpus-per-task N]] [--fresh] [--json]
    (analyze and sim also take --gains FILE, a gain file written by tune; analyze, sim and tune
    take --imc-form full|printed, sim takes --start rest|zero)

Errors in the input print one line ``pusupu: error: ...`` and exit with status 2: a ParameterError, and a ValueError,
OverflowError or FloatingPointError raised while the inputs are read and checked (:func:`.common.checking`).  Any other
exception, or one raised in the work, is a bug and keeps its traceback.
"""

from __future__ import annotations

import argparse
import contextlib
import functools
import signal
import sys
import threading
import warnings

from pusupu_jax.cascade import AXIS_MODES, GAIN_FILE_MODES, Mode
from pusupu_jax.devices import DeviceChoice
from pusupu_jax.params import IMC_FORMS, ParameterError

from . import bridge as bridge_cli
from .analyze import cmd_analyze
from .common import say
from .experiment import cmd_experiment
from .gain_files import cmd_gains
from .identify import add_parser as add_identify_parser, cmd_identify
from .machine import cmd_machine
from .sim import cmd_sim
from .tuning import cmd_batch, cmd_tune


class _Parser(argparse.ArgumentParser):
    def error(self, message):
        _fail(message)


def _fail(message: str):
    say(f"pusupu: error: {message}")
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
        metavar="FIG",
        help="write Bode and step plots of axis 0 (with --identify-T0: the machine's step responses and their fits)",
    )
    a.add_argument(
        "--trajectory",
        metavar="NAME|FILE",
        help="analyse the loops also with the load each slider carries at the lightest and the heaviest pose along "
        "this path on the machine (arc|p2p|circle|tilt or a path file; docs/machine.md)",
    )
    a.add_argument(
        "--coupled",
        action="store_true",
        help="also the coupled linear model at the machine's home: the six cascades on the mechanism linearised "
        "there, each axis's loops broken in turn with the other five closed (docs/machine.md)",
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
    s.add_argument("--plot", metavar="FIG", help="write reference, error and current plots of axis 0")
    s.add_argument(
        "--log",
        metavar="MCAP",
        help="mjx: write the run as an MCAP log (Foxglove, PlotJuggler; docs/logs.md), as pusupu bridge --log does",
    )
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
    b.add_argument(
        "--cpus-per-task",
        type=int,
        metavar="N",
        help="CPUs (and XLA host devices) each Ray task asks for where the cluster has no GPU (default 1)",
    )
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
    g_check.add_argument(
        "--trajectory",
        action="append",
        default=[],
        metavar="PATH",
        help="also check the margins with the mass the sliders carry at the lightest and the heaviest pose along "
        "this path (repeatable; a named path or a path file)",
    )
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
    idn = add_identify_parser(sub)
    e = sub.add_parser("experiment", help="reproduce one of the paper's claims: runs, figures, JSON and a table")
    e.add_argument(
        "name",
        metavar="NAME",
        help="arc (Fig. 7), p2p (section 4, Table 2), hybrid_grid (hybrid "
        "stability across lambda2), timing (every step halved), servo "
        "(each loop: Bode, step, load-torque step, margins), tuned "
        "(Table 1 vs pusupu tune's gains on arc and p2p, every mode), "
        "peg_in_hole (Fig. 9a), surface_tracking (Fig. 9b) or loop_match (the "
        "MJX machine's loop gains against the single-axis and the coupled linear models)",
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
    for sp in (s, t, b, e, idn):
        sp.add_argument(
            "--device",
            choices=[str(d) for d in DeviceChoice],
            default=str(DeviceChoice.AUTO),
            help="where to compute: auto (the GPU only for work wide enough to run faster there, measured; "
            "docs/benchmarks.md), cpu (every core) or gpu (default auto)",
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
    # JAX warns for each program whose entry in the persistent compilation cache cannot be read or written, and
    # pusupu_jax.programs for each traced program it cannot keep beside them (a full disk, a read-only or over-quota
    # cache folder): dozens of lines before the command's own.  The programs are compiled or traced instead and the
    # results do not change; if the disk is full the command's own write fails too, and that error is the one line
    # it ends with.
    warnings.filterwarnings("ignore", message="Error (reading|writing) persistent compilation cache entry")
    warnings.filterwarnings("ignore", message="pusupu_jax.programs: could not keep")
    commands = {
        "analyze": cmd_analyze,
        "sim": cmd_sim,
        "tune": cmd_tune,
        "batch": cmd_batch,
        "experiment": cmd_experiment,
        "gains": cmd_gains,
        "machine": cmd_machine,
        "identify": cmd_identify,
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
        say(f"pusupu: interrupted{where}")
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


if __name__ == "__main__":
    sys.exit(main())
