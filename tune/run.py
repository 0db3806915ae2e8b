"""The tuning problem (objective over scenarios) and the optimiser loop with checkpoints.

The objective at log-parameters ``z`` is, per scenario (path window x kinematic-error
seed x payload; the scenarios run as one vmapped batch), ``sum_k w_k term_k(z) / term_k(z0)`` over the weighted
:mod:`pusupu_jax.objectives` terms, plus penalties: the smooth branch-force peak above
``force_peak_limit`` times its start value, current/voltage saturation, and every loop's
phase and gain margins (:mod:`pusupu_jax.margins`, single-axis model) below
``pm_min``/``gm_min``.  Scenarios are aggregated by their mean or maximum.

:func:`optimise` is generic (any ``value_and_grad`` over a dict of arrays): clipped Adam
(optax) whose learning rate may decay along a cosine to ``final_lr_fraction`` of itself over each
start's iterations (1: constant, the default), projection onto the box after each step, multi-start, a checkpoint every
``checkpoint_every`` iterations (written atomically), resumption from it, and progress
lines on stderr.
"""

from __future__ import annotations

import dataclasses
import functools
import pickle
import sys
import time
from pathlib import Path
from typing import Callable

import jax
import jax.numpy as jnp
import numpy as np
import optax

from pusupu_jax import objectives
from pusupu_jax.config import write_atomic
from pusupu_jax.gradients import value_and_grad
from pusupu_jax.hybrid import HybridGains
from pusupu_jax.machine import machine_metrics, machine_plant, machine_rates, machine_reference
from pusupu_jax.margins import loop_margins
from pusupu_jax.params import AxisLoad, ParameterError, ServoParams, stack
from pusupu_jax.plant.geometry import Geometry
from pusupu_jax.plant.model import ModelOptions
from pusupu_jax.sim import rollout
from pusupu_jax.trajectories import platform_path

from .config import TuneConfig
from .space import Space

PENALTY_WEIGHT = 100.0


def scenario_list(cfg: TuneConfig) -> list[tuple[str, str, ModelOptions]]:
    """``(name, trajectory, model options)`` of every scenario, named ``arc``, ``arc/seed3``, ``p2p/seed3/10kg``..."""
    return [(kind + (f"/seed{seed}" if seed is not None else "") + (f"/{payload:g}kg" if payload else ""), kind,
             ModelOptions(kin_error_seed=seed, payload=float(payload)))
            for kind in cfg.trajectories for seed in cfg.kin_error_seeds for payload in cfg.payloads]


def platform_paths(cfg: TuneConfig, rates) -> dict:
    """``{trajectory: platform poses (N, 5)}`` of the configuration's paths, whole, about the default home."""
    return {kind: platform_path(kind, Geometry.default().home, rates) for kind in cfg.trajectories}


def window(duration: float, dt: float) -> int:
    """The number of position periods in the first ``duration`` seconds of a path (at least 3)."""
    return max(3, int(round(duration / dt)))


@dataclasses.dataclass(frozen=True)
class Scenarios:
    """Every (path, seed, payload) combination, stacked along a leading axis for one vmapped rollout.

    Each path is cut to the same window (its first ``duration`` s, or the shortest path), so
    that the batch is rectangular; seeds and payloads enter as :meth:`MJXPlant.variant` models.
    """

    names: list
    plant: object  # the nominal MJXPlant (structure and static fields)
    models: object  # stacked mjx.Model variants, (S, ...)
    reference: object  # stacked rollout references, (S, N, ...)
    path: object  # stacked platform poses, (S, N, 5)

    @classmethod
    def build(cls, cfg: TuneConfig, servo: ServoParams, duration: float | None, rates) -> "Scenarios":
        paths = platform_paths(cfg, rates)
        n = min(len(p) for p in paths.values())
        if duration is not None:
            n = min(n, window(duration, rates.dt_position))
        plant = machine_plant(ModelOptions())
        names, models, refs, cut = [], [], [], []
        for name, kind, options in scenario_list(cfg):
            names.append(name)
            models.append(plant.variant(options))
            refs.append(machine_reference(servo, paths[kind][:n], cfg.mode, options=options, rates=rates))
            cut.append(paths[kind][:n])
        return cls(names, plant, stack(models), stack(refs), np.stack(cut))


