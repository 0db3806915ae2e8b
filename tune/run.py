"""The tuning problem (objective over scenarios) and the optimiser loop with checkpoints.

The objective at log-parameters ``z`` is, per scenario (path x kinematic-error seed x payload),
``sum_k w_k term_k(z) / term_k(z0)`` over the weighted :mod:`pusupu_jax.objectives` terms of its
training windows joined end to end (``cfg.windows`` windows of ``cfg.window_s`` spread over the
whole path, every window of every scenario in one vmapped batch), plus penalties: the smooth branch-force peak above
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
import io
import json
import os
import sys
import time
import warnings
import zipfile
import zlib
from pathlib import Path
from typing import Callable

import jax
import jax.numpy as jnp
import numpy as np
import optax

from pusupu_jax import inputs, machine_file, objectives, workload
from pusupu_jax.cascade import control_mode
from pusupu_jax.files import write_atomic
from pusupu_jax.gradients import value_and_grad
from pusupu_jax.hybrid import HybridGains
from pusupu_jax.inputs import shown
from pusupu_jax.machine import machine_metrics, machine_plant, machine_rates, machine_reference
from pusupu_jax.margins import loop_margins
from pusupu_jax.machine_file import Machine
from pusupu_jax.params import AxisLoad, ParameterError, ServoParams, stack
from pusupu_jax.plant.geometry import Geometry
from pusupu_jax.plant.model import ModelOptions
from pusupu_jax.programs import Program, describe
from pusupu_jax.sim import rollout, run_chunked
from pusupu_jax.paths import path_label, platform_path_from

from .config import TuneConfig
from .space import Space

HERE = Path(__file__).parent  # the tuner's source, which its traced programs depend on (pusupu_jax.programs)
PENALTY_WEIGHT = 100.0
GRADIENTS_KEPT = 4  # compiled gradients kept for Problems built again with the same structure (Problem.__init__)


@dataclasses.dataclass(frozen=True, eq=False)
class ScenarioSpec:
    """One scenario: a path (a name or a path file, :func:`pusupu_jax.paths.platform_path_from`; the first ``path_s``
    seconds of it, or all) on a machine with ``options`` (seeded kinematic errors, payload) and the nominal geometry
    ``geometry`` (None: :meth:`Geometry.default`)."""

    name: str
    trajectory: str
    options: ModelOptions = ModelOptions()
    geometry: Geometry | None = None
    path_s: float | None = None

    def geom(self) -> Geometry:
        return Geometry.default() if self.geometry is None else self.geometry

    def path(self, rates):
        """The platform poses ``(N, 5)`` about the geometry's home, one per position period (checked later)."""
        path = platform_path_from(self.trajectory, self.geom().home, rates)
        return path if self.path_s is None else path[: max(3, int(round(self.path_s / rates.dt_position)))]


def scenario_list(cfg: TuneConfig, machine: Machine | None = None) -> list[ScenarioSpec]:
    """Every scenario of the configuration on ``machine`` (default: the built-in one), named ``arc``, ``arc/seed3``,
    ``p2p/seed3/10kg``... (a path file by its stem; a payload scenario adds its mass to the machine's payload, at the
    same centre of mass)."""
    machine = Machine.default() if machine is None else machine
    base = machine.options()
    return [
        ScenarioSpec(
            path_label(kind) + (f"/seed{seed}" if seed is not None else "") + (f"/{payload:g}kg" if payload else ""),
            kind,
            dataclasses.replace(base, kin_error_seed=seed, payload=base.payload + float(payload)),
            geometry=machine.geometry,
            path_s=cfg.path_s,
        )
        for kind in cfg.trajectories
        for seed in cfg.kin_error_seeds
        for payload in cfg.payloads
    ]


