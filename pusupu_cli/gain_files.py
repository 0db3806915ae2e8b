"""``pusupu gains``: show, check, sign, diff, migrate, export-ros, check-ros."""

from __future__ import annotations

import json
import sys


from pusupu_jax.cascade import Mode
from pusupu_jax.metrics import Metric
from pusupu_jax.params import ParameterError

from .common import check_along_paths, check_path_on, checking, machine_of, say

COMPARED = (Metric.RMS_TRACKING_ERROR_MM, Metric.MAX_TRACKING_ERROR_MM, Metric.HIGHEST_BRANCH_FORCE_PEAK_N)


def cmd_gains(args) -> int:
    from pathlib import Path

    from pusupu_jax import gain_view, gains
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
        print(json.dumps(g.document, indent=2) if args.json else gain_view.show(g.document))
    elif args.action == "diff":
        with checking(args.other):
            other = gains.load(args.other, floors)
        lines = gain_view.diff(g.document, other.document)
        print("\n".join(lines) if lines else "no difference in gains, rates or mode")
    elif args.action == "check":
        from pusupu_jax import machine_file

        along = _check_along(args, g, machine, floors)
        print(
            f"{args.file}: valid {gains.SCHEMA} v{g.document['version']}, mode {g.mode}, tuned on machine "
            f"{g.machine['name']!r} (digest {g.machine['digest'][:12]}); on machine {machine.name!r} (digest "
            f"{machine_file.digest(machine)[:12]}) every loop is stable at the file's rates and has at least "
            f"{floors[0]:g} deg and {floors[1]:g} dB" + along
        )
        if not g.tuned_on(machine):
            say(
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
        short = ros2.short_of_floors(g.servo, g.mode, machine, floors)
        if short:
            say(f"pusupu: warning: {short}")
    else:
        return _check_ros(args, g)
    return 0


def _check_along(args, g, machine, floors) -> str:
    """``gains check --trajectory``: what the check's line adds (:func:`.common.check_along_paths`)."""
    if not args.trajectory:
        return ""
    loads = check_along_paths(g, machine, args.trajectory, floors, args.file)
    light, heavy = loads["lightest"].mass, loads["heaviest"].mass
    return f", also with the {light.min():.1f} to {heavy.max():.1f} kg the sliders carry along " + " and ".join(
        args.trajectory
    )


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
        check_path_on(machine, p, g.servo, f"--trajectory {k}", g.rates.dt_position)
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
            result["paths"].setdefault(sc.name, {})[who] = {k.value: r.metrics.value(k) for k in COMPARED}
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
        for key in COMPARED:
            print(f"{name:<6} {key:<28} {per['pusupu'][key]:>18.4g} {per['ros'][key]:>12.4g}")
    for key in ("phase_margin_deg", "gain_margin_db"):
        print(
            f"{'':<6} {'position loop ' + key:<28} {result['position_margins']['pusupu'][key]:>18.4g} "
            f"{result['position_margins']['ros'][key]:>12.4g}"
        )
    return 0
