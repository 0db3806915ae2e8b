"""Many tuning problems of one shape in one compiled, vmapped gradient (the engine of ``pusupu batch``).

A *member* is one start of one problem: its log-gains ``z`` (a row of every leaf of ``zb``) and
its scenarios.  Members of independent problems share nothing; the members of a robust problem
share its scenarios.  Every member has the same number of scenarios, so that a *pair* (member,
scenario) list of ``Q = P x S_p`` entries, member-major, lays out every training window of the
batch as ``(Q K, W, ...)``: one ``rollout`` vmapped over all of them, as
:class:`pusupu_jax.tune.run.Problem` vmaps one problem's windows.  Each member's objective is exactly a
:class:`~pusupu_jax.tune.run.Problem`'s at its ``z`` (:func:`pusupu_jax.tune.run.scenario_objective`,
:func:`pusupu_jax.tune.run.aggregate`); the batch minimises their sum, whose gradient with respect to
member ``m``'s row is member ``m``'s own gradient, since no term couples two members.

:func:`optimise_batch` runs every member at once through the tuner's one engine
(:func:`pusupu_jax.tune.optimise.iterate`: the optax update vmapped, so clipping stays per member); a member whose
objective or gradient turns non-finite is frozen and reported, and the others go on.  With more than one device the
batch axis is sharded over all of them (``jax.sharding``), padded to a multiple of their number
with copies of the last member.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Callable

import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh, NamedSharding, PartitionSpec

from pusupu_jax import devices as placement, machine_file, objectives
from pusupu_jax.cascade import control_mode
from pusupu_jax.gradients import value_and_grad
from pusupu_jax.hybrid import HybridGains
from pusupu_jax.machine import machine_rates
from pusupu_jax.margins import envelope_margins
from pusupu_jax.machine_file import Machine
from pusupu_jax.params import ServoParams, stack
from pusupu_jax.programs import Program
from pusupu_jax.sim import rollout

from .config import TuneConfig
from .checkpoint import CheckpointLayout, load_checkpoint, save_checkpoint
from .optimise import iterate, optimiser, start_point, train_step
from .state import Evaluation, TunerState
from .run import (
    HERE,
    Scenarios,
    ScenarioSpec,
    WindowStarts,
    aggregate,
    join_windows,
    scenario_objective,
    structure_key,
    whole_path_metrics,
)
from .space import Space


def _take(tree, index):
    return jax.tree.map(lambda x: x[index], tree)


def lay_out(jobs: list[list[ScenarioSpec]]) -> tuple[list[ScenarioSpec], list[list[int]]]:
    """A :class:`BatchProblem`'s ``specs`` and ``problems`` for one list of scenarios per job, in order: every job's
    scenarios end to end, and each job's indices into them."""
    specs: list[ScenarioSpec] = []
    problems = []
    for scenarios in jobs:
        problems.append(list(range(len(specs), len(specs) + len(scenarios))))
        specs += scenarios
    return specs, problems


