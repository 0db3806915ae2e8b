"""``pusupu machine``: init, check, schema."""

from __future__ import annotations

import json

import numpy as np

from pusupu_jax.params import ParameterError

from .common import check_path_on, checking, machine_of


def cmd_machine(args) -> int:
    from pathlib import Path

    from pusupu_jax import machine_file

    if args.action == "schema":
        print(machine_file.schema_text(), end="")
        return 0
    if args.action == "init":
        from pusupu_jax.files import write_atomic

        out = Path(args.out)
        if not args.out:
            raise ParameterError("--out: expected the name of a new file, got ''")
        if out.exists() or out.is_symlink():
            found = "a folder" if out.is_dir() else "one there"
            raise ParameterError(f"--out {args.out}: expected a new file, found {found} (left as it is)")
        write_atomic(out, machine_file.template())
        print(f"wrote {out}: the built-in machine, every field commented; edit it, then pusupu machine check {out}")
        return 0
    from pusupu_jax.runtime import setup_jax

    setup_jax()
    args.machine = args.file
    machine = machine_of(args)
    from pusupu_jax.params import LoopRates
    from pusupu_jax.paths import platform_path_from

    paths = []
    for name in args.trajectory or ["arc", "p2p"]:
        with checking(f"--trajectory {name}"):
            paths.append((name, platform_path_from(name, machine.geometry.home, LoopRates())))
    from pusupu_jax.start_gains import derive

    with checking(args.file):
        found = machine_file.check(machine, paths)
        servo, report = derive(machine, identify=False)  # the drives' limits: speed_max, Kt I_peak
        for name, poses in paths:
            check_path_on(machine, poses, servo, f"--trajectory {name}")
    mass = np.asarray(report["carried_mass_kg"])
    result = {
        "file": args.file,
        "name": machine.name,
        "digest": machine_file.digest(machine),
        "carried_mass_kg": mass.tolist(),
        "workspace": found,
        "encoders": machine_file.encoder_quanta(machine, LoopRates().dt_velocity),
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
    encoders = result["encoders"]
    if encoders is None:
        print("  encoders: ideal (no encoder_counts given)")
    else:
        print(
            f"  encoders: {_span(encoders['counts_per_rev'], '{:.0f}')} counts a revolution, one count "
            f"{_span(np.multiply(encoders['slider_count_m'], 1e9), '{:.3g}')} nm at the slider; a speed counted over "
            f"one velocity period ({LoopRates().dt_velocity * 1e3:g} ms) moves in steps of "
            f"{_span(encoders['speed_step_rad_s'], '{:.3g}')} rad/s"
        )
    return 0


def _span(values, fmt: str) -> str:
    lo, hi = min(values), max(values)
    return fmt.format(lo) if lo == hi else f"{fmt.format(lo)} to {fmt.format(hi)}"
