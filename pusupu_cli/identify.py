"""``pusupu identify``: the machine file's drive fields (friction, rotor inertia, torque constant) and payload fitted
to run logs."""

from __future__ import annotations

import json
import sys
from typing import TYPE_CHECKING

from pusupu_jax.params import ParameterError

from .common import check_output_path, check_plot_path, checking, machine_of

if TYPE_CHECKING:
    from pusupu_jax.machine_fit import FitReport


def add_parser(sub):
    """The ``identify`` subcommand's parser (``--device`` is added with the other computing commands')."""
    i = sub.add_parser(
        "identify",
        help="fit the machine file's drive friction, rotor inertia, torque constant or payload to run logs (MCAP of "
        "pusupu sim --log or bridge --log, or CSV drive tables)",
    )
    i.add_argument("logs", nargs="+", metavar="LOG", help="MCAP run logs, or CSV drive tables (.csv; docs/logs.md)")
    i.add_argument("--machine", metavar="FILE", help="the machine file to start from (default the built-in machine)")
    i.add_argument(
        "--gains", metavar="FILE", help="the gain file the logged runs used (default the built-in start gains)"
    )
    i.add_argument(
        "--fit",
        default="friction",
        metavar="NAMES",
        help="comma-separated fields to fit: per axis coulomb, viscous, J (rotor inertia), Kt (torque constant, and "
        "Ke in the machine file's ratio to it: needs logs with currents); payload_mass, payload_com; the groups "
        "friction (coulomb,viscous), motor (J,Kt) and payload (payload_mass,payload_com) (default friction)",
    )
    i.add_argument(
        "--window",
        type=float,
        metavar="S",
        help="replay each log's first S seconds from rest at the path's start (default 2: the excitation path's "
        "motion)",
    )
    i.add_argument("--trajectory", metavar="NAME|FILE", help="the path the logs ran, where not the one they name")
    i.add_argument(
        "--mech-step",
        type=float,
        metavar="S",
        help="the replay's mechanical step: 0.00005 (one a current-loop tick: closer to the robot, 5x the time) or "
        "0.00025 (default: the model's, as tune steps it)",
    )
    i.add_argument(
        "--step-check",
        metavar="S|none",
        help="replay the fitted values at this finer step [s] and move them by one Gauss-Newton step on its "
        "residual, the values (and standard errors) a fit at that step would find, for two replays at it; none: no "
        "check (default: 0.00005, one step a current-loop tick, for a robot's logs, bridge or CSV; none where every "
        "log is pusupu sim's, the model's own at its step)",
    )
    i.add_argument(
        "--derivatives",
        default="exact",
        choices=("exact", "mujoco-minimize", "finite-differences"),
        help="the solver and its Jacobian: exact (default: scipy's trust-region solver on the exact Jacobian through "
        "the replay), mujoco-minimize (MuJoCo's mujoco.minimize on forward differences, each Jacobian's replays as "
        "one batch), finite-differences (scipy's solver on its own differences, one replay after another)",
    )
    i.add_argument("--out", required=True, metavar="FILE", help="the identified machine file to write")
    i.add_argument(
        "--plot", metavar="FIG", help="write the logged currents (or torques) against the replay's, before and after"
    )
    i.add_argument("--json", action="store_true", help="print the report as JSON")
    return i


