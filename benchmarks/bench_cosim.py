"""Co-simulation throughput: the cascade + MJX mechanism against the MJX plant alone; prints JSON.

    python benchmarks/bench_cosim.py [--batches 1,16,64] [--horizon-s 0.05] [--repeats 3] [--grad-batch 16]
                                     [--dtype float64|float32] [--remat]

An env-step is one mechanical step (0.25 ms of simulated time) of one machine.
``cascade+plant`` runs the full servo cascade of six axes (five current-loop ticks per
env-step, velocity loop every step, position loop every fourth) in IMC mode;
``plant_alone`` runs the same MJX steps with a trivial controller (a PD on the slider
in one line), so ``overhead_ratio`` = cascade+plant / plant-alone throughput shows what
the controllers cost.  ``grad_over_forward`` is the time of ``jax.grad`` of a
tracking-error objective over the time of the same forward run, vmapped over
``--grad-batch`` parameter sets.  Figures: the median of ``--repeats`` warm runs.
"""

from __future__ import annotations

import argparse
import json
import os
import platform


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--batches", default="1,16,64")
    ap.add_argument("--horizon-s", type=float, default=0.05)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--grad-batch", type=int, default=16)
    ap.add_argument("--dtype", choices=("float64", "float32"), default="float64")
    ap.add_argument("--remat", action="store_true", help="rematerialise each position period in the gradient")
    args = ap.parse_args()
    from pusupu_jax.config import setup_jax

    setup_jax(x64=args.dtype == "float64")
    import jax
    import jax.numpy as jnp
    import numpy as np

    from pusupu_jax import ServoParams
    from pusupu_jax.machine import machine_plant, machine_rates
    from pusupu_jax.params import stack
    from pusupu_jax.plant.model import ModelOptions
    from pusupu_jax.sim import rollout
    from timing import median_time

    options = ModelOptions()
    plant, rates = machine_plant(options), machine_rates(options)
    n_pos = int(round(args.horizon_s / rates.dt_position))
    env_steps_per_run = n_pos * rates.n_position * (rates.n_velocity // rates.n_mech)
    ref = jnp.asarray(np.sin(np.linspace(0, np.pi, n_pos))[:, None] * np.ones(6) * 2.0)  # motor rad

    def cascade(p):
        return rollout(p, None, ref, plant=plant, rates=rates, outer="imc").theta

    def plant_alone(p):
        aux = plant.prepare(p, None, rates.dt_mech)

        def body(d, _):
            theta, omega = plant.measure(aux, d)
            return plant.step(aux, d, -0.05 * theta - 0.005 * omega + 0.06), None

        d, _ = jax.lax.scan(body, plant.init(aux), None, length=env_steps_per_run)
        return d.qpos

    def loss(p):
        tr = rollout(p, None, ref, plant=plant, rates=rates, outer="imc", remat=args.remat)
        return jnp.mean((tr.theta - tr.reference) ** 2)

    def timed(fn, x):
        return median_time(lambda: fn(x), args.repeats)

    base = ServoParams.table1()
    rng = np.random.default_rng(0)
    result = {"benchmark": "cascade + MJX mechanism", "device": str(jax.devices()[0]), "platform": platform.platform(),
              "cpu_count": os.cpu_count(), "dtype": args.dtype, "jax": jax.__version__,
              "horizon_s": args.horizon_s, "env_steps_per_run": env_steps_per_run, "batches": {}}
    for batch in [int(b) for b in args.batches.split(",")]:
        params = stack([base.replace(Kv=base.Kv * f) for f in rng.uniform(0.8, 1.2, batch)])
        row = {}
        for name, fn in (("cascade+plant", cascade), ("plant_alone", plant_alone)):
            wall = timed(jax.jit(jax.vmap(fn)), params)
            row[name] = {"wall_s": wall, "env_steps_per_s": batch * env_steps_per_run / wall}
        row["overhead_ratio"] = row["cascade+plant"]["env_steps_per_s"] / row["plant_alone"]["env_steps_per_s"]
        result["batches"][str(batch)] = row
    params = stack([base.replace(Kv=base.Kv * f) for f in rng.uniform(0.8, 1.2, args.grad_batch)])
    fwd = timed(jax.jit(jax.vmap(loss)), params)
    grad = timed(jax.jit(jax.vmap(jax.grad(loss))), params)
    result["gradient"] = {"batch": args.grad_batch, "remat": args.remat, "forward_s": fwd, "grad_s": grad, "grad_over_forward": grad / fwd,
                          "grad_env_steps_per_s": args.grad_batch * env_steps_per_run / grad}
    print(json.dumps(result, indent=2))


if __name__ == "__main__":
    main()
