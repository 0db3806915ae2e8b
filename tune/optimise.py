"""The optimiser loop: clipped Adam (optax) whose learning rate may decay along a cosine, projection onto the box after
each step, multi-start, a checkpoint every ``checkpoint_every`` iterations (:mod:`.checkpoint`) and resumption from
it, progress through a callback.  Generic: any ``value_and_grad`` over a dict of arrays."""

from __future__ import annotations

import time
from pathlib import Path
from typing import Callable

import jax
import jax.numpy as jnp
import numpy as np
import optax

from .checkpoint import CheckpointLayout, load_checkpoint, save_checkpoint


def start_point(z0: dict, k: int, spread: float, seed: int, project: Callable) -> dict:
    """Start ``k`` of a multi-start run: ``z0`` for the first, a projected log-normal perturbation (std ``spread``)
    drawn from ``seed`` and ``k`` for the others."""
    if k == 0:
        return dict(z0)
    keys = jax.random.split(jax.random.PRNGKey(seed + 1000 * k), len(z0))
    return project(
        {n: v + spread * jax.random.normal(key, jnp.shape(v)) for (n, v), key in zip(sorted(z0.items()), keys)}
    )


def optimiser(learning_rate: float, iterations: int, clip_norm: float, final_lr_fraction: float):
    """Clipped Adam whose learning rate follows a cosine from ``learning_rate`` to ``final_lr_fraction`` of it."""
    schedule = optax.cosine_decay_schedule(learning_rate, iterations, alpha=final_lr_fraction)
    return optax.chain(optax.clip_by_global_norm(clip_norm), optax.adam(schedule))


def optimise(
    value_and_grad: Callable,
    z0: dict,
    project: Callable,
    *,
    iterations: int,
    learning_rate: float,
    clip_norm: float = 1.0,
    final_lr_fraction: float = 1.0,
    starts: int = 1,
    start_spread: float = 0.0,
    seed: int = 0,
    checkpoint: Path | None = None,
    checkpoint_every: int = 5,
    digest: str = "",
    progress: Callable | None = None,
    prepare: Callable | None = None,
) -> dict:
    """Minimise from ``z0`` (and ``starts - 1`` perturbed starts); returns the best ``z`` and the history.

    ``value_and_grad(z) -> ((value, aux), grad)``; ``prepare(z, iteration)``, if given, runs before
    each evaluation (a start's iterations count from 0).  With ``checkpoint``, the state is saved
    every ``checkpoint_every`` iterations and at the end of each start, and a run that
    finds one continues from it (bit-identical to an uninterrupted run: every random draw
    is made from ``seed`` and the start index).
    """
    opt = optimiser(learning_rate, iterations, clip_norm, final_lr_fraction)
    layout = CheckpointLayout(z0, opt.init(z0), iterations, starts)
    state = load_checkpoint(checkpoint, digest, layout) if checkpoint else None
    if state is None:
        state = {
            "digest": digest,
            "start": 0,
            "iteration": 0,
            "z": None,
            "opt": None,
            "history": [],
            "best_value": np.inf,
            "best_z": None,
            "done": False,
        }
    t_start = time.perf_counter()
    while not state["done"]:
        k = state["start"]
        if state["z"] is None:
            z = start_point(z0, k, start_spread, seed, project)
            state["z"], state["opt"] = z, opt.init(z)
        z, opt_state = jax.tree.map(jnp.asarray, state["z"]), state["opt"]

        def note(z, value, iteration):  # history entry, and the best point so far
            state["history"].append(
                {
                    "start": k,
                    "iteration": iteration,
                    "objective": value,
                    "z": {n: np.asarray(v).tolist() for n, v in z.items()},
                }
            )
            if value < state["best_value"]:
                state["best_value"], state["best_z"] = value, {n: np.asarray(v) for n, v in z.items()}

        while state["iteration"] < iterations:
            if prepare:
                prepare(z, state["iteration"])
            (value, aux), grad = value_and_grad(z)
            value = float(value)
            if not np.isfinite(value) or not all(np.isfinite(np.asarray(g)).all() for g in grad.values()):
                raise FloatingPointError(
                    f"tune: non-finite objective or gradient at start {k}, "
                    f"iteration {state['iteration']} (value {value})"
                )
            note(z, value, state["iteration"])
            updates, opt_state = opt.update(grad, opt_state, z)
            z = project(optax.apply_updates(z, updates))
            state["iteration"] += 1
            state["z"], state["opt"] = z, opt_state
            if progress:
                progress(
                    k, state["iteration"], iterations, value, state["best_value"], aux, time.perf_counter() - t_start
                )
            if checkpoint and state["iteration"] % checkpoint_every == 0:
                save_checkpoint(checkpoint, state)
        if prepare:
            prepare(z, iterations)
        (value, _), _ = value_and_grad(z)  # the last step's result is evaluated too: it may be the best
        note(z, float(value), iterations)
        state.update(start=k + 1, iteration=0, z=None, opt=None, done=k + 1 >= starts)
        if checkpoint:
            save_checkpoint(checkpoint, state)
    return OptimiseResult(z=state["best_z"], objective=state["best_value"], history=state["history"])


class OptimiseResult(dict):
    """What :func:`optimise` returns: a dict of the best ``z``, its ``objective`` and the ``history`` (one entry per
    evaluation), shown as a short summary (a notebook's cell output) rather than every entry of the history."""

    def __repr__(self) -> str:
        history = self.get("history") or []
        first = f"{history[0]['objective']:.4g} at the start, " if history else ""
        best = next((h for h in history if h["objective"] == self.get("objective")), None)
        where = f" (start {best['start'] + 1}, iteration {best['iteration']})" if best else ""
        starts = len({h["start"] for h in history})
        z = ", ".join(f"{k} {_values(v)}" for k, v in (self.get("z") or {}).items())
        return (
            f"OptimiseResult: objective {first}best {self.get('objective', float('nan')):.4g}{where}; "
            f"{len(history)} evaluations over {starts} start(s)\n  z: {z}"
        )[:2000]


def _values(v) -> str:
    flat = np.ravel(np.asarray(v, dtype=float))
    return (
        " ".join(f"{x:.4g}" for x in flat)
        if flat.size <= 6
        else f"{flat.size} values {flat.min():.4g}..{flat.max():.4g}"
    )
