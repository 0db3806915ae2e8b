"""Tuning across what identification left uncertain: the gains ``pusupu tune`` finds on an identified machine without
drawn machines and with ``draws: N``, measured on machines drawn afresh from the same uncertainty section (another
seed: machines neither tune saw) and, where given, on the true machine, each along the whole task path on the MJX
machine, the controller told the identified machine (:class:`pusupu_jax.plant.PlantDrives`).

    python benchmarks/bench_draws.py --machine identified.yaml --gains start.yaml --truth true.yaml \
        [--draws 4] [--held-out 8] [--iterations 25] [--out FILE]

Both tunes are IMC (``lambda1, lambda2, T0, Kv, Tv``) on the arc from the same start gains, with the default windows
and iterations, as ``pusupu experiment real2sim`` tunes.  Prints JSON: each tune's objective and wall time (compile
included: the tune with draws compiles a program of its own), and per measured machine each gain set's RMS and
largest platform error [mm], with their mean and worst over the held-out machines.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).parent))

from timing import emit, processor  # noqa: E402

HELD_OUT_SEED = 1000  # the held-out machines' draw seed: the tunes draw with the configuration's seed (0)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--machine", required=True, help="the identified machine file (with an uncertainty section)")
    ap.add_argument("--gains", required=True, help="the start gain file of both tunes")
    ap.add_argument("--truth", help="the true machine file, measured as well (its sensors are not simulated here)")
    ap.add_argument("--draws", type=int, default=4, help="machines drawn in the robust tune (default 4)")
    ap.add_argument("--held-out", type=int, default=8, help="machines drawn afresh to measure on (default 8)")
    ap.add_argument("--iterations", type=int, default=25, help="tuning iterations (default 25, the default's)")
    ap.add_argument("--path-s", type=float, help="the task path's first seconds only (a check, not a measurement)")
    ap.add_argument("--out", help="also write the JSON here")
    args = ap.parse_args()

    from pusupu_jax.runtime import cpu_count, setup_jax

    setup_jax()  # float64 and the persistent compile cache, as the command line has them

    import numpy as np

    from pusupu_jax import gains as gain_files
    from pusupu_jax import machine_draws, machine_file
    from pusupu_jax.machine import Scenario, machine_rates, simulate_scenarios
    from pusupu_jax.paths import platform_path_from
    from pusupu_jax.tune.config import TuneConfig
    from pusupu_jax.tune.job import run_job

    machine = machine_file.load(args.machine)
    start = gain_files.load(args.gains, machine=machine)
    cfg = TuneConfig(
        mode="imc", groups=("imc", "velocity"), trajectories=("arc",), baselines=(), iterations=args.iterations
    )
    if args.path_s is not None:
        cfg = cfg.replace(path_s=args.path_s, windows=2, window_s=0.3, refresh_every=1, checkpoint_every=1)
    tunes, gain_sets = {}, {}
    with tempfile.TemporaryDirectory() as tmp:
        for draws in (0, args.draws):
            out = Path(tmp) / f"draws{draws}"
            print(f"bench_draws: tune with draws: {draws}", file=sys.stderr, flush=True)
            t0 = time.perf_counter()
            report, status = run_job(cfg.replace(draws=draws), out, machine=machine, start=start)
            if status:
                raise SystemExit(f"bench_draws: the tune with draws: {draws} exported no gains: {report.export.error}")
            tunes[draws] = {
                "objective_before": report.objective_before,
                "objective_after": report.objective_after,
                "wall_s": time.perf_counter() - t0,
                "tuned": report.result,
            }
            gain_sets[draws] = gain_files.load(out / "gains.yaml", machine=machine)

    measured = machine_draws.draw(machine, args.held_out, HELD_OUT_SEED)
    if args.truth:
        measured.append(machine_file.load(args.truth))
    rates = machine_rates()
    path = platform_path_from("arc", machine.geometry.home, rates)
    if args.path_s is not None:
        path = path[: int(round(args.path_s / rates.dt_position))]
    scenarios = [
        Scenario(path, m.options(), m.name, m.geometry, machine_draws.plant_drives(m))
        for m in measured  # the controller told the identified machine, the plant each measured one
    ]
    runs = {}
    for draws, g in gain_sets.items():
        print(f"bench_draws: the gains of draws: {draws} on {len(scenarios)} machines", file=sys.stderr, flush=True)
        runs[draws] = [r for r, _ in simulate_scenarios(machine.servo(g.servo), scenarios, mode="imc", rates=rates)]
    rows = [
        {
            "machine": m.name,
            **{
                f"draws_{d}": {
                    "rms_tracking_error_mm": runs[d][k].metrics.rms_tracking_error_mm,
                    "max_tracking_error_mm": runs[d][k].metrics.max_tracking_error_mm,
                }
                for d in runs
            },
        }
        for k, m in enumerate(measured)
    ]
    held = rows[: args.held_out]

    def over(key: str, metric: str) -> dict:
        values = np.array([r[key][metric] for r in held])
        return {"mean": float(values.mean()), "worst": float(values.max())}

    summary = {
        f"draws_{d}": {m: over(f"draws_{d}", m) for m in ("rms_tracking_error_mm", "max_tracking_error_mm")}
        for d in runs
    }
    emit(
        {
            "benchmark": "draws",
            "command": " ".join(["python", "benchmarks/bench_draws.py", *sys.argv[1:]]),
            "machine": {"processor": processor(), "cores": cpu_count()},
            "identified": {"name": machine.name, "uncertainty": machine.content().get("uncertainty")},
            "settings": cfg.to_json() | {"draws": args.draws, "held_out": args.held_out},
            "held_out_seed": HELD_OUT_SEED,
            "tunes": {f"draws_{d}": t for d, t in tunes.items()},
            "measured": rows,
            "held_out_summary": summary,
        },
        args.out,
    )


if __name__ == "__main__":
    main()
