"""Gradient tuner vs a derivative-free optimiser on the same objective and start (JSON on stdout).

The problem is ``pusupu tune``'s (hybrid mode, the default groups in log space, same
penalties) on a short stretch of one path (``--path`` seconds, ``--windows`` training windows
of ``--window`` s, start states from one forward pass at the start gains) so that the
derivative-free side finishes.  The
gradient tuner (clipped Adam, :func:`pusupu_jax.tune.optimise.optimise`) runs ``--iterations``; scipy's
Nelder-Mead then minimises the same objective (forward rollouts only, the same box bounds)
until it reaches the gradient tuner's best value or ``--max-evals``.  Counted: rollouts
(a gradient evaluation counts as one rollout, its cost is reported separately as the
gradient/forward time ratio) and wall time to reach the target (compile excluded on both
sides).

    python benchmarks/bench_tuner.py [--trajectory arc] [--path 2] [--windows 2] [--window 0.25] [--iterations 25]
                                     [--max-evals 1500] [--groups imc,velocity,hybrid] [--per-axis]
"""

from __future__ import annotations

import argparse
import json
import sys
import time

import jax
import numpy as np
from jax.flatten_util import ravel_pytree
from scipy.optimize import minimize

from pusupu_jax.runtime import setup_jax
from timing import median_time  # beside this script


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--trajectory", default="arc", choices=("arc", "p2p"))
    ap.add_argument("--path", type=float, default=2.0, help="the first seconds of the path [s]")
    ap.add_argument("--windows", type=int, default=2, help="training windows spread over it")
    ap.add_argument("--window", type=float, default=0.25, help="training window [s]")
    ap.add_argument("--iterations", type=int, default=25)
    ap.add_argument("--max-evals", type=int, default=1500)
    ap.add_argument("--groups", default="imc,velocity,hybrid", help="comma-separated tuned groups (tune/space.py)")
    ap.add_argument("--per-axis", action="store_true", help="one value per axis instead of shared")
    args = ap.parse_args()
    setup_jax()
    from pusupu_jax import ServoParams
    from pusupu_jax.hybrid import HybridGains
    from pusupu_jax.tune.config import TuneConfig
    from pusupu_jax.tune.optimise import optimise
    from pusupu_jax.tune.run import Problem

    cfg = TuneConfig(
        trajectories=(args.trajectory,),
        path_s=args.path,
        windows=args.windows,
        window_s=args.window,
        iterations=args.iterations,
        groups=tuple(args.groups.split(",")),
        shared=not args.per_axis,
    )
    problem = Problem(cfg, ServoParams.table1(), HybridGains())
    space, z0 = problem.space, problem.space.z0()
    baseline = problem.start_baseline()  # and the window start states at z0, kept for both optimisers
    value = jax.jit(lambda z: problem.objective(z, baseline, problem.starts, problem.windows, problem.space.start)[0])
    t_forward = median_time(lambda: value(z0), 1)  # after one compiling call each
    t_grad = median_time(lambda: problem.value_and_grad(z0), 1)

    trace = []
    t0 = time.perf_counter()

    def counted(z):
        out = problem.value_and_grad(z)
        trace.append((float(out[0][0]), time.perf_counter() - t0))
        return out

    result = optimise(
        counted, z0, space.project, iterations=cfg.iterations, learning_rate=cfg.learning_rate, clip_norm=cfg.clip_norm
    )
    target = result.objective
    grad_evals = next(i + 1 for i, (v, _) in enumerate(trace) if v <= target)
    grad_wall = trace[grad_evals - 1][1]

    x0, unflatten = ravel_pytree(z0)  # fields in sorted order, as the dicts below
    x0 = np.asarray(x0)
    lo = np.asarray(ravel_pytree({n: np.log(v) for n, v in space.lower.items()})[0])
    hi = np.asarray(ravel_pytree({n: np.log(v) for n, v in space.upper.items()})[0])
    evals = []
    t0 = time.perf_counter()

    def f(x):
        x = np.clip(x, lo, hi)
        v = float(value(unflatten(x)))
        evals.append((v, time.perf_counter() - t0))
        if v <= target:
            raise StopIteration
        return v

    try:
        minimize(
            f,
            x0,
            method="Nelder-Mead",
            options={
                "maxfev": args.max_evals,
                "xatol": 1e-6,
                "fatol": 1e-9,
                "initial_simplex": x0 + 0.3 * np.vstack([np.zeros(len(x0)), np.eye(len(x0))]),
            },
        )
    except StopIteration:
        pass
    reached = evals[-1][0] <= target
    best_nm = min(v for v, _ in evals)
    out = {
        "problem": {
            "trajectory": args.trajectory,
            "path_s": args.path,
            "windows": args.windows,
            "window_s": args.window,
            "mode": cfg.mode,
            "fields": sorted(z0),
            "parameters": int(x0.size),
            "start_objective": trace[0][0],
        },
        "forward_s": t_forward,
        "gradient_s": t_grad,
        "gradient_over_forward": t_grad / t_forward,
        "gradient_tuner": {"target_objective": target, "rollouts_to_target": grad_evals, "wall_s_to_target": grad_wall},
        "nelder_mead": {
            "reached_target": reached,
            "rollouts": len(evals),
            "wall_s": evals[-1][1],
            "best_objective": best_nm,
            "max_evals": args.max_evals,
        },
        "rollout_ratio": len(evals) / grad_evals,
        "wall_ratio": evals[-1][1] / grad_wall,
    }
    json.dump(out, sys.stdout, indent=2)
    print()


if __name__ == "__main__":
    main()
