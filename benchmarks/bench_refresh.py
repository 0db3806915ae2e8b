"""The tuner's forward pass over the whole paths (what ``Problem.refresh`` computes: the start states of the training
windows, renewed every ``refresh_every`` iterations), timed on the device JAX picks (JSON on stdout).

The default configuration's two paths cut to ``--path-s`` seconds (the windows scaled to fit; 0: the whole paths),
the start gains.  Each call is ``Problem.run_paths`` itself, which runs to the last window's start (the start states
kept on disk, which a later ``refresh`` at the same gains would read, are not used); the first call includes the
compile of the start and chunk programs, the later ones are the run alone.  ``--to-end`` times, alternating with
it, the same pass run on to the paths' end (as the final evaluation runs it)::

    JAX_PLATFORMS=cpu taskset -c 0-1 python benchmarks/bench_refresh.py --path-s 1 --repeat 3
    python benchmarks/bench_refresh.py --path-s 1 --repeat 3          # on a GPU host: the GPU
    python benchmarks/bench_refresh.py --path-s 0 --repeat 4 --to-end
"""

from __future__ import annotations

import argparse
import json
import platform
import tempfile
import time


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument(
        "--path-s", type=float, default=1.0, help="each path cut to this many seconds (default 1; 0: whole)"
    )
    ap.add_argument("--repeat", type=int, default=3, help="calls, the first with the compile (default 3)")
    ap.add_argument("--to-end", action="store_true", help="also the pass to the paths' end, alternating")
    args = ap.parse_args()
    if args.path_s < 0 or args.repeat < 2:
        ap.error(f"expected --path-s >= 0 and --repeat >= 2, got {args.path_s} and {args.repeat}")
    from pusupu_jax.runtime import cpu_count, setup_jax

    with tempfile.TemporaryDirectory(prefix="pusupu-refresh-") as cache:
        setup_jax(cache)
        import jax

        from pusupu_jax.hybrid import HybridGains
        from pusupu_jax.params import ServoParams
        from pusupu_jax.tune.config import TuneConfig
        from pusupu_jax.tune.run import Problem

        cfg = TuneConfig()
        if args.path_s:
            cfg = cfg.replace(path_s=args.path_s, window_s=min(cfg.window_s, args.path_s / cfg.windows))
        problem = Problem(cfg, ServoParams.table1(), HybridGains())
        z = problem.space.z0()
        times: dict[str, list[float]] = {"to_last_start": [], "to_end": []}
        periods = {}
        for _ in range(args.repeat):
            for name in ("to_last_start", "to_end") if args.to_end else ("to_last_start",):
                t = time.perf_counter()
                runs = jax.block_until_ready(problem.run_paths(z, starts_only=name == "to_last_start"))
                times[name].append(time.perf_counter() - t)
                periods[name] = [len(trace.t) for trace, _ in runs]
    print(
        json.dumps(
            {
                "benchmark": "refresh",
                "path_s": args.path_s or None,
                "scenarios": list(problem.scenarios.names),
                "first_call_s": times["to_last_start"][0],
                "later_calls_s": times["to_last_start"][1:],
                "position_periods_run": periods["to_last_start"],
                **(
                    {
                        "to_end": {
                            "first_call_s": times["to_end"][0],
                            "later_calls_s": times["to_end"][1:],
                            "position_periods_run": periods["to_end"],
                        }
                    }
                    if args.to_end
                    else {}
                ),
                "device": str(jax.devices()[0]),
                "devices": len(jax.devices()),
                "cpus": cpu_count(),
                "machine": platform.machine(),
                "jax": jax.__version__,
            },
            indent=1,
        )
    )


if __name__ == "__main__":
    main()
