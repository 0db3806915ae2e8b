"""The tuner's forward pass over the whole paths (``Problem.refresh``: the start states of the training windows, renewed
every ``refresh_every`` iterations), timed on the device JAX picks (JSON on stdout).

The default configuration's two paths cut to ``--path-s`` seconds (the windows scaled to fit), the start gains; the
first call includes the compile of the start and chunk programs, the later ones are the run alone::

    JAX_PLATFORMS=cpu taskset -c 0-1 python benchmarks/bench_refresh.py --path-s 1 --repeat 3
    python benchmarks/bench_refresh.py --path-s 1 --repeat 3          # on a GPU host: the GPU
"""

from __future__ import annotations

import argparse
import json
import platform
import tempfile
import time


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--path-s", type=float, default=1.0, help="each path cut to this many seconds (default 1)")
    ap.add_argument("--repeat", type=int, default=3, help="calls, the first with the compile (default 3)")
    args = ap.parse_args()
    from pusupu_jax.runtime import cpu_count, setup_jax

    with tempfile.TemporaryDirectory(prefix="pusupu-refresh-") as cache:
        setup_jax(cache)
        import jax

        from pusupu_jax.hybrid import HybridGains
        from pusupu_jax.params import ServoParams
        from pusupu_jax.tune.config import TuneConfig
        from pusupu_jax.tune.run import Problem

        cfg = TuneConfig()
        cfg = cfg.replace(path_s=args.path_s, window_s=args.path_s / cfg.windows)
        problem = Problem(cfg, ServoParams.table1(), HybridGains())
        z = problem.space.z0()
        times = []
        for _ in range(args.repeat):
            t = time.perf_counter()
            problem.refresh(z)
            jax.block_until_ready(problem.starts)
            times.append(time.perf_counter() - t)
    print(
        json.dumps(
            {
                "benchmark": "refresh",
                "path_s": args.path_s,
                "scenarios": list(problem.scenarios.names),
                "first_call_s": times[0],
                "later_calls_s": times[1:],
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