@dataclasses.dataclass(frozen=True)
class Scenarios:
    """Scenarios, and the training windows spread over each path.

    Each path of ``N`` periods is padded with its last pose to ``K * every`` periods (``K =
    cfg.windows``, ``every = ceil(N / K)``); window ``k`` is its ``W`` periods from ``k * every``
    (``W = cfg.window_s``), started from the carry a forward pass over the whole path has there.
    Seeds, payloads and geometries enter as :meth:`MJXPlant.variant` models.
    """

    names: list
    lengths: list  # its unpadded number of periods
    paths: list  # its platform poses (N, 5), unpadded
    plant: object  # the nominal MJXPlant (structure and static fields)
    groups: (
        dict  # padded length -> (scenario indices, stacked models (S_k, ...), stacked references (S_k, K every, ...))
    )
    group_of: list  # the padded length of each scenario (its key in ``groups``)
    windows: int
    window_models: object  # (S K, ...) in scenario-major order
    window_reference: object  # (S K, W, ...)
    window_path: object  # (S K, W, 5)

    @classmethod
    def build(cls, cfg: TuneConfig, servo: ServoParams, rates, specs: list[ScenarioSpec] | None = None) -> "Scenarios":
        """The scenarios ``specs`` (default: the configuration's); a path outside the workspace raises
        :class:`~pusupu_jax.plant.geometry.GeometryError` naming the scenario."""
        specs = scenario_list(cfg) if specs is None else specs
        K, W = cfg.windows, max(3, int(round(cfg.window_s / rates.dt_position)))
        plant = machine_plant(ModelOptions())
        lengths, cut, models, refs, padded_paths = [], [], [], [], []
        for spec in specs:
            path = spec.path(rates)
            every = -(-len(path) // K)
            if W > every:
                raise ParameterError(
                    f"scenario {spec.name}: window_s expected at most a {K}th of the {spec.trajectory} "
                    f"path ({every * rates.dt_position:g} s), got {cfg.window_s}"
                )
            padded = np.concatenate([path, np.repeat(path[-1:], K * every - len(path), axis=0)])
            try:
                refs.append(
                    machine_reference(servo, padded, cfg.mode, options=spec.options, rates=rates, geom=spec.geom())
                )
                models.append(plant.variant(spec.options, spec.geometry))
            except ParameterError as e:
                raise type(e)(f"scenario {spec.name}: {e}") from None
            lengths.append(len(path))
            cut.append(path)
            padded_paths.append(padded)
        group_of = [len(p) for p in padded_paths]
        groups = {}
        for n in dict.fromkeys(group_of):
            idx = [i for i, g in enumerate(group_of) if g == n]
            groups[n] = (idx, stack([models[i] for i in idx]), stack([refs[i] for i in idx]))
        pick = [(i, k * (group_of[i] // K)) for i in range(len(specs)) for k in range(K)]
        return cls(
            [s.name for s in specs],
            lengths,
            cut,
            plant,
            groups,
            group_of,
            K,
            stack([models[i] for i, _ in pick]),
            stack([jax.tree.map(lambda x: np.asarray(x)[a : a + W], refs[i]) for i, a in pick]),
            np.stack([padded_paths[i][a : a + W] for i, a in pick]),
        )

    def whole(self, servo, hybrid, models, references, mode: str, rates, batched: bool = False):
        """The forward pass over whole paths of one group (``models``, ``references`` ``(n, K every, ...)``):
        ``(traces (n, K every, ...), carries at the window starts (n, K, ...))``.  ``servo`` and ``hybrid`` are shared,
        or one set per path when ``batched``.  One compiled chunk of :func:`~pusupu_jax.sim.run_chunked` serves every
        path length."""
        length = jax.tree.leaves(references)[0].shape[1]
        hybrid_mode = control_mode(mode).hybrid
        return run_chunked(
            servo,
            models,
            references,
            plant=self.plant,
            rates=rates,
            outer=mode,
            hybrid=hybrid if hybrid_mode else None,
            params_axis=0 if batched else None,
            hybrid_axis=0 if batched and hybrid_mode else None,
            marks=tuple(range(0, length, length // self.windows)),
        )

    def reference(self, i: int):
        """Scenario ``i``'s reference over its unpadded path (host arrays)."""
        idx, _, refs = self.groups[self.group_of[i]]
        return jax.tree.map(lambda x: np.asarray(x)[idx.index(i), : self.lengths[i]], refs)


GRADIENT_COST = 3  # forward passes a reverse-mode gradient costs, about (its forward pass, then the backward one)


def check_work(cfg: TuneConfig, specs: list[ScenarioSpec] | None = None, where: str = "tune config") -> None:
    """Before anything is built: the mechanical steps of the machine that tuning ``specs`` (default: the
    configuration's scenarios) with ``cfg`` implies, within :func:`pusupu_jax.workload.check_tuning`: one gradient's
    (scenarios x windows x window length) and all of them: ``cfg.starts x (iterations + 1)`` gradients and the start's
    (:data:`GRADIENT_COST` forward passes each), forward passes over the whole paths every ``refresh_every`` iterations
    of each start, and before and after the run and the baselines."""
    rates = machine_rates()
    specs = scenario_list(cfg) if specs is None else specs
    per_period = rates.n_velocity * rates.n_position // rates.n_mech
    window = max(3, int(round(cfg.window_s / rates.dt_position)))
    gradient = len(specs) * cfg.windows * window * per_period
    paths = sum(len(spec.path(rates)) for spec in specs) * per_period
    passes = cfg.starts * (-(-cfg.iterations // cfg.refresh_every) + 1) + 3 + len(cfg.baselines)
    workload.check_tuning(
        where, gradient, (cfg.starts * (cfg.iterations + 1) + 1) * GRADIENT_COST * gradient + passes * paths
    )


def scenario_objective(cfg: TuneConfig, t: dict, baseline: dict):
    """Each scenario's objective ``(S,)`` from its terms ``t`` and its start terms ``baseline`` (``{term: (S,)}``):
    the weighted terms over their start values, and the penalties on the force peak and saturation."""
    per = sum(w * t[k] / baseline[k] for k, w in cfg.weights.items())
    per += PENALTY_WEIGHT * jax.nn.relu(t["force_peak"] / (cfg.force_peak_limit * baseline["force_peak"]) - 1.0) ** 2
    return per + PENALTY_WEIGHT * t["saturation"]


def aggregate(cfg: TuneConfig, per, margins: dict):
    """The problem's objective: the scenarios' mean (or max) plus the penalties on every loop margin below the
    floors."""
    total = jnp.mean(per, axis=-1) if cfg.aggregate == "mean" else jnp.max(per, axis=-1)
    for loop in margins.values():
        pm = jnp.minimum(loop["phase_margin_deg"], 180.0)
        gm = jnp.minimum(loop["gain_margin_db"], 60.0)
        total += PENALTY_WEIGHT * jnp.sum(jax.nn.relu((cfg.pm_min + 1.0 - pm) / 10.0) ** 2)
        total += PENALTY_WEIGHT * jnp.sum(jax.nn.relu((cfg.gm_min + 0.5 - gm) / 3.0) ** 2)
    return total


def whole_path_metrics(cfg: TuneConfig, sc: Scenarios, i: int, trace, servo, hybrid, rates) -> tuple:
    """:func:`~pusupu_jax.machine.machine_metrics` of scenario ``i``'s forward pass over its whole (padded) path."""
    n = sc.lengths[i]
    return machine_metrics(
        jax.tree.map(lambda x: np.asarray(x)[:n], trace),
        servo,
        sc.paths[i],
        sc.reference(i),
        cfg.mode,
        rates.dt_position,
        hybrid if control_mode(cfg.mode).hybrid else None,
    )


def join_windows(x, S: int, K: int):
    """``(S K, W, ...) -> (S, K W, ...)``: each scenario's windows end to end (``(S K,) -> (S, K)``)."""
    return x.reshape((S, K * x.shape[1]) + x.shape[2:]) if x.ndim >= 2 else x.reshape(S, K)


class WindowStarts:
    """What :class:`Problem` and :class:`pusupu_jax.tune.batch.BatchProblem` share: the training windows' start states,
    renewed
    by ``refresh(z)`` (a forward pass over the whole paths), and the normalisers at the start ``z0()``.

    A subclass sets ``cfg``, ``windows``, ``_value_and_grad(z, baseline, starts, windows)`` and ``rows`` (the
    length of each term's vector) and defines ``z0()`` and ``refresh(z)``, which sets ``starts`` and ``_starts_z``.
    """

    baseline = None
    starts = None  # window start carries (rows K, ...)
    _starts_z = None

    def prepare(self, z, iteration: int) -> None:
        """Before iteration ``iteration``: renew the start states every ``refresh_every`` iterations (and when
        missing)."""
        same = self._starts_z is not None and all(
            np.array_equal(np.asarray(z[k]), v) for k, v in self._starts_z.items()
        )
        if self.starts is None or (iteration % self.cfg.refresh_every == 0 and not same):
            self.refresh(z)

    def start_baseline(self):
        """The terms at the start, from one call of the compiled gradient (normalisers of 1: no new compile)."""
        if self.baseline is None:
            kept = (self.starts, self._starts_z)  # a resumed run has its own starts already: keep them
            z0 = self.z0()
            self.refresh(z0)
            ones = {k: jnp.ones(self.rows) for k in objectives.TERMS}
            (_, aux), _ = self._value_and_grad(z0, ones, self.starts, self.windows)
            self.baseline = aux["terms"]
            if kept[0] is not None:
                self.starts, self._starts_z = kept
        return self.baseline


class Problem(WindowStarts):
    """The objective of a :class:`TuneConfig` (its scenarios, or ``specs``) around the start ``servo0``, ``hybrid0``.

    Training windows start from the states of a forward pass over the whole paths at the
    current gains (:meth:`refresh`, every ``cfg.refresh_every`` iterations: :meth:`prepare`); the
    gradient runs every window of every scenario as one vmapped batch, and cuts the
    dependence of the windows' start states on the gains (truncated backpropagation).
    """

    def __init__(
        self,
        cfg: TuneConfig,
        servo0: ServoParams,
        hybrid0: HybridGains,
        specs: list[ScenarioSpec] | None = None,
        digest: str | None = None,
        load: AxisLoad | None = None,
    ):
        self.cfg = cfg
        self.digest = cfg.digest() if digest is None else digest  # what a checkpoint must match to be resumed
        self.rates = machine_rates()
        self.space = Space.create(
            cfg.groups, servo0.replace(imc_form=cfg.imc_form), hybrid0, shared=cfg.shared, bounds=cfg.bounds
        )
        self.scenarios = sc = Scenarios.build(cfg, self.space.servo0, self.rates, specs)
        # the windows' models, references and paths enter the gradient as arguments, not as constants folded into
        # the compiled program (constants cost compile time, and change its cache key with their last bits)
        self.windows = (sc.window_models, sc.window_reference, jnp.asarray(sc.window_path))
        # the margin constraints' single-axis load: the machine's (machine_file.axis_load; default the built-in one's)
        self.load = machine_file.axis_load(Machine.default()) if load is None else load
        self.rows = len(sc.names)
        self._value_and_grad = _shared_gradient(self)

    def run_paths(self, z) -> list:
        """The forward pass over every scenario's whole path at ``z``: ``[(trace (K every, ...), carries (K,
        ...))]``."""
        servo, hybrid = self.space.apply(z)
        out = [None] * len(self.scenarios.names)
        for idx, models, refs in self.scenarios.groups.values():
            traces, carries = self.scenarios.whole(servo, hybrid, models, refs, self.cfg.mode, self.rates)
            for j, i in enumerate(idx):
                out[i] = jax.tree.map(lambda x: x[j], (traces, carries))
        return out

    def refresh(self, z) -> None:
        """Renew the windows' start states from a forward pass over the whole paths at ``z``."""
        runs = self.run_paths(z)
        self.starts = jax.tree.map(lambda *c: jnp.concatenate(c), *[carries for _, carries in runs])
        self._starts_z = {k: np.asarray(v) for k, v in z.items()}

    def z0(self) -> dict:
        return self.space.z0()

    def scenario_terms(self, z, starts, windows) -> tuple[dict, object]:
        """Every objective term of every scenario over its ``windows`` (models, references, paths), ``{term: (S,)}``,
        and the window traces."""
        servo, hybrid = self.space.apply(z)
        sc = self.scenarios

        def one(model, reference, init):
            return rollout(
                servo,
                model,
                reference,
                plant=sc.plant,
                rates=self.rates,
                outer=self.cfg.mode,
                hybrid=hybrid if control_mode(self.cfg.mode).hybrid else None,
                init=init,
                remat=self.cfg.remat,
            )

        models, reference, path = windows
        traces = jax.vmap(one)(models, reference, starts)
        S, K = len(sc.names), sc.windows
        joined = jax.tree.map(lambda x: join_windows(x, S, K), traces)
        path = join_windows(path, S, K)
        terms = jax.vmap(
            lambda tr, p: objectives.terms(
                tr, servo, p, self.rates.dt_position, sharpness_force=self.cfg.sharpness_force
            )
        )(joined, path)
        return terms, traces

    def margins(self, z) -> dict:
        servo, _ = self.space.apply(z)
        return loop_margins(servo, self.load, mode=self.cfg.mode)

    def objective(self, z, baseline, starts, windows):
        """``(J, aux)``; ``baseline`` holds each scenario's terms at the start (the normalisers)."""
        t, traces = self.scenario_terms(z, starts, windows)
        per = scenario_objective(self.cfg, t, baseline)
        return aggregate(self.cfg, per, self.margins(z)), {"scenarios": per, "terms": t}

    def value_and_grad(self, z):
        return self._value_and_grad(z, self.start_baseline(), self.starts, self.windows)

    def tune(self, *, checkpoint: Path | None = None, progress: Callable | None = None) -> "OptimiseResult":
        """:func:`optimise` from the start gains with the config's optimiser, starts and seed (what ``pusupu tune``
        runs); ``checkpoint``: its file (saved every ``cfg.checkpoint_every`` iterations, resumed from)."""
        cfg = self.cfg
        return optimise(
            self.value_and_grad,
            self.space.z0(),
            self.space.project,
            iterations=cfg.iterations,
            learning_rate=cfg.learning_rate,
            clip_norm=cfg.clip_norm,
            final_lr_fraction=cfg.final_lr_fraction,
            starts=cfg.starts,
            start_spread=cfg.start_spread,
            seed=cfg.seed,
            checkpoint=checkpoint,
            checkpoint_every=cfg.checkpoint_every,
            digest=self.digest,
            prepare=self.prepare,
            progress=progress,
        )

    def path_metrics(self, z) -> dict:
        """``{scenario: (metrics, plot arrays)}`` on the whole paths at ``z``, from the same compiled forward pass."""
        servo, hybrid = self.space.host_values(z)
        sc = self.scenarios
        out = {}
        for i, (trace, _) in enumerate(self.run_paths(z)):
            out[sc.names[i]] = whole_path_metrics(self.cfg, sc, i, trace, servo, hybrid, self.rates)
        return out


CHECKPOINT, CHECKPOINT_FORMAT = "checkpoint.npz", "pusupu-checkpoint-1"


_GRADIENTS: dict = {}


def structure_key(problem: WindowStarts, *layout) -> str:
    """A stable description (:func:`pusupu_jax.programs.describe`) of what a problem's objective reads from it besides
    its arguments: the configuration (every setting), the tuned fields around their start (``space``), the nominal
    plant's options, the rates, the load of the margins, the number of rows, and ``layout`` (a subclass's own), with
    the problem's class."""
    space = problem.space
    start = (space.servo0, space.hybrid0, problem.load)
    # the weights' order too: the objective sums its terms in it, and the digest sorts them
    return describe(
        (
            type(problem),
            problem.cfg.digest(),
            tuple(problem.cfg.weights),
            problem.scenarios.plant.options,
            problem.rates,
            problem.rows,
            space.fields,
            space.shared,
            start,
            jax.tree.structure(start),
            layout,
        )
    )


def _shared_gradient(problem: Problem) -> Program:
    """The jitted ``value_and_grad`` of ``problem.objective``, or that of an earlier Problem of the same structure.

    The objective reads from its Problem only what :func:`structure_key` holds; the scenarios' windows, start states
    and normalisers are arguments.  So Problems that differ only in their scenarios (seeds, payloads, geometry
    arrays, paths) share one trace and one compile: tracing the gradient of the MJX rollout takes about half a minute
    on this CPU, each time a new function is jitted.  The same key names the traced program on disk
    (:class:`pusupu_jax.programs.Program`), so that a later process loads it instead of tracing.
    """
    key = structure_key(problem)
    if key not in _GRADIENTS:
        while len(_GRADIENTS) >= GRADIENTS_KEPT:
            _GRADIENTS.pop(next(iter(_GRADIENTS)))
        # the file's name is taken again when it is traced: a configuration whose dicts (weights, bounds) were edited
        # in place since this Problem was built is traced under its own name, not under this key's
        _GRADIENTS[key] = Program(
            value_and_grad(problem.objective, problem.cfg.gradient), lambda: structure_key(problem), sources=(HERE,)
        )
    return _GRADIENTS[key]


def save_checkpoint(path: Path, state: dict) -> None:
    """The optimiser state as one ``.npz`` of arrays (``z/<field>``, ``best/<field>``, ``opt/<k>``: the optax state's
    leaves in order) plus its JSON ``meta`` (digest, counters, history), written atomically."""
    arrays = {f"z/{k}": np.asarray(v) for k, v in (state["z"] or {}).items()}
    arrays |= {f"best/{k}": np.asarray(v) for k, v in (state["best_z"] or {}).items()}
    if state["opt"] is not None:
        arrays |= {f"opt/{k}": np.asarray(leaf) for k, leaf in enumerate(jax.tree.leaves(state["opt"]))}
    meta = {k: v for k, v in state.items() if k not in ("z", "best_z", "opt")}
    meta = {"format": CHECKPOINT_FORMAT, **meta, "best_value": np.asarray(meta["best_value"], dtype=float).tolist()}
    buffer = io.BytesIO()
    np.savez(buffer, meta=np.frombuffer(json.dumps(meta).encode(), dtype=np.uint8), **arrays)
    write_atomic(path, buffer.getvalue())


NPY_HEADER = 4096  # bytes: at most an array's .npy header in a checkpoint (numpy writes 128)
ZIP_RECORD = 1024  # bytes: at most a member's records in the zip (local and central headers, name, zip64 fields)
# what reading a crafted zip, .npy or JSON raises (ValueError covers JSON's and UTF-8's errors; RecursionError: nesting)
CHECKPOINT_ERRORS = (
    OSError,
    ValueError,
    KeyError,
    EOFError,
    NotImplementedError,
    RecursionError,
    zipfile.BadZipFile,
    zlib.error,
)


@dataclasses.dataclass(frozen=True)
class CheckpointLayout:
    """What a checkpoint of one optimisation may hold, from its settings: :func:`load_checkpoint` checks a file against
    it before it loads any array.

    ``z``: the log-parameters ``{field: array}``, whose shapes and dtypes ``z/<field>`` and ``best/<field>`` have;
    ``opt``: an optax state of the right structure, whose leaves ``opt/<k>`` are; ``iterations``, ``starts``: each
    start evaluates ``iterations + 1`` points, one history entry each; ``members``: a batch's number of members (a
    history per member, of one start each, a best value per member, and the failed members), None for one problem.
    """

    z: dict
    opt: object
    iterations: int
    starts: int = 1
    members: int | None = None

    def arrays(self) -> dict:
        """``{name: (shape, dtype)}`` of every array but ``meta`` that a checkpoint may hold."""
        out = {f"{group}/{k}": (np.shape(v), np.asarray(v).dtype) for group in ("z", "best") for k, v in self.z.items()}
        return out | {
            f"opt/{k}": (np.shape(leaf), np.asarray(leaf).dtype) for k, leaf in enumerate(jax.tree.leaves(self.opt))
        }

    def entries(self) -> int:
        """History entries of one history (a member's in a batch) at most."""
        return (self.iterations + 1) * (1 if self.members else self.starts)

    def meta_bytes(self) -> int:
        """At most the JSON ``meta`` [bytes]: every history entry with its ``z`` (32 characters a number), a best value
        and a failure message per member."""
        members = self.members or 1
        values = sum(np.size(v) for v in self.z.values()) // members
        return 4096 + members * (self.entries() * (256 + 32 * (values + len(self.z))) + 256)

    def file_bytes(self) -> int:
        """At most the whole file [bytes]: ``meta`` and every array, with their headers and records in the zip."""
        arrays = [int(np.prod(shape)) * dtype.itemsize for shape, dtype in self.arrays().values()]
        return self.meta_bytes() + sum(arrays) + (len(arrays) + 1) * (NPY_HEADER + ZIP_RECORD) + ZIP_RECORD


def _array_header(zf: zipfile.ZipFile, info: zipfile.ZipInfo, limit: int) -> tuple:
    """``(shape, dtype)`` of the array in member ``info``, from its declared size (at most ``limit`` bytes of data) and
    its .npy header alone: nothing else of it is decompressed."""
    if info.file_size > limit + NPY_HEADER:
        raise ValueError(
            f"{shown(info.filename)} declares {info.file_size} bytes, expected at most {limit + NPY_HEADER}"
        )
    with zf.open(info) as f:
        version = np.lib.format.read_magic(f)
        if version not in ((1, 0), (2, 0)):
            raise ValueError(f"{shown(info.filename)}: .npy version {version}, expected 1.0 or 2.0")
        read = np.lib.format.read_array_header_1_0 if version == (1, 0) else np.lib.format.read_array_header_2_0
        shape, _, dtype = read(f)
    if dtype.hasobject:
        raise ValueError(f"{shown(info.filename)}: an object array, expected numbers")
    return shape, dtype


def _check_meta(meta: dict, layout: CheckpointLayout) -> None:
    """The JSON ``meta`` of a checkpoint of ``layout``'s settings: its keys, counters and history entries."""
    batch = layout.members is not None
    keys = ("format", "digest", "iteration", "history", "best_value", "done") + (("failed",) if batch else ("start",))
    inputs.check_keys(meta, "meta", keys, ValueError, required=keys)
    inputs.integer(meta["iteration"], "meta.iteration", ValueError, low=0, high=layout.iterations)
    if not isinstance(meta["done"], bool):
        raise ValueError(f"meta.done: expected true or false, got {shown(meta['done'])}")
    if batch:
        histories, best = meta["history"], meta["best_value"]
        if not (
            isinstance(histories, list) and isinstance(best, list) and len(histories) == len(best) == layout.members
        ):
            raise ValueError(f"meta: expected a history and a best value for each of {layout.members} members")
        for m, value in enumerate(best):
            inputs.number(value, f"meta.best_value[{m}]", ValueError, finite=False)
        for m, message in inputs.check_keys(
            meta["failed"], "meta.failed", [str(m) for m in range(layout.members)], ValueError, what="member"
        ).items():
            if not isinstance(message, str):
                raise ValueError(f"meta.failed.{m}: expected a message, got {shown(message)}")
    else:
        histories = [meta["history"]]
        inputs.integer(meta["start"], "meta.start", ValueError, low=0, high=layout.starts)
        inputs.number(meta["best_value"], "meta.best_value", ValueError, finite=False)
    for m, history in enumerate(histories):
        where = f"meta.history[{m}]" if batch else "meta.history"
        if not isinstance(history, list) or len(history) > layout.entries():
            raise ValueError(f"{where}: expected a list of at most {layout.entries()} entries")
        for k, h in enumerate(history):
            inputs.check_keys(
                h,
                f"{where}[{k}]",
                ("start", "iteration", "objective", "z"),
                ValueError,
                required=("start", "iteration", "objective", "z"),
            )
            inputs.integer(h["start"], f"{where}[{k}].start", ValueError, low=0, high=layout.starts - 1)
            inputs.integer(h["iteration"], f"{where}[{k}].iteration", ValueError, low=0, high=layout.iterations)
            if isinstance(h["objective"], bool) or not isinstance(h["objective"], (int, float)):
                raise ValueError(f"{where}[{k}].objective: expected a number, got {shown(h['objective'])}")
            inputs.check_keys(h["z"], f"{where}[{k}].z", layout.z, ValueError, required=layout.z, what="field")


def load_checkpoint(path: Path, digest: str, layout: CheckpointLayout) -> dict | None:
    """The checkpoint at ``path`` if there is one (None otherwise), checked against ``layout`` (the run's settings).

    A regular file no larger than ``layout`` implies, read as plain arrays (``allow_pickle=False``: nothing in it
    runs).  Its ``meta`` is read first, and a checkpoint of another configuration (``digest``) refused; then every
    member's declared size, shape and dtype are checked from the zip's directory and the arrays' headers before any
    array is loaded (a zip bomb or a crafted header is refused, not decompressed), and its JSON; each group of arrays
    (``z``, ``best``, ``opt``) is whole or absent, and a run that evaluated anything has its best point.  Anything else
    is refused with one line (:class:`ParameterError`), never a traceback.
    """
    if not os.path.lexists(path):
        return None
    fix = "delete it or use --fresh"
    try:
        data = inputs.read_bytes(path, "pusupu checkpoint", ParameterError, limit=layout.file_bytes())
    except ParameterError as e:
        raise ParameterError(f"{e}; {fix}") from None
    try:
        with zipfile.ZipFile(io.BytesIO(data)) as zf:
            infos = {info.filename: info for info in zf.infolist()}
            if len(infos) != len(zf.infolist()) or "meta.npy" not in infos:
                raise ValueError("expected one member of each name, meta.npy among them")
            shape, dtype = _array_header(zf, infos["meta.npy"], layout.meta_bytes())
            if dtype != np.uint8 or len(shape) != 1 or shape[0] > layout.meta_bytes():
                raise ValueError(f"meta: expected at most {layout.meta_bytes()} bytes, got {dtype} of shape {shape}")
            with np.load(io.BytesIO(data), allow_pickle=False) as f:
                meta = json.loads(bytes(f["meta"]).decode())
                if not isinstance(meta, dict) or meta.get("format") != CHECKPOINT_FORMAT:
                    raise ValueError(f"not a {CHECKPOINT_FORMAT} file")
                if meta.get("digest") != digest:
                    raise ParameterError(
                        f"{path}: checkpoint of another configuration (hash "
                        f"{shown(meta.get('digest'))}, this one {digest}); use --fresh or another --out"
                    )
                expected = layout.arrays()
                for name, info in infos.items():
                    key = name.removesuffix(".npy")
                    if key == "meta":
                        continue
                    if not name.endswith(".npy") or key not in expected:
                        raise ValueError(f"unexpected member {shown(name)}")
                    want = expected[key]
                    got = _array_header(zf, info, int(np.prod(want[0])) * want[1].itemsize)
                    if got != want:
                        raise ValueError(
                            f"{key}: expected {want[1]} of shape {want[0]}, got {got[1]} of shape {got[0]}"
                        )
                _check_meta(meta, layout)
                groups = {g: sorted(k for k in expected if k.startswith(g + "/")) for g in ("z", "best", "opt")}
                held = {g: [k for k in names if k + ".npy" in infos] for g, names in groups.items()}
                for g, names in held.items():
                    if names and names != groups[g]:
                        raise ValueError(f"{next(k for k in groups[g] if k not in names)} missing")
                needed = {"z": held["opt"], "best": meta["history"], "opt": held["z"]}  # or every group in a batch
                missing = [g for g, need in needed.items() if (need or layout.members) and not held[g]]
                if missing:
                    raise ValueError(f"missing arrays: {', '.join(missing)}")
                arrays = {k: np.asarray(f[k]) for k in f.files if k != "meta"}
    except ParameterError:
        raise
    except CHECKPOINT_ERRORS as e:
        raise ParameterError(f"{path}: not a pusupu checkpoint ({e}); {fix}") from None
    z = {k[2:]: v for k, v in arrays.items() if k.startswith("z/")} or None
    best = {k[5:]: v for k, v in arrays.items() if k.startswith("best/")} or None
    leaves = [arrays[f"opt/{k}"] for k in range(len(held["opt"]))]
    opt = jax.tree.unflatten(jax.tree.structure(layout.opt), leaves) if leaves else None
    return {**{k: v for k, v in meta.items() if k != "format"}, "z": z, "best_z": best, "opt": opt}


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


def progress_line(desc: str, done: int, total: int, summary: str, elapsed: float, first: tuple[int, float]) -> str:
    """One line of progress: ``tune [start 1/1] [#####.....] 12/25 J=0.7342 best=0.7310 3.1 s/it, ETA 40 s``.

    ``first``: ``(iterations done, elapsed s)`` at the first iteration this process ran, whose time includes the
    compile: the rate and the ETA leave it out, and that first line gives its time instead.
    """
    filled = round(20 * done / total)
    if done > first[0]:
        rate = (elapsed - first[1]) / (done - first[0])
        timing = f"{rate:.1f} s/it, ETA {rate * (total - done):.0f} s"
    else:
        timing = f"first iteration (with the compile) {elapsed:.0f} s"
    return f"{desc} [{'#' * filled}{'.' * (20 - filled)}] {done}/{total} {summary} {timing}"


def interactive(stream) -> bool:
    """Whether progress on ``stream`` is best a bar: a terminal, or the standard streams of a Jupyter kernel.

    Elsewhere (a log file, a pipe, a test's capture) progress stays one line per iteration.
    """
    if stream is sys.stderr or stream is sys.stdout:
        shell = getattr(sys.modules.get("IPython"), "get_ipython", lambda: None)()
        if shell is not None and "IPKernelApp" in getattr(shell, "config", {}):
            return True
    try:
        return bool(stream.isatty())
    except (AttributeError, ValueError):  # no isatty, or a closed stream
        return False


class ProgressBar:
    """A tqdm bar (:mod:`tqdm.auto`: a widget in a notebook) of iterations, started at the first one reported.

    That first iteration, which includes the compile, is kept apart: its time shows in the bar's postfix, and the
    bar's clock starts after it, so that its rate (s/it) and ETA are those of the compiled iterations.
    """

    def __init__(self, total: int, stream=sys.stderr):
        self.total, self.stream = total, stream
        self.bar, self.first = None, ""

    def update(self, done: int, elapsed: float, desc: str, postfix: str) -> None:
        if self.bar is None:
            with warnings.catch_warnings():  # a notebook without ipywidgets: tqdm's text bar, without its warning
                warnings.simplefilter("ignore")
                from tqdm.auto import tqdm

            self.first = f"first iteration (with the compile) {elapsed:.0f} s"
            self.bar = tqdm(
                total=self.total,
                initial=done,
                desc=desc,
                file=self.stream,
                unit="it",
                dynamic_ncols=True,
                postfix=f"{postfix}, {self.first}",
            )
        else:
            self.bar.set_description_str(desc, refresh=False)
            self.bar.set_postfix_str(f"{postfix}, {self.first}", refresh=False)
            self.bar.update(done - self.bar.n)
        if done >= self.total:
            self.close()

    def close(self) -> None:
        if self.bar is not None:
            self.bar.close()


class Progress:
    """Progress over iterations: a :class:`ProgressBar` where :func:`interactive`, else a :func:`progress_line` per
    iteration (logs of batch jobs keep the history). Both keep the first iteration this process ran, with the
    compile, out of the rate and the ETA. Call it with ``(done, total, elapsed s, description, summary)``."""

    def __init__(self, stream=sys.stderr):
        self.stream, self.first, self.bar = stream, None, None

    def __call__(self, done: int, total: int, elapsed: float, desc: str, summary: str) -> None:
        if self.first is None:
            self.first = (done, elapsed)
            self.bar = ProgressBar(total, self.stream) if interactive(self.stream) else None
        if self.bar is not None:
            return self.bar.update(done, elapsed, desc, summary)
        print(progress_line(desc, done, total, summary, elapsed, self.first), file=self.stream, flush=True)


def progress_reporter(starts: int = 1, stream=sys.stderr) -> Callable:
    """The ``progress`` callback of :func:`optimise` for ``pusupu tune`` and notebooks (:class:`Progress`); the
    bar covers every start."""
    report = Progress(stream)

    def progress(start, iteration, iterations, value, best, aux, elapsed):
        report(
            start * iterations + iteration,
            starts * iterations,
            elapsed,
            f"tune [start {start + 1}/{starts}]",
            f"J={value:.4f} best={best:.4f}",
        )

    return progress
