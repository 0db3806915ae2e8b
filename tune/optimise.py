"""The tuner's one engine: clipped Adam (optax) whose learning rate may decay along a cosine, one jitted step that
updates every member of a batch and projects it onto the box, multi-start, a checkpoint every ``checkpoint_every``
iterations (:mod:`.checkpoint`) and resumption from it, progress through a callback.

A *member* is one start of one problem, a row of every leaf of the log-gains ``z``.  :func:`iterate` runs the members
of a batch in step (:func:`pusupu_jax.tune.batch.optimise_batch`: ``pusupu batch``); a single problem is a batch of one
(:func:`optimise`: ``pusupu tune`` and notebooks, any ``value_and_grad`` over a dict of arrays), whose starts run one
after another, each from its own start point, since its windows' start states follow its gains.
"""

from __future__ import annotations

import dataclasses
import time
from pathlib import Path
from typing import Callable

import jax
import jax.numpy as jnp
import numpy as np
import optax

from .checkpoint import CheckpointLayout, load_checkpoint, save_checkpoint
from .state import Evaluation, TunerState


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


def train_step(opt: optax.GradientTransformation, project: Callable, members: int) -> Callable:
    """The jitted step ``(grad, opt_state, zb, ok) -> (zb, opt_state)`` of ``members`` members at once: the optax update
    (vmapped, so that clipping stays per member), then the projection onto the box; a member whose ``ok`` is false
    stays where it is."""
    project = jax.vmap(project)

    @jax.jit
    def step(grad, opt_state, zb, ok):
        def keep(new, old):
            return jnp.where(ok.reshape((members,) + (1,) * (new.ndim - 1)), new, old)

        grad = jax.tree.map(lambda g: keep(g, jnp.zeros_like(g)), grad)
        updates, new_opt = jax.vmap(opt.update)(grad, opt_state, zb)
        new_z = project(jax.tree.map(lambda z, u: z + u, zb, updates))
        return jax.tree.map(keep, new_z, zb), jax.tree.map(keep, new_opt, opt_state)

    return step