class Problem:
    """The objective of a :class:`TuneConfig` around the start ``servo0``, ``hybrid0``."""

    def __init__(self, cfg: TuneConfig, servo0: ServoParams, hybrid0: HybridGains):
        self.cfg = cfg
        self.rates = machine_rates()
        self.space = Space.create(cfg.groups, servo0, hybrid0, shared=cfg.shared, bounds=cfg.bounds)
        self.scenarios = Scenarios.build(cfg, servo0, cfg.horizon_s, self.rates)
        self.load = AxisLoad.default()
        self._value_and_grad = jax.jit(value_and_grad(self.objective, cfg.gradient))
        self.baseline = None

    def scenario_terms(self, z) -> tuple[dict, object]:
        """Every objective term of every scenario, ``{term: (S,)}``, and the traces (leading axis S)."""
        servo, hybrid = self.space.apply(z)
        sc = self.scenarios

        def one(model, reference, path):
            trace = rollout(servo, model, reference, plant=sc.plant, rates=self.rates, outer=self.cfg.mode,
                            hybrid=hybrid if self.cfg.mode == "hybrid" else None)
            return objectives.terms(trace, servo, path, self.rates.dt_position,
                                    sharpness_force=self.cfg.sharpness_force), trace

        return jax.vmap(one)(sc.models, sc.reference, sc.path)

    def margins(self, z) -> dict:
        servo, _ = self.space.apply(z)
        return loop_margins(servo, self.load, mode=self.cfg.loop_mode)

    def objective(self, z, baseline):
        """``(J, aux)``; ``baseline`` holds each scenario's terms at the start (the normalisers)."""
        cfg = self.cfg
        t, traces = self.scenario_terms(z)
        per = sum(w * t[k] / baseline[k] for k, w in cfg.weights.items())
        per += PENALTY_WEIGHT * jax.nn.relu(t["force_peak"] / (cfg.force_peak_limit * baseline["force_peak"])
                                            - 1.0) ** 2
        per += PENALTY_WEIGHT * t["saturation"]
        total = jnp.mean(per) if cfg.aggregate == "mean" else jnp.max(per)
        for loop in self.margins(z).values():
            pm = jnp.minimum(loop["phase_margin_deg"], 180.0)
            gm = jnp.minimum(loop["gain_margin_db"], 60.0)
            total += PENALTY_WEIGHT * jnp.sum(jax.nn.relu((cfg.pm_min + 1.0 - pm) / 10.0) ** 2)
            total += PENALTY_WEIGHT * jnp.sum(jax.nn.relu((cfg.gm_min + 0.5 - gm) / 3.0) ** 2)
        return total, {"scenarios": per, "terms": t, "traces": traces}

    def start_baseline(self):
        """The terms at the start, from one call of the compiled gradient (normalisers of 1: no new compile)."""
        if self.baseline is None:
            ones = {k: jnp.ones(len(self.scenarios.names)) for k in objectives.TERMS}
            (_, aux), _ = self._value_and_grad(self.space.z0(), ones)
            self.baseline = aux["terms"]
        return self.baseline

    def value_and_grad(self, z):
        return self._value_and_grad(z, self.start_baseline())

    def window_metrics(self, z) -> dict:
        """``{scenario: (metrics, plot arrays)}`` of the training windows at ``z``, from the compiled gradient."""
        (_, aux), _ = self.value_and_grad(z)
        servo, hybrid = self.space.host_values(z)
        out = {}
        for k, name in enumerate(self.scenarios.names):
            pick = functools.partial(jax.tree.map, lambda x: np.asarray(x[k]))
            out[name] = machine_metrics(pick(aux["traces"]), servo, np.asarray(self.scenarios.path[k]),
                                        pick(self.scenarios.reference), self.cfg.mode, self.rates.dt_position,
                                        hybrid if self.cfg.mode == "hybrid" else None)
        return out


def _save_atomic(path: Path, state: dict) -> None:
    arrays = {k: jax.tree.map(np.asarray, state[k]) for k in ("z", "opt", "best_z")}  # off the device
    write_atomic(path, pickle.dumps(state | arrays))


def load_checkpoint(path: Path, digest: str) -> dict | None:
    """The checkpoint at ``path`` if it exists; an error if it belongs to another configuration."""
    if not path.exists():
        return None
    try:
        with open(path, "rb") as f:
            state = pickle.load(f)
    except (OSError, pickle.UnpicklingError, EOFError) as e:
        raise ParameterError(f"{path}: unreadable checkpoint ({e}); delete it or use --fresh") from None
    if state.get("digest") != digest:
        raise ParameterError(f"{path}: checkpoint of another configuration (hash {state.get('digest')}, this one "
                             f"{digest}); use --fresh or another --out")
    return state


