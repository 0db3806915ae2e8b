"""``pusupu sim``: the single-axis cascade, or the MJX machine on a path."""

from __future__ import annotations

import json
import sys
import time


from pusupu_jax.metrics import Metric
from pusupu_jax.params import ParameterError

from pusupu_jax import devices

from .common import check_log_path, check_path_on, check_plot_path, load_gains, machine_of, num


def cmd_sim(args) -> int:
    from pusupu_jax.runtime import setup_jax

    axis_kinds = ("step", "ramp", "sine")
    args.trajectory = args.trajectory or ("step" if args.plant == "axis" else "arc")
    if args.plant == "axis" and args.trajectory not in axis_kinds:
        raise ParameterError(f"--trajectory: expected one of {axis_kinds} with --plant axis, got {args.trajectory!r}")
    if args.plant == "axis" and args.kin_error is not None:
        raise ParameterError("--kin-error: only the mjx plant has kinematic errors")
    devices.choose(args.device, 1, "one run")
    servo, load, rates, hybrid = load_gains(args)
    if args.plot is not None:
        check_plot_path(args.plot)
    if args.log is not None:
        if args.plant != "mjx":
            raise ParameterError("--log: the log is of the MJX machine's run; give --plant mjx")
        check_log_path(args.log)
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
    devices.announce()
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
        print(f"{a:>4} " + " ".join(f"{num(result[k][a], 'not settled'):>16}" for k in keys))
    if args.plot:
        print(f"plot: {args.plot}")
    return 0


def _sim_machine(args, servo, rates, hybrid) -> int:
    from pusupu_jax import workload
    from pusupu_jax.machine import machine_rates, simulate_machine
    from pusupu_jax.paths import check_spec, path_seconds, platform_path_from
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
    check_path_on(machine, path, servo, f"--trajectory {args.trajectory}", rates.dt_position, options)
    devices.announce()
    print(
        f"simulating {len(path) * rates.dt_position:.1f} s of the {args.trajectory} path on the MJX machine "
        f"({args.mode} mode); the first run compiles for about 15 s",
        file=sys.stderr,
    )
    started_ns = time.time_ns()
    run, trace = simulate_machine(
        servo,
        path,
        mode=args.mode,
        options=options,
        rates=rates,
        hybrid=hybrid,
        start=args.start,
        geom=machine.geometry,
    )
    m = run.metrics
    if args.log:
        from pusupu_jax import __version__, machine_file, run_log

        metadata = {
            "package_version": __version__,
            "source": run_log.SIM_SOURCE,
            "mode": str(args.mode),
            "trajectory": args.trajectory,
            "machine": machine_file.reference(machine),
            "gains": args.gains or "params",
            "rate_hz": 1.0 / rates.dt_position,
        }
        run_log.write(args.log, run_log.machine_channels(trace), metadata, started_ns)
    if args.plot:
        from pusupu_jax.plots import plot_platform_path

        plot_platform_path(
            trace,
            args.plot,
            title=f"{args.trajectory}, {args.mode} mode"
            + (f", kinematic errors seed {args.kin_error}" if args.kin_error is not None else ""),
        )
    if args.json:
        print(json.dumps({"plant": "mjx", "trajectory": args.trajectory} | run.to_json(), indent=2))
        return 0
    print(
        f"{args.trajectory} on the MJX machine {machine_of(args).name!r}, {args.mode} mode "
        f"(IMC form {servo.imc_form}, start {args.start}), "
        f"{m.duration_s:.3g} s simulated "
        f"in {run.wall_s:.2f} s (compile included)"
    )
    for key in (
        Metric.RMS_TRACKING_ERROR_MM,
        Metric.MAX_TRACKING_ERROR_MM,
        Metric.SYNC_ERROR_RHO,
        Metric.LOOP_CLOSURE_RESIDUAL_MAX_MM,
    ):
        print(f"  {key:<30} {num(m.value(key))}")
    for key, value in (m.hybrid.to_json() if m.hybrid else {}).items():
        print(f"  hybrid {key:<23} {value if isinstance(value, str) else num(value)}")
    keys = (
        Metric.BRANCH_RMS_ERROR_MM,
        Metric.BRANCH_REVERSAL_ERROR_MM,
        Metric.MOTOR_TORQUE_PEAK_NM,
        Metric.BRANCH_FORCE_PEAK_N,
    )
    print(f"{'branch':>6} " + " ".join(f"{k:>24}" for k in keys))
    for b in range(6):  # a branch whose reference never reverses: no reversal error
        print(f"{b + 1:>6} " + " ".join(f"{num(m.value(k)[b], none='-'):>24}" for k in keys))
    if args.plot:
        print(f"plot: {args.plot}")
    return 0