def iterate(
    state: TunerState,
    evaluate: Callable,
    step: Callable,
    *,
    iterations: int,
    starts: list[int],
    place: Callable = lambda tree: tree,
    checkpoint: Path | None = None,
    checkpoint_every: int = 5,
    progress: Callable | None = None,
    raise_on_failure: bool = False,
    t_start: float | None = None,
) -> None:
    """Run ``state``'s members from ``state.iteration`` to ``iterations``, then evaluate their last point (it may be
    the best).

    ``evaluate(zb, iteration) -> (values (M,), grad, aux)`` (the gradient's leaves with the member axis);
    ``step``: :func:`train_step`'s; ``starts``: each member's start index (for the history); ``place``: lays a tree
    of member rows on the devices (once: no recompiles later).  A member whose objective or gradient turns
    non-finite is frozen and named in ``state.failed`` (with ``raise_on_failure``, :class:`FloatingPointError`
    instead, but for the last point).  ``progress(state, values, aux, elapsed)`` after each iteration; the state is
    checkpointed every ``checkpoint_every`` iterations.
    """
    t_start = time.perf_counter() if t_start is None else t_start
    zb, opt_state = place(jax.tree.map(jnp.asarray, state.z)), place(state.opt)
    members = len(starts)

    def evaluated(zb, iteration, last=False):
        values, grad, aux = evaluate(zb, iteration)
        values = np.asarray(values, dtype=float)
        finite = np.isfinite(values) & np.all(
            [np.isfinite(np.asarray(g)).reshape(members, -1).all(axis=1) for g in grad.values()], axis=0
        )
        for m in np.flatnonzero(~finite):
            message = (
                f"non-finite objective or gradient at start {starts[m]}, iteration {iteration} (value {values[m]})"
            )
            if raise_on_failure and not last:  # the last point's failure only keeps it from being the best
                raise FloatingPointError(f"tune: {message}")
            state.failed.setdefault(int(m), message)
        state.note(values, zb, starts, iteration)
        return values, grad, aux

    while state.iteration < iterations:
        values, grad, aux = evaluated(zb, state.iteration)
        ok = jnp.asarray([m not in state.failed for m in range(members)])
        zb, opt_state = step(grad, opt_state, zb, ok)
        state.iteration += 1
        state.z, state.opt = zb, opt_state
        if progress:
            progress(state, values, aux, time.perf_counter() - t_start)
        if checkpoint and state.iteration % checkpoint_every == 0:
            save_checkpoint(checkpoint, state)
    evaluated(zb, iterations, last=True)


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
) -> OptimiseResult:
    """Minimise from ``z0`` (and ``starts - 1`` perturbed starts); returns the best ``z`` and the history.

    A batch of one member through :func:`iterate`, one start after another.  ``value_and_grad(z) -> ((value, aux),
    grad)``; ``prepare(z, iteration)``, if given, runs before each evaluation (a start's iterations count from 0);
    ``progress(start, iteration, iterations, value, best, aux, elapsed)`` after each iteration.  With
    ``checkpoint``, the state is saved every ``checkpoint_every`` iterations and at the end of each start, and a run
    that finds one continues from it (bit-identical to an uninterrupted run: every random draw is made from ``seed``
    and the start index).  A non-finite objective or gradient raises :class:`FloatingPointError`.
    """
    opt = optimiser(learning_rate, iterations, clip_norm, final_lr_fraction)
    one = {k: jnp.asarray(v)[None] for k, v in z0.items()}
    template = TunerState.fresh(digest, one, jax.vmap(opt.init)(one))
    layout = CheckpointLayout(one, template.opt, iterations, starts)
    state = (load_checkpoint(checkpoint, digest, layout) if checkpoint else None) or template
    step = train_step(opt, project, 1)
    t_start = time.perf_counter()

    def evaluate(zb, iteration):
        z = {k: v[0] for k, v in zb.items()}
        if prepare:
            prepare(z, iteration)
        (value, aux), grad = value_and_grad(z)
        return np.asarray([value], dtype=float), {k: jnp.asarray(g)[None] for k, g in grad.items()}, aux

    def reported(state, values, aux, elapsed):
        progress(state.start, state.iteration, iterations, values[0], state.best_value[0], aux, elapsed)

    while not state.done:
        if state.z is None:
            z = {k: jnp.asarray(v)[None] for k, v in start_point(z0, state.start, start_spread, seed, project).items()}
            state.z, state.opt = z, jax.vmap(opt.init)(z)
        iterate(
            state,
            evaluate,
            step,
            iterations=iterations,
            starts=[state.start],
            checkpoint=checkpoint,
            checkpoint_every=checkpoint_every,
            progress=reported if progress else None,
            raise_on_failure=True,
            t_start=t_start,
        )
        state.start += 1
        state.iteration, state.z, state.opt, state.done = 0, None, None, state.start >= starts
        if checkpoint:
            save_checkpoint(checkpoint, state)
    best = {k: np.asarray(v)[0] for k, v in state.best_z.items()}
    return OptimiseResult(z=best, objective=float(state.best_value[0]), history=state.history[0])


@dataclasses.dataclass(frozen=True)
class OptimiseResult:
    """What :func:`optimise` returns: the best log-gains ``z`` (field -> array), their ``objective`` and the
    ``history`` (one :class:`~pusupu_jax.tune.state.Evaluation` per evaluation, over every start), shown as a short
    summary (a notebook's cell output) rather than every entry of the history."""

    z: dict[str, np.ndarray]
    objective: float
    history: list[Evaluation]

    def __repr__(self) -> str:
        history = self.history
        first = f"{history[0].objective:.4g} at the start, " if history else ""
        best = next((h for h in history if h.objective == self.objective), None)
        where = f" (start {best.start + 1}, iteration {best.iteration})" if best else ""
        starts = len({h.start for h in history})
        z = ", ".join(f"{k} {_values(v)}" for k, v in self.z.items())
        return (
            f"OptimiseResult: objective {first}best {self.objective:.4g}{where}; "
            f"{len(history)} evaluations over {starts} start(s)\n  z: {z}"
        )[:2000]


def _values(v) -> str:
    flat = np.ravel(np.asarray(v, dtype=float))
    return (
        " ".join(f"{x:.4g}" for x in flat)
        if flat.size <= 6
        else f"{flat.size} values {flat.min():.4g}..{flat.max():.4g}"
    )