def optimise(value_and_grad: Callable, z0: dict, project: Callable, *, iterations: int, learning_rate: float,
             clip_norm: float = 1.0, final_lr_fraction: float = 1.0, starts: int = 1, start_spread: float = 0.0,
             seed: int = 0,
             checkpoint: Path | None = None, checkpoint_every: int = 5, digest: str = "",
             progress: Callable | None = None) -> dict:
    """Minimise from ``z0`` (and ``starts - 1`` perturbed starts); returns the best ``z`` and the history.

    ``value_and_grad(z) -> ((value, aux), grad)``.  With ``checkpoint``, the state is saved
    every ``checkpoint_every`` iterations and at the end of each start, and a run that
    finds one continues from it (bit-identical to an uninterrupted run: every random draw
    is made from ``seed`` and the start index).
    """
    schedule = optax.cosine_decay_schedule(learning_rate, iterations, alpha=final_lr_fraction)
    opt = optax.chain(optax.clip_by_global_norm(clip_norm), optax.adam(schedule))
    state = load_checkpoint(checkpoint, digest) if checkpoint else None
    if state is None:
        state = {"digest": digest, "start": 0, "iteration": 0, "z": None, "opt": None, "history": [],
                 "best_value": np.inf, "best_z": None, "done": False}
    t_start = time.perf_counter()
    while not state["done"]:
        k = state["start"]
        if state["z"] is None:
            z = dict(z0)
            if k > 0:
                keys = jax.random.split(jax.random.PRNGKey(seed + 1000 * k), len(z))
                z = project({n: v + start_spread * jax.random.normal(key, jnp.shape(v))
                             for (n, v), key in zip(sorted(z.items()), keys)})
            state["z"], state["opt"] = z, opt.init(z)
        z, opt_state = jax.tree.map(jnp.asarray, state["z"]), state["opt"]

        def note(z, value, iteration):  # history entry, and the best point so far
            state["history"].append({"start": k, "iteration": iteration, "objective": value,
                                     "z": {n: np.asarray(v).tolist() for n, v in z.items()}})
            if value < state["best_value"]:
                state["best_value"], state["best_z"] = value, {n: np.asarray(v) for n, v in z.items()}

        while state["iteration"] < iterations:
            (value, aux), grad = value_and_grad(z)
            value = float(value)
            if not np.isfinite(value) or not all(np.isfinite(np.asarray(g)).all() for g in grad.values()):
                raise FloatingPointError(f"tune: non-finite objective or gradient at start {k}, "
                                         f"iteration {state['iteration']} (value {value})")
            note(z, value, state["iteration"])
            updates, opt_state = opt.update(grad, opt_state, z)
            z = project(optax.apply_updates(z, updates))
            state["iteration"] += 1
            state["z"], state["opt"] = z, opt_state
            if progress:
                progress(k, state["iteration"], iterations, value, state["best_value"], aux,
                         time.perf_counter() - t_start)
            if checkpoint and state["iteration"] % checkpoint_every == 0:
                _save_atomic(checkpoint, state)
        (value, _), _ = value_and_grad(z)  # the last step's result is evaluated too: it may be the best
        note(z, float(value), iterations)
        state.update(start=k + 1, iteration=0, z=None, opt=None, done=k + 1 >= starts)
        if checkpoint:
            _save_atomic(checkpoint, state)
    return {"z": state["best_z"], "objective": state["best_value"], "history": state["history"]}


def print_progress(start, iteration, iterations, value, best, aux, elapsed, starts=1, stream=sys.stderr):
    """A line per iteration: ``tune [start 1/1] [#####.....] 12/25 J=0.7342 best=0.7310 3.1 s/it, ETA 40 s``.

    The bar covers the whole run (every start); a line each, so that logs of batch jobs keep the history.
    """
    done = start * iterations + iteration
    total = starts * iterations
    rate = elapsed / max(done, 1)
    filled = round(20 * done / total)
    print(f"tune [start {start + 1}/{starts}] [{'#' * filled}{'.' * (20 - filled)}] {iteration}/{iterations} "
          f"J={value:.4f} best={best:.4f} {rate:.1f} s/it, ETA {rate * (total - done):.0f} s", file=stream, flush=True)
