"""Co-simulation throughput and gradient cost: the cascade + MJX mechanism against the MJX plant alone; prints JSON.

    python benchmarks/bench_cosim.py [--batches 1,16,64 (empty: skip)] [--horizon-s 0.05] [--repeats 3]
                                     [--grad-batches 16] [--grad-groups "imc;imc,hybrid;imc,velocity,hybrid"]
                                     [--dtype float64|float32] [--remat]

An env-step is one mechanical step (0.25 ms of simulated time) of one machine.
``cascade+plant`` runs the full servo cascade of six axes (five current-loop ticks per
env-step, velocity loop every step, position loop every fourth) in IMC mode;
``plant_alone`` runs the same MJX steps with a trivial controller (a PD on the slider
in one line), so ``overhead_ratio`` = cascade+plant / plant-alone throughput shows what
the controllers cost.

``gradient``: the machine in hybrid mode on the first ``--horizon-s`` of the arc, objective
= platform RMS tracking error [mm] + smooth branch-force peak [hN] (``pusupu_jax.objectives``),
a function of the tuner's log-parameters (``pusupu_jax.tune.space``), vmapped over each of
``--grad-batches`` parameter sets.  ``forward_s`` times the objective alone; ``reverse``
is ``jax.value_and_grad`` with respect to every field of the ``--grad-groups`` sets
(its cost does not depend on how many; ``--remat`` rematerialises each position period);
``plant_alone`` is reverse mode through the same MJX steps with the trivial controller
(d sum(qpos^2) / d its constant torque offset; ``--remat`` rematerialises each step): the
floor that no controller code can go under;
``forward_mode[groups]`` is ``jacfwd`` with respect to that set's fields (cost grows with
their number).  Each ``*_over_forward`` is that time over ``forward_s``;
``forward_vs_reverse_diff`` compares the two gradients of the largest set, per field
(largest difference over the batch / largest gradient).
Figures: the median of ``--repeats`` warm runs.
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
    ap.add_argument("--grad-batches", default="16")
    ap.add_argument(
        "--grad-groups",
        default="imc;imc,hybrid;imc,velocity,hybrid",
        help="';'-separated tune-group sets differentiated in forward mode; the largest also in reverse",
    )
    ap.add_argument("--dtype", choices=("float64", "float32"), default="float64")
    ap.add_argument("--remat", action="store_true", help="rematerialise each position period in the gradient")
    args = ap.parse_args()
    from pusupu_jax.runtime import setup_jax

    setup_jax(x64=args.dtype == "float64")
    import jax
    import jax.numpy as jnp
    import numpy as np

    from pusupu_jax import ServoParams, objectives
    from pusupu_jax.gradients import value_and_grad
    from pusupu_jax.hybrid import HybridGains
    from pusupu_jax.machine import machine_plant, machine_rates, machine_reference
    from pusupu_jax.params import stack
    from pusupu_jax.plant.geometry import Geometry
    from pusupu_jax.plant.model import ModelOptions
    from pusupu_jax.sim import rollout
    from pusupu_jax.trajectories import platform_path
    from timing import median_time
    from pusupu_jax.tune.space import Space

    options = ModelOptions()
    plant, rates = machine_plant(options), machine_rates(options)
    n_pos = int(round(args.horizon_s / rates.dt_position))
    env_steps_per_run = n_pos * rates.n_position * (rates.n_velocity // rates.n_mech)
    ref = jnp.asarray(np.sin(np.linspace(0, np.pi, n_pos))[:, None] * np.ones(6) * 2.0)  # motor rad

    def cascade(p):
        return rollout(p, None, ref, plant=plant, rates=rates, outer="imc").theta

    def plant_alone(p, offset=0.06, remat=False):
        aux = plant.prepare(p, None, rates.dt_mech)

        def body(d, _):
            theta, omega = plant.measure(aux, d)
            return plant.step(aux, d, -0.05 * theta - 0.005 * omega + offset), None

        if remat:
            body = jax.checkpoint(body)
        d, _ = jax.lax.scan(body, plant.init(aux), None, length=env_steps_per_run)
        return d.qpos

    base = ServoParams.table1()
    path = jnp.asarray(platform_path("arc", Geometry.default().home, rates)[:n_pos])
    hybrid_reference = machine_reference(base, np.asarray(path), "hybrid", rates=rates)

    def objective(space, remat=False):
        def fun(z):
            servo, hybrid = space.apply(z)
            tr = rollout(
                servo, None, hybrid_reference, plant=plant, rates=rates, outer="hybrid", hybrid=hybrid, remat=remat
            )
            t = objectives.terms(tr, servo, path, rates.dt_position)
            return t["track_rms"] * 1e3 + t["force_peak"] * 1e-2, None

        return fun

    def timed(fn, x):
        return median_time(lambda: fn(x), args.repeats)

    rng = np.random.default_rng(0)
    result = {
        "benchmark": "cascade + MJX mechanism",
        "device": str(jax.devices()[0]),
        "platform": platform.platform(),
        "cpu_count": os.cpu_count(),
        "dtype": args.dtype,
        "jax": jax.__version__,
        "horizon_s": args.horizon_s,
        "env_steps_per_run": env_steps_per_run,
        "batches": {},
    }
    for batch in [int(b) for b in args.batches.split(",") if b]:
        params = stack([base.replace(Kv=base.Kv * f) for f in rng.uniform(0.8, 1.2, batch)])
        row = {}
        for name, fn in (("cascade+plant", cascade), ("plant_alone", plant_alone)):
            wall = timed(jax.jit(jax.vmap(fn)), params)
            row[name] = {"wall_s": wall, "env_steps_per_s": batch * env_steps_per_run / wall}
        row["overhead_ratio"] = row["cascade+plant"]["env_steps_per_s"] / row["plant_alone"]["env_steps_per_s"]
        result["batches"][str(batch)] = row
    group_sets = [tuple(g.split(",")) for g in args.grad_groups.split(";")]
    spaces = {gs: Space.create(gs, base, HybridGains()) for gs in group_sets}
    largest = max(group_sets, key=lambda gs: len(spaces[gs].fields))
    result["gradient"] = {
        "objective": "hybrid mode, arc: RMS tracking error [mm] + smooth force peak [hN]",
        "remat": args.remat,
        "batches": {},
    }
    for batch in [int(b) for b in args.grad_batches.split(",") if b]:
        z = {f: v + jnp.asarray(rng.normal(0.0, 0.1, (batch,) + v.shape)) for f, v in spaces[largest].z0().items()}
        fwd = timed(jax.jit(jax.vmap(lambda x: objective(spaces[largest])(x)[0])), z)
        reverse_fn = jax.jit(jax.vmap(value_and_grad(objective(spaces[largest], args.remat), "reverse")))
        row = {
            "forward_s": fwd,
            "reverse": {"fields": list(spaces[largest].fields), "grad_s": timed(reverse_fn, z)},
            "forward_mode": {},
        }
        row["reverse"]["grad_over_forward"] = row["reverse"]["grad_s"] / fwd
        offsets = jnp.asarray(rng.uniform(0.05, 0.07, (batch, 6)))

        def plant_objective(offset):
            return jnp.sum(plant_alone(base, offset, args.remat) ** 2)

        plant_fwd = timed(jax.jit(jax.vmap(plant_objective)), offsets)
        plant_grad = timed(jax.jit(jax.vmap(jax.value_and_grad(plant_objective))), offsets)
        row["plant_alone"] = {"forward_s": plant_fwd, "grad_s": plant_grad, "grad_over_forward": plant_grad / plant_fwd}
        row["forward_env_steps_per_s"] = batch * env_steps_per_run / fwd
        for gs in group_sets:
            zg = {f: z[f] for f in spaces[gs].fields}
            fn = jax.jit(jax.vmap(value_and_grad(objective(spaces[gs]), "forward")))
            grad_s = timed(fn, zg)
            row["forward_mode"][",".join(gs)] = {
                "fields": list(spaces[gs].fields),
                "grad_s": grad_s,
                "grad_over_forward": grad_s / fwd,
            }
            if gs == largest:
                g_fwd, g_rev = fn(zg)[1], reverse_fn(z)[1]
                row["forward_vs_reverse_diff"] = {  # per field, over the batch, relative to its largest gradient
                    f: float(jnp.max(jnp.abs(g_fwd[f] - g_rev[f])) / jnp.max(jnp.abs(g_rev[f]))) for f in g_rev
                }
        result["gradient"]["batches"][str(batch)] = row
    print(json.dumps(result, indent=2))


if __name__ == "__main__":
    main()