class BatchProblem(WindowStarts):
    """``problems`` (scenario index lists into ``specs``, all of one length) x ``starts`` members, one objective.

    ``devices``: the devices to shard the batch over (default every GPU of the chosen platform,
    :func:`pusupu_jax.devices.chosen_devices`, or one CPU device).  ``machine``: the machine that
    ``servo0`` and ``specs`` are on (default the built-in one), whose load the margin constraints take.
    """

    def __init__(
        self,
        cfg: TuneConfig,
        specs: list[ScenarioSpec],
        problems: list[list[int]],
        servo0: ServoParams,
        hybrid0: HybridGains,
        devices=None,
        machine: Machine | None = None,
    ):
        if len({len(p) for p in problems}) != 1:
            raise ValueError("BatchProblem: every problem needs the same number of scenarios")
        self.cfg = cfg
        self.rates = machine_rates()
        self.space = Space.create(
            cfg.groups, servo0.replace(imc_form=cfg.imc_form), hybrid0, shared=cfg.shared, bounds=cfg.bounds
        )
        # (its references not kept on disk: a batch may hold thousands of scenarios, each of a few MB)
        self.scenarios = sc = Scenarios.build(cfg, self.space.servo0, self.rates, specs, keep=False)
        # the margin constraints' loads, per problem (machine_file.margin_loads): ``machine``'s at home, and at the
        # lightest and the heaviest pose along the problem's paths with their payloads (on its scenarios' geometry)
        # (problems of the same scenarios share them: 28 ms each on 2 cores, minutes for thousands of problems)
        machine = Machine.default() if machine is None else machine
        loads: dict[tuple[int, ...], dict] = {}
        for p in map(tuple, problems):
            if p not in loads:
                runs = [machine_file.PathRun(sc.paths[i], specs[i].options, specs[i].geometry) for i in p]
                loads[p] = machine_file.margin_loads(machine, runs)
        self.loads = [loads[tuple(p)] for p in problems]
        self.problems = problems
        if devices is None:
            devices = placement.chosen_devices()
            # on the CPU one device: over several the gradient is jitted in each process (its traced program is kept
            # on disk for one device only), and tracing it again in every process and Ray worker cost more than the
            # split of the members over two cores gained (the suite's batch tests: 119 -> 150 s, 66 -> 175 s)
            devices = devices[:1] if devices[0].platform == "cpu" else devices
        self.devices = list(devices)
        members = [(j, k) for j in range(len(problems)) for k in range(cfg.starts)]
        self.n_real = len(members)
        members += [members[-1]] * (-len(members) % len(self.devices))  # padding: results discarded
        self.members = members
        self.pairs = [(m, s) for m, (j, _) in enumerate(members) for s in problems[j]]
        K = sc.windows
        windows = np.array([s * K + k for _, s in self.pairs for k in range(K)])
        self.window_member = np.array([m for m, _ in self.pairs for _ in range(K)])
        self.pair_member = np.array([m for m, _ in self.pairs])
        mesh = Mesh(np.array(self.devices), ("batch",))
        self.sharding = NamedSharding(mesh, PartitionSpec("batch"))
        # arguments of the gradient, not constants in it (as pusupu_jax.tune.run.Problem.windows): the windows,
        # and each member's margin loads, whole on every device
        self.windows = self.shard(
            (
                _take(sc.window_models, windows),
                _take(sc.window_reference, windows),
                jnp.asarray(sc.window_path)[windows],
            )
        ) + (jax.tree.map(jnp.asarray, stack([stack(list(self.loads[j].values())) for j, _ in members])),)
        self._apply = jax.jit(jax.vmap(self.space.apply))
        self.rows = len(self.pairs)  # the baseline's terms are per pair
        gradient = value_and_grad(self.objective, cfg.gradient)
        if (
            len(self.devices) == 1
        ):  # traced once for every process (Ray's workers, a resumed batch) that runs this layout
            self._value_and_grad = Program(
                gradient,
                lambda: structure_key(self, len(members), self.window_member, self.pair_member),
                sources=(HERE,),
            )
        else:  # sharded arguments: jitted as it is (an exported program is kept for one device)
            self._value_and_grad = jax.jit(gradient)

    def shard(self, tree):
        """``tree`` with its leading (batch) axis spread over the devices (a no-op on one)."""
        if len(self.devices) == 1:
            return jax.tree.map(jnp.asarray, tree)
        return jax.device_put(tree, self.sharding)

    def member_z(self, zb, m: int) -> dict:
        return {k: v[m] for k, v in zb.items()}

    def run_paths(self, zb, starts_only: bool = False) -> list:
        """The forward pass over every pair's whole path at its member's ``z``, per group of equal path lengths:
        ``[(pair indices, traces (n, K every, ...), carries (n, K, ...))]``; with ``starts_only``, for the windows'
        start states, to the last of them (the traces end there)."""
        sc = self.scenarios
        out = []
        for length, (idx, models, refs) in sc.groups.items():
            qs = np.array([q for q, (_, s) in enumerate(self.pairs) if sc.group_of[s] == length])
            local = np.array([idx.index(self.pairs[q][1]) for q in qs])
            servo, hybrid = self._apply(_take(zb, self.pair_member[qs]))
            traces, carries = sc.whole(
                servo,
                hybrid,
                _take(models, local),
                _take(refs, local),
                self.cfg.mode,
                self.rates,
                batched=True,
                to_end=not starts_only,
            )
            out.append((qs, traces, carries))
        return out

    def refresh(self, zb) -> None:  # members iterate in step: prepare() renews them all at once
        """Renew the windows' start states: every pair's carries, in pair order (one gather, no per-pair copies)."""
        runs = self.run_paths(zb, starts_only=True)
        order = np.argsort(np.concatenate([qs for qs, _, _ in runs]), kind="stable")
        carries = jax.tree.map(lambda *c: jnp.concatenate(c)[order], *[c for _, _, c in runs])
        self.starts = self.shard(jax.tree.map(lambda x: x.reshape((x.shape[0] * x.shape[1],) + x.shape[2:]), carries))
        self._starts_z = {k: np.asarray(v) for k, v in zb.items()}

    def objective(self, zb, baseline, starts, windows, start):
        """``(sum of the members' objectives, aux)``: aux ``value`` ``(P,)``, ``scenarios`` and ``terms`` ``(Q,)``;
        ``start`` the start point (:attr:`Space.start`) that gives the fields not tuned."""
        cfg, sc = self.cfg, self.scenarios
        hybrid_mode = control_mode(cfg.mode).hybrid

        def one(z, model, reference, init):
            servo, hybrid = self.space.apply(z, start)
            return rollout(
                servo,
                model,
                reference,
                plant=sc.plant,
                rates=self.rates,
                outer=cfg.mode,
                hybrid=hybrid if hybrid_mode else None,
                init=init,
                remat=cfg.remat,
            )

        models, reference, path = windows[:3]
        traces = jax.vmap(one)(_take(zb, self.window_member), models, reference, starts)
        Q, K = len(self.pairs), sc.windows
        joined = jax.tree.map(lambda x: join_windows(x, Q, K), traces)
        path = join_windows(path, Q, K)

        def terms(z, trace, p):
            return objectives.terms(
                trace, self.space.apply(z, start)[0], p, self.rates.dt_position, sharpness_force=cfg.sharpness_force
            )

        t = jax.vmap(terms)(_take(zb, self.pair_member), joined, path)
        per = scenario_objective(cfg, t, baseline)

        def member(z, per_member, loads):
            return aggregate(cfg, per_member, envelope_margins(self.space.apply(z, start)[0], loads, mode=cfg.mode))

        value = jax.vmap(member)(zb, per.reshape(len(self.members), -1), windows[3])
        return jnp.sum(value), {"value": value, "scenarios": per, "terms": t}

    def z0(self) -> dict:
        return {k: jnp.broadcast_to(v, (len(self.members),) + jnp.shape(v)) for k, v in self.space.z0().items()}

    def value_and_grad(self, zb):
        return self._value_and_grad(self.shard(zb), self.start_baseline(), self.starts, self.windows, self.space.start)

    def path_metrics(self, zb) -> list[dict]:
        """Per real member, ``{scenario: (metrics, plot arrays)}`` on the whole paths at its ``z``."""
        sc = self.scenarios
        out = [{} for _ in range(self.n_real)]
        for qs, traces, _ in self.run_paths(zb):
            traces = jax.tree.map(np.asarray, traces)
            for j, q in enumerate(qs):
                m, s = self.pairs[q]
                if m < self.n_real:
                    servo, hybrid = self.space.host_values(self.member_z(zb, m))
                    out[m][sc.names[s]] = whole_path_metrics(
                        self.cfg, sc, s, _take(traces, j), servo, hybrid, self.rates
                    )
        return out


