"""``pusupu analyze``: every loop's crossover, margins and bandwidth, and the identification of T0."""

from __future__ import annotations

import json
import sys
import warnings

import numpy as np

from pusupu_jax.params import N_AXES, ParameterError

from .common import check_plot_path, checking, load_gains, loads_along, machine_of, num


def cmd_analyze(args) -> int:
    from pusupu_jax import analysis

    servo, _, rates, hybrid = load_gains(args, check=False)  # analysed as a diagnosis, then checked
    load = args.linear_load  # the machine's (or the params file's load section)
    if args.plot is not None:
        check_plot_path(args.plot)
    if args.identify_T0:
        if args.trajectory:
            raise ParameterError(
                "--trajectory: not with --identify-T0 (T0 is identified from velocity steps about home)"
            )
        if args.coupled:
            raise ParameterError("--coupled: not with --identify-T0 (it is a loop analysis)")
        return _identify(args, servo, load, rates)
    if args.kin_error is not None:
        raise ParameterError("--kin-error: only with --identify-T0 (the loop analysis uses the single-axis load)")
    if args.coupled and args.load_from_params:
        raise ParameterError(
            f"--coupled: expected the machine's mechanism, got the load section of --params {args.params}"
        )
    loads = {"home": load} | _along_path(args, servo)
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
        if len(loads) > 1:
            result["along_path"] = {
                "trajectory": args.trajectory,
                "carried_mass_kg": {k: np.asarray(v.mass).tolist() for k, v in loads.items() if k != "home"},
            } | {k: _margins(servo, v, args.mode) for k, v in loads.items() if k != "home"}
        if args.plot:
            from pusupu_jax.plots import plot_loops

            plot_loops(servo, load, args.plot, mode=args.mode)
    if args.coupled:
        result["coupled"] = _coupled(args, servo)
    if args.json:
        print(json.dumps(result, indent=2))
        return _refuse_unstable(args, servo, hybrid, rates, loads)
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
            print(f"{k:>4} {name:<9} " + " ".join(f"{num(m[key]):>{w}}" for key, _, w in cols))
    if "along_path" in result:
        along = result["along_path"]
        light, heavy = (np.asarray(along["carried_mass_kg"][k]) for k in ("lightest", "heaviest"))
        print(
            f"along {args.trajectory}: each slider carries {light.min():.1f} to {heavy.max():.1f} kg "
            f"(at home {np.min(load.mass):.1f} to {np.max(load.mass):.1f} kg); over home and those extremes:"
        )
        for name in result["axes"][0]:
            rows = [
                axes[k][name] for axes in (result["axes"], along["lightest"], along["heaviest"]) for k in range(N_AXES)
            ]
            hz = [r["crossover_hz"] for r in rows if r["crossover_hz"] is not None]
            worst = {
                key: min((r[key] for r in rows if r[key] is not None), default=None)
                for key in ("phase_margin_deg", "gain_margin_db")
            }
            print(
                f"  {name:<9} crossover {num(min(hz, default=None))} to {num(max(hz, default=None))} Hz, "
                f"PM at least {num(worst['phase_margin_deg'])} deg, GM at least {num(worst['gain_margin_db'])} dB"
            )
    if "coupled" in result:
        coupled = result["coupled"]
        print(
            f"coupled model at home ({coupled['pose']}): each axis's loop broken, the other five closed "
            "(velocity: at the current reference, the axis's position loop open)"
        )
        print(f"{'axis':>4} {'loop':<9} " + " ".join(f"{title:>{w}}" for _, title, w in cols[:3]))
        for k, row in enumerate(coupled["axes"]):
            for name, m in row.items():
                print(f"{k:>4} {name:<9} " + " ".join(f"{num(m[key]):>{w}}" for key, _, w in cols[:3]))
    if args.plot:
        print(f"plot: {args.plot}")
    return _refuse_unstable(args, servo, hybrid, rates, loads)


def _coupled(args, servo) -> dict:
    """``--coupled``: :func:`pusupu_jax.coupled.loop_margins` at the machine's home (its payload in), per axis
    ``{loop: {crossover_hz, phase_margin_deg, gain_margin_db}}`` for the current, velocity and position loops."""
    from pusupu_jax import coupled
    from pusupu_jax.margins import in_units

    machine = machine_of(args)
    home = np.asarray(machine.geometry.home, dtype=float)
    found = coupled.loop_margins(servo, coupled.Mechanism.at(machine.geometry, home, machine.options()), args.mode)
    return {
        "pose": home.tolist(),
        "axes": [
            {loop: in_units(found[loop], k) for loop in ("current", "velocity", "position")} for k in range(N_AXES)
        ],
    }


def _margins(servo, load, mode) -> list:
    """Per axis ``{loop: {crossover_hz, phase_margin_deg, gain_margin_db}}`` (None: no crossing) from the JAX margins
    (:func:`pusupu_jax.stability.margins`, which the gain check reads; agreeing with python-control's to 0.5 deg and
    0.1 dB, tests/test_margins.py)."""
    from pusupu_jax import stability
    from pusupu_jax.margins import in_units

    found, _ = stability.margins(servo, mode, load)
    return [{loop: in_units(m, k) for loop, m in found.items()} for k in range(N_AXES)]


def _along_path(args, servo) -> dict:
    """``--trajectory``: the linear model's load at the lightest and the heaviest pose of the path on the machine
    (:func:`.common.loads_along`, at the default rates), the path checked against the machine first; else none."""
    if not args.trajectory:
        return {}
    from pusupu_jax.params import LoopRates

    if args.load_from_params:
        raise ParameterError(
            f"--trajectory: expected the machine's load, got the load section of --params {args.params}"
        )
    loads = loads_along(machine_of(args), [args.trajectory], servo, LoopRates())
    return {k: load for k, load in loads.items() if k != "home"}


def _refuse_unstable(args, servo, hybrid, rates, loads: dict) -> int:
    """After ``analyze`` printed its diagnosis: 0 if the gains pass :func:`pusupu_jax.stability.check_loads` with
    ``loads`` (home, and with ``--trajectory`` the path's lightest and heaviest), else its reason on stderr and 2."""
    from pusupu_jax import stability

    try:
        stability.check_loads(servo, hybrid, rates, args.mode, args.floors, loads, along=str(args.trajectory))
    except ParameterError as e:
        print(f"pusupu: error: {e}", file=sys.stderr)
        return 2
    return 0


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
