"""Throughput and compile time of the cascade + single-axis plant; prints JSON.

    python benchmarks/bench_cascade.py [--horizon-s 1.0] [--batch 1024] [--batch-horizon-s 0.1] [--repeats 5]

An axis-step is one current-loop tick (20 kHz by default) of one axis, with everything
that runs inside it (current loop and electrical model every tick, mechanics, velocity
and position loops at their rates).  Figures: the median of ``--repeats`` warm runs.
Compile times are measured in fresh subprocesses sharing a new, empty persistent cache:
the first compiles cold, the second loads from the cache (warm).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import tempfile
import time

import numpy as np

from timing import median_time  # beside this script


def throughput(args) -> dict:
    from pusupu_jax import AxisLoad, LoopRates, ServoParams, simulate
    from pusupu_jax.params import stack

    rates = LoopRates()
    params, load = ServoParams.table1(), AxisLoad.default()
    ticks_per_sample = rates.n_velocity * rates.n_position
    out = {}
    for label, p, horizon in [("single", params, args.horizon_s), (f"vmap_{args.batch}", None, args.batch_horizon_s)]:
        if p is None:
            rng = np.random.default_rng(0)
            p = stack(
                [
                    params.replace(Kv=params.Kv * f, lambda1=params.lambda1 * f)
                    for f in rng.uniform(0.7, 1.3, args.batch)
                ]
            )
        n = int(round(horizon / rates.dt_position))
        ref = 0.01 * np.sin(2 * np.pi * np.arange(n) * rates.dt_position)
        wall = median_time(lambda: simulate(p, ref, load=load), args.repeats)
        batch = 1 if np.ndim(p.Kv) == 1 else np.shape(p.Kv)[0]
        axis_steps = batch * n * ticks_per_sample * 6
        out[label] = {
            "batch": batch,
            "horizon_s": horizon,
            "axis_steps": axis_steps,
            "wall_s": wall,
            "axis_steps_per_s": axis_steps / wall,
            "realtime_factor": batch * horizon / wall,
        }
    return out


def compile_probe() -> dict:
    """Run in a subprocess: time lowering+compilation of the rollout and of its gradient."""
    import jax
    import jax.numpy as jnp

    from pusupu_jax import AxisLoad, ServoParams, sim
    from pusupu_jax.runtime import setup_jax

    setup_jax(os.environ["PUSUPU_JAX_CACHE"])
    params, load, ref = ServoParams.table1(), AxisLoad.default(), jnp.zeros((100, 6))
    t0 = time.perf_counter()
    sim._rollout_jit.lower(params, load, ref, plant=sim.AxisPlant(), rates=sim.LoopRates(), outer="imc").compile()
    t1 = time.perf_counter()
    grad = jax.jit(jax.grad(lambda p: jnp.mean(sim.rollout(p, load, ref).theta ** 2)))
    grad.lower(params).compile()
    t2 = time.perf_counter()
    return {"rollout_compile_s": t1 - t0, "grad_compile_s": t2 - t1}


def compile_times() -> dict:
    with tempfile.TemporaryDirectory() as cache:
        env = dict(os.environ, PUSUPU_JAX_CACHE=cache)
        runs = []
        for _ in range(2):
            r = subprocess.run(
                [sys.executable, __file__, "--compile-probe"], env=env, capture_output=True, text=True, check=True
            )
            runs.append(json.loads(r.stdout))
    return {"cold": runs[0], "warm": runs[1]}


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--horizon-s", type=float, default=1.0, help="simulated seconds, single run")
    ap.add_argument("--batch", type=int, default=1024, help="parameter sets in the vmapped run")
    ap.add_argument("--batch-horizon-s", type=float, default=0.1, help="simulated seconds, vmapped run")
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--compile-probe", action="store_true", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.compile_probe:
        print(json.dumps(compile_probe()))
        return
    from pusupu_jax.runtime import setup_jax

    setup_jax()
    import jax

    result = {
        "benchmark": "cascade+axis plant",
        "device": str(jax.devices()[0]),
        "platform": platform.platform(),
        "cpu_count": os.cpu_count(),
        "dtype": "float64",
        "jax": jax.__version__,
        "rates_hz": {"current": 20000, "velocity": 4000, "position": 1000},
        "throughput": throughput(args),
        "compile": compile_times(),
    }
    print(json.dumps(result, indent=2))


if __name__ == "__main__":
    main()