@dataclasses.dataclass(frozen=True)
class BatchResult:
    """What :func:`optimise_batch` returns, per real member: ``best_value`` ``(n_real,)`` (the objective,
    dimensionless), ``best_z`` (field -> log-gains with the member axis first), ``history`` (per member, one
    :class:`~pusupu_jax.tune.state.Evaluation` per evaluation) and ``failed`` (``{member: message}``)."""

    best_value: np.ndarray
    best_z: dict[str, np.ndarray]
    history: list[list[Evaluation]]
    failed: dict[int, str]


def optimise_batch(
    problem: BatchProblem, *, checkpoint: Path | None = None, digest: str = "", progress: Callable | None = None
) -> BatchResult:
    """Every member of ``problem`` at once through the tuner's engine (:func:`pusupu_jax.tune.optimise.iterate`), with
    its configuration's settings; ``progress(iteration, iterations, values, elapsed)`` after each iteration.

    Returns a :class:`BatchResult` of the real members.  With ``checkpoint`` the state
    is saved every ``checkpoint_every`` iterations and at the end, and a run that finds one continues from it.
    """
    cfg = problem.cfg
    P = len(problem.members)
    opt = optimiser(cfg.learning_rate, cfg.iterations, cfg.clip_norm, cfg.final_lr_fraction)
    z0 = problem.space.z0()
    starts = [k for _, k in problem.members]
    zb = jax.tree.map(
        lambda *v: jnp.stack(v),
        *[start_point(z0, k, cfg.start_spread, cfg.seed, problem.space.project) for k in starts],
    )
    template = TunerState.fresh(digest, zb, jax.vmap(opt.init)(zb))
    layout = CheckpointLayout(zb, template.opt, cfg.iterations, cfg.starts, members=P, sequential=False)
    state = (load_checkpoint(checkpoint, digest, layout) if checkpoint else None) or template

    def evaluate(zb, iteration):
        problem.prepare(zb, iteration)
        (_, aux), grad = problem.value_and_grad(zb)
        return aux["value"], grad, aux

    def reported(state, values, aux, elapsed):
        progress(state.iteration, cfg.iterations, values[: problem.n_real], elapsed)

    if not state.done:
        iterate(
            state,
            evaluate,
            train_step(opt, problem.space.project, P),
            iterations=cfg.iterations,
            starts=starts,
            place=problem.shard,
            checkpoint=checkpoint,
            checkpoint_every=cfg.checkpoint_every,
            progress=reported if progress else None,
        )
        state.done = True
        if checkpoint:
            save_checkpoint(checkpoint, state)
    n = problem.n_real
    return BatchResult(
        best_value=state.best_value[:n],
        best_z={k: v[:n] for k, v in state.best_z.items()},
        history=state.history[:n],
        failed={m: msg for m, msg in state.failed.items() if m < n},
    )