def cmd_identify(args) -> int:
    import numpy as np
    import yaml

    from pusupu_jax import drive_table, machine_file, machine_fit, run_log
    from pusupu_jax.files import write_atomic
    from pusupu_jax.params import LoopRates, ServoParams
    from pusupu_jax.runtime import setup_jax

    from pusupu_jax import devices

    devices.choose(args.device, len(args.logs), "log replay(s), one after another")
    fields = machine_fit.fit_fields(args.fit)
    if args.window is None:
        args.window = machine_fit.WINDOW_S
    if not (np.isfinite(args.window) and args.window > 0):
        raise ParameterError(f"--window: expected a positive number of seconds, got {args.window}")
    machine_fit.check_mech_step(args.mech_step, name="--mech-step")
    step_check = _step_check_option(args.step_check)
    if step_check is not None:
        machine_fit.check_step_check(step_check, args.mech_step, name="--step-check")
    check_output_path(args.out, "--out", "machine")
    if args.plot is not None:
        check_plot_path(args.plot)
    logs = []
    for path in args.logs:  # read and checked before any line of progress
        with checking(path):
            logs.append((drive_table.read if path.lower().endswith(".csv") else run_log.drive_log)(path))
            machine_fit.check_log(logs[-1], args.trajectory, "--trajectory")
    setup_jax()
    machine = machine_of(args)
    gains, hybrid, rates = ServoParams.table1(), None, LoopRates()
    if args.gains:
        from pusupu_jax import gains as gain_files

        with checking(f"--gains {args.gains}"):
            g = gain_files.load(args.gains, check_stability=False, machine=machine)
        gains, hybrid, rates = g.servo, g.hybrid, g.rates
        for log in logs:
            if log.gain_checksum and log.gain_checksum != g.document["checksum"]:
                raise ParameterError(
                    f"{log.path}: ran with the gain file of checksum {log.gain_checksum[:12]}, expected --gains "
                    f"{args.gains}'s {g.document['checksum'][:12]}"
                )
    if args.step_check is None:
        choice = machine_fit.default_step_check(logs, args.mech_step, rates)
        step_check = choice.step
        taken = "none" if step_check is None else f"at {step_check * 1e6:g} us"
        print(f"identify: step check {taken}: {choice.why} (--step-check sets it)", file=sys.stderr)
    devices.announce()
    with checking(f"--machine {args.machine}" if args.machine else "the built-in machine"):
        report, identified, plots = machine_fit.fit(
            logs,
            machine,
            gains,
            hybrid,
            rates,
            fields,
            args.window,
            args.trajectory,
            progress=lambda line: print(line, file=sys.stderr, flush=True),
            derivatives=machine_fit.Derivatives(args.derivatives),
            mech_step=args.mech_step,
            step_check=step_check,
        )
    checked = _step_check_words(report)
    header = [
        f"# identified by pusupu identify from {machine.name!r}: {', '.join(map(str, fields))} fitted to "
        f"{len(logs)} log(s), the first {args.window:g} s of each, replayed at a {report.mech_step_s * 1e6:g} us step",
        *(f"#   log {d['path']} sha256 {d['sha256']}" for d in report.logs),
        f"#   residual RMS {report.residual_rms_before:.4g} -> {report.residual_rms_after:.4g} over "
        f"{report.samples} samples",
        *([] if checked is None else [f"#   {checked}"]),
        *(
            f"#   {v.name} not excited by the logs: kept at {v.start:g} {machine_fit.UNITS[v.field]}"
            for v in report.unexcited()
        ),
    ]
    text = "\n".join(header) + "\n" + machine_file.template(identified)
    with checking(f"the identified machine for --out {args.out}"):  # what is written loads: never a refused file
        machine_file.parse(yaml.safe_load(text))
    write_atomic(args.out, text)
    if args.plot:
        from pusupu_jax.plots import plot_drive_fit

        plot_drive_fit(plots, args.plot)
    if args.json:
        print(json.dumps(report.as_dict() | {"out": args.out}, indent=2))
        return 0
    print(
        f"identify: residual RMS {report.residual_rms_before:.4g} -> {report.residual_rms_after:.4g} over "
        f"{report.samples} samples of {len(logs)} log(s) ({report.evaluations} evaluations, {report.wall_s:.0f} s)"
    )
    if checked is not None:
        print(f"identify: {checked} ({report.step_check_wall_s:.0f} s)")
    step = "" if checked is None else f" {'step move':>10}"
    print(f"{'value':<15} {'start':>10} {'fitted':>10} {'std error':>10}{step}  unit")
    for v in report.values:
        note = "" if v.excited else "  not excited: kept"
        moved = "" if checked is None else f" {v.step_correction:>10.2g}"
        print(
            f"{v.name:<15} {v.start:>10.4g} {v.value:>10.4g} {v.std_error:>10.2g}{moved}  "
            f"{machine_fit.UNITS[v.field]}{note}"
        )
    print(f"std errors count the residual's correlation in time over {report.error_bandwidth} samples")
    strongest = machine_fit.strongest_correlations(report.values, report.correlation)
    if strongest:
        print(
            "correlated (drawn together by tune's draws): "
            + ", ".join(f"{a} and {b} {r:+.2f}" for a, b, r in strongest)
        )
    if not report.converged:
        print(
            f"pusupu: warning: the fit stopped after {report.evaluations} evaluations without converging "
            f"({report.solver_message}); the values with large standard errors are loosely determined by these logs",
            file=sys.stderr,
        )
    for v in report.unexcited():
        print(f"pusupu: warning: {v.name} was not excited by the logs; kept at {v.start:g}", file=sys.stderr)
    print(f"wrote {args.out}" + (f", {args.plot}" if args.plot else ""))
    return 0


def _step_check_option(text: str | None) -> float | None:
    """``--step-check``'s step [s]: None for ``none`` or where not given (the default is chosen from the logs,
    :func:`pusupu_jax.machine_fit.default_step_check`); a ParameterError in one line for anything but a number."""
    if text is None or text.strip().lower() == "none":
        return None
    try:
        return float(text)
    except ValueError:
        raise ParameterError(f"--step-check: expected a step in seconds or none, got {text!r}") from None


def _step_check_words(report: FitReport) -> str | None:
    """What the step check found (:func:`pusupu_jax.machine_fit.fit`), for the file's header and the terminal; None
    without one."""
    if report.step_check_s is None or report.step_check_rms is None:
        return None
    before, after = report.step_check_rms
    return (
        f"step check at {report.step_check_s * 1e6:g} us: that replay's residual RMS {before:.4g} at the values "
        f"fitted, {after:.4g} moved" + ("" if report.step_check_moved else ": not moved, these are the values fitted")
    )
