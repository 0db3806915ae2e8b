"""The tuning problem: scenarios, windows and the objective over them, with the compiled gradient that serves every
problem of one structure.

The objective at log-parameters ``z`` is, per scenario (path x kinematic-error seed x payload),
``sum_k w_k term_k(z) / term_k(z0)`` over the weighted :mod:`pusupu_jax.objectives` terms of its
training windows joined end to end (``cfg.windows`` windows of ``cfg.window_s`` spread over the
whole path, every window of every scenario in one vmapped batch), plus penalties: the smooth branch-force peak above
``force_peak_limit`` times its start value, current/voltage saturation, and every loop's
phase and gain margins (:mod:`pusupu_jax.margins`, single-axis model) below
``pm_min``/``gm_min``.  Scenarios are aggregated by their mean or maximum.

:meth:`Problem.tune` minimises it with :func:`pusupu_jax.tune.optimise.optimise` (the optimiser loop; checkpoints in
:mod:`pusupu_jax.tune.checkpoint`, progress lines in :mod:`pusupu_jax.tune.progress`).
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Callable

import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import NamedSharding, PartitionSpec

from pusupu_jax import devices, machine_draws, machine_file, objectives, workload
from pusupu_jax.cascade import control_mode
from pusupu_jax.gradients import value_and_grad
from pusupu_jax.hybrid import HybridGains, HybridReference
from pusupu_jax.machine import machine_metrics, machine_plant, machine_rates, machine_reference, with_drives
from pusupu_jax.margins import envelope_margins
from pusupu_jax.machine_file import Machine
from pusupu_jax.params import ParameterError, ServoParams, stack
from pusupu_jax.plant.geometry import Geometry
from pusupu_jax.plant.model import ModelOptions
from pusupu_jax.programs import Program, UnstableKey, describe, fingerprint
from pusupu_jax.chunked import carry_structure, run_chunked
from pusupu_jax.sim import rollout
from pusupu_jax.paths import check_path, path_label, platform_path_from

from .config import OBJECTIVE_SETTINGS, TuneConfig
from .optimise import OptimiseResult, optimise
from .space import Space
from . import starts as kept_starts

HERE = Path(__file__).parent  # the tuner's source, which its traced programs depend on (pusupu_jax.programs)
PENALTY_WEIGHT = 100.0
GRADIENTS_KEPT = 4  # compiled gradients kept for Problems built again with the same structure (Problem.__init__)


@dataclasses.dataclass(frozen=True, eq=False)
class ScenarioSpec:
    """One scenario: a path (a name or a path file, :func:`pusupu_jax.paths.platform_path_from`; the first ``path_s``
    seconds of it, or all) on a machine with ``options`` (seeded kinematic errors, payload) and the nominal geometry
    ``geometry`` (None: :meth:`Geometry.default`); ``drives``: the drive values of a machine drawn about the tuned one
    (:func:`pusupu_jax.machine_draws.plant_drives`, run as :class:`~pusupu_jax.plant.PlantDrives`: the machine file
    still the tuned machine's), or None: the tuned machine's own; ``told``: the options the host computes the
    reference with (the hybrid force feedforward's payload), where not ``options``: a drawn machine's payload is not
    the machine file's."""

    name: str
    trajectory: str
    options: ModelOptions = ModelOptions()
    geometry: Geometry | None = None
    path_s: float | None = None
    drives: dict | None = None
    told: ModelOptions | None = None

    def geom(self) -> Geometry:
        return Geometry.default() if self.geometry is None else self.geometry

    def whole_path(self, rates):
        """The whole path's platform poses ``(N, 5)`` about the geometry's home, one per position period, ``path_s``
        or not."""
        return platform_path_from(self.trajectory, self.geom().home, rates)

    def path(self, rates):
        """The platform poses ``(N, 5)`` about the geometry's home, one per position period (checked later)."""
        path = self.whole_path(rates)
        return path if self.path_s is None else path[: max(3, int(round(self.path_s / rates.dt_position)))]

    def cut_note(self, servo: ServoParams, rates, options: ModelOptions | None = None) -> str:
        """For an error about this scenario's path: where ``path_s`` cut a path whose whole passes its check
        (:func:`pusupu_jax.paths.check_path` with ``servo``'s drives, on ``options`` or the scenario's), the words
        that say so (a cut path stops at once at its end, which can ask more of the drives than the whole path);
        else ''."""
        if self.path_s is None:
            return ""
        try:
            check_path(self.whole_path(rates), servo, rates.dt_position, self.geom(), options or self.options)
        except ParameterError:
            return ""
        return (
            f" (the whole path passes: path_s = {self.path_s:g} s cuts it while it moves, and the cut path stops "
            "there at once; cut it where it is at rest)"
        )


def scenario_list(cfg: TuneConfig, machine: Machine | None = None) -> list[ScenarioSpec]:
    """Every scenario of the configuration on ``machine`` (default: the built-in one), named ``arc``, ``arc/seed3``,
    ``p2p/seed3/10kg``... (a path file by its stem; a payload scenario adds its mass to the machine's payload, at the
    same centre of mass).  With ``cfg.draws``, each also on that many machines drawn about ``machine``
    (:func:`pusupu_jax.machine_draws.draw`, seeded by ``cfg.seed``), named ``arc/draw1``..."""
    machine = Machine.default() if machine is None else machine
    machines = [(machine, "")]
    if cfg.draws:
        drawn = machine_draws.draw(machine, cfg.draws, cfg.seed)
        machines += [(m, f"/draw{k + 1}") for k, m in enumerate(drawn)]

    def options(m: Machine, seed: int | None, payload: float) -> ModelOptions:
        base = m.options()
        return dataclasses.replace(base, kin_error_seed=seed, payload=base.payload + float(payload))

    out = []
    for kind in cfg.trajectories:
        for seed in cfg.kin_error_seeds:
            for payload in cfg.payloads:
                name = (
                    path_label(kind)
                    + (f"/seed{seed}" if seed is not None else "")
                    + (f"/{payload:g}kg" if payload else "")
                )
                for m, label in machines:
                    out.append(
                        ScenarioSpec(
                            name + label,
                            kind,
                            options(m, seed, payload),
                            geometry=machine.geometry,
                            path_s=cfg.path_s,
                            drives=machine_draws.plant_drives(m) if cfg.draws else None,
                            told=options(machine, seed, payload) if m is not machine else None,
                        )
                    )
    return out


def kept_reference(
    servo: ServoParams, path: np.ndarray, mode: str, options: ModelOptions, rates, geom: Geometry, keep: bool = True
):
    """:func:`~pusupu_jax.machine.machine_reference` of ``path`` (``(N, 5)``), kept on disk beside the start states
    (:mod:`.starts`) under a name that hashes everything it is computed from (the arguments and this package's
    source): a later run of the same scenario reads the arrays its first run computed, bit for bit, instead of
    checking the path and running its inverse kinematics and dynamics again (about 5 s of the default job's set-up on
    2 cores).  A path that fails its check raises as before: nothing is kept for it.  Without ``keep``, computed and
    not kept."""
    file = None
    if keep:
        try:
            parts = ("machine_reference", *map(describe, (servo, np.asarray(path), str(mode), options, rates, geom)))
            file = kept_starts.path_for(fingerprint(parts))
        except UnstableKey:
            pass
    theta = jax.ShapeDtypeStruct((len(path), 6), jnp.asarray(0.0).dtype)
    hybrid = HybridReference(theta, *(jax.ShapeDtypeStruct(s, theta.dtype) for s in ((len(path),), (len(path), 5))))
    return kept_starts.kept(
        None if file is None else file.with_name(f"{file.stem}-reference.npz"),
        lambda: hybrid if control_mode(mode).hybrid else theta,
        lambda: machine_reference(servo, path, mode, options=options, rates=rates, geom=geom),
    )[0]


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
    def build(
        cls, cfg: TuneConfig, servo: ServoParams, rates, specs: list[ScenarioSpec] | None = None, keep: bool = True
    ) -> "Scenarios":
        """The scenarios ``specs`` (default: the configuration's); a path outside the workspace raises
        :class:`~pusupu_jax.plant.geometry.GeometryError` naming the scenario.  With ``keep`` their references are
        kept on disk (:func:`kept_reference`: 4.2 and 1.6 MB for the default job's two paths, hybrid);
        a batch of thousands of scenarios builds without."""
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
                    kept_reference(servo, padded, cfg.mode, spec.told or spec.options, rates, spec.geom(), keep)
                )
                models.append(plant.variant(spec.options, spec.geometry))
            except ParameterError as e:
                note = spec.cut_note(servo, rates, spec.told or spec.options)
                raise type(e)(f"scenario {spec.name}: {e}{note}") from None
            lengths.append(len(path))
            cut.append(path)
            padded_paths.append(padded)
        models = with_drives(models, [spec.drives for spec in specs], "Scenarios.build")
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

    def whole(
        self, servo, hybrid, models, references, mode: str, rates, batched: bool = False, marks=None, to_end=True
    ):
        """The forward pass over whole paths of one group (``models``, ``references`` ``(n, K every, ...)``):
        ``(traces (n, K every, ...), carries at the window starts (n, K, ...))``.  ``servo`` and ``hybrid`` are shared,
        or one set per path when ``batched``.  One compiled chunk of :func:`~pusupu_jax.chunked.run_chunked` serves
        every path length.  ``marks``: the periods to keep the carries at, if not the window starts; ``to_end=False``:
        for the carries only, the pass stops at the last window's start (its traces end there)."""
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
            marks=tuple(range(0, length, length // self.windows)) if marks is None else marks,
            to_end=to_end,
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

    A subclass sets ``cfg``, ``space``, ``scenarios``, ``rates``, ``windows``, ``_value_and_grad(z, baseline, starts,
    windows, start)`` and ``rows`` (the length of each term's vector) and defines ``z0()`` and ``refresh(z)``, which
    sets ``starts`` and ``_starts_z``.
    """

    baseline = None
    starts = None  # window start carries (rows K, ...)
    _starts_z = None
    mesh = None  # the devices the gradient's windows are laid over (pusupu_jax.devices.row_mesh), or None: one
    baseline_loaded = 0  # start terms read from disk rather than computed (start_baseline)

    def _baseline_file(self, z0) -> Path | None:
        """Where the terms at the start ``z0`` are kept, or None: not kept (a subclass that keeps its start states
        names it)."""
        return None

    def member_z(self, z, m: int) -> dict:
        """Member ``m``'s ``z`` (a problem of one member: ``z``)."""
        return z

    def starts_structure(self, z) -> object:
        """The structure of one path group's start states at ``z`` (``jax.ShapeDtypeStruct`` leaves; for a batch, its
        first member's), not run (from the start program kept on disk, where it is)."""
        servo, hybrid = self.space.apply(self.member_z(z, 0))
        sc = self.scenarios
        _, models, refs = next(iter(sc.groups.values()))
        return carry_structure(
            servo,
            models,
            jax.tree.map(lambda x: np.asarray(x)[:, 0], refs),
            plant=sc.plant,
            rates=self.rates,
            outer=self.cfg.mode,
            hybrid=hybrid if control_mode(self.cfg.mode).hybrid else None,
        )

    def prepare(self, z, iteration: int) -> None:
        """Before iteration ``iteration``: renew the start states every ``refresh_every`` iterations (and when
        missing).  Before the first, the gradient's stored program is loaded or traced, and compiled, in a thread of
        its own (:meth:`pusupu_jax.programs.Program.compile_ahead`), while the forward passes over the whole paths
        give the windows their start states."""
        if self.baseline is None and isinstance(self._value_and_grad, Program):
            n = self.rows * self.scenarios.windows  # a start state per window: the groups' structure, n long
            starts = jax.tree.map(lambda s: np.zeros((n,) + s.shape[1:], s.dtype), self.starts_structure(z))
            ones = {k: np.ones(self.rows) for k in objectives.TERMS}
            self._value_and_grad.compile_ahead(z, ones, starts, self.windows, self.space.start)
        if self.starts is None or (iteration % self.cfg.refresh_every == 0 and not self.starts_at(z)):
            self.refresh(z)

    def starts_at(self, z) -> bool:
        """Whether the start states are those of ``z`` (renewed at these very gains)."""
        return (
            self.starts is not None
            and self._starts_z is not None
            and all(np.array_equal(np.asarray(z[k]), v) for k, v in self._starts_z.items())
        )

    def start_baseline(self):
        """The terms at the start, from one call of the compiled gradient (normalisers of 1: no new compile), or
        read from the file an earlier run of the same problem kept beside its start states (:meth:`_baseline_file`;
        counted in ``baseline_loaded``)."""
        if self.baseline is None:
            kept = (self.starts, self._starts_z)  # a resumed run has its own starts already: keep them
            z0 = self.z0()
            if not self.starts_at(z0):  # a fresh run has just renewed them at z0 (prepare): not twice
                self.refresh(z0)
            structure = {k: jax.ShapeDtypeStruct((self.rows,), np.float64) for k in objectives.TERMS}

            def terms():
                ones = {k: jnp.ones(self.rows) for k in objectives.TERMS}
                (_, aux), _ = self._value_and_grad(z0, ones, self.starts, self.windows, self.space.start)
                return aux["terms"]

            self.baseline, loaded = kept_starts.kept(self._baseline_file(z0), lambda: structure, terms)
            self.baseline_loaded += loaded
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
        machine: Machine | None = None,
    ):
        self.cfg = cfg
        self.digest = cfg.digest() if digest is None else digest  # what a checkpoint must match to be resumed
        self.rates = machine_rates()
        self.space = Space.create(
            cfg.groups, servo0.replace(imc_form=cfg.imc_form), hybrid0, shared=cfg.shared, bounds=cfg.bounds
        )
        with devices.set_up_device():  # a GPU job's set-up on the host's CPU
            self.scenarios = sc = Scenarios.build(cfg, self.space.servo0, self.rates, specs)
            # the margin constraints' single-axis loads (machine_file.margin_loads): ``machine``'s (default the
            # built-in one) at home, and at the lightest and the heaviest pose along the scenarios' paths with their
            # payloads
            specs = scenario_list(cfg) if specs is None else specs
            runs = [machine_file.PathRun(path, spec.options, spec.geometry) for path, spec in zip(sc.paths, specs)]
            self.loads = machine_file.margin_loads(Machine.default() if machine is None else machine, runs)
        # the windows' models, references and paths, and the margins' loads, enter the gradient as arguments, not as
        # constants folded into the compiled program (constants cost compile time, and change its cache key with
        # their last bits): problems of other paths, seeds or payloads share one program
        self.windows = (
            sc.window_models,
            sc.window_reference,
            jnp.asarray(sc.window_path),
            stack(list(self.loads.values())),
        )
        if specs[0].drives is not None:  # the margins on every machine the scenarios run on (drawn ones), too
            machines = {tuple(np.concatenate([np.ravel(v) for v in s.drives.values()])): s.drives for s in specs}
            self.windows += (stack(list(machines.values())),)
        self.rows = len(sc.names)
        # every window of every scenario is independent: they are laid over the devices (one per CPU core)
        self.mesh = devices.row_mesh(self.rows * sc.windows)
        self._value_and_grad = _shared_gradient(self)
        self.starts_loaded = 0  # start states read from disk rather than computed (refresh)

    def run_paths(self, z, starts_only: bool = False) -> list:
        """The forward pass over every scenario's whole path at ``z``: ``[(trace (K every, ...), carries (K,
        ...))]``; with ``starts_only``, for the windows' start states, to the last of them (the traces end there).
        On one device, each group of equal path length in its own batch; where the scenarios can be laid over several
        devices (:func:`pusupu_jax.devices.row_mesh`), every path in one batch laid over them, held at its last pose
        to the longest path's length (each device then runs the longest path's length, but all at once; with
        ``starts_only``, to the latest start of any).  A GPU job's few paths run on the host's CPU
        (:func:`pusupu_jax.devices.forward_pass_devices`)."""
        where = devices.forward_pass_devices(len(self.scenarios.names))
        if where[0].platform == devices.chosen_devices()[0].platform:
            return self._run_paths(z, where, starts_only)
        with jax.default_device(where[0]):  # host copies: the gradient takes the carries on its own device
            return jax.tree.map(np.asarray, self._run_paths(jax.tree.map(np.asarray, z), where, starts_only))

    def _run_paths(self, z, where: list, starts_only: bool) -> list:
        """:meth:`run_paths` on the devices ``where``."""
        servo, hybrid = self.space.apply(z)
        sc = self.scenarios
        out = [None] * len(sc.names)
        mesh = devices.row_mesh(len(sc.names), where) if len(sc.groups) > 1 else None
        if mesh is None:
            for idx, models, refs in sc.groups.values():
                traces, carries = sc.whole(
                    servo, hybrid, models, refs, self.cfg.mode, self.rates, to_end=not starts_only
                )
                for j, i in enumerate(idx):
                    out[i] = jax.tree.map(lambda x: x[j], (traces, carries))
            return out
        longest = max(sc.groups)
        marks = sorted({m for n in sc.groups for m in range(0, n, n // sc.windows)})
        rows = [(i, n) for n, (idx, _, _) in sc.groups.items() for i in idx]

        def held(x, n):  # a group's references, holding their last sample to the longest length
            x = np.asarray(x)
            return np.pad(x, [(0, 0), (0, longest - n)] + [(0, 0)] * (x.ndim - 2), mode="edge")

        models = jax.tree.map(
            lambda *x: np.concatenate([np.asarray(a) for a in x]), *[m for _, m, _ in sc.groups.values()]
        )
        refs = jax.tree.map(
            lambda *x: np.concatenate(x), *[jax.tree.map(lambda a: held(a, n), r) for n, (_, _, r) in sc.groups.items()]
        )
        models = jax.device_put(models, NamedSharding(mesh, PartitionSpec("rows")))
        traces, carries = sc.whole(
            servo, hybrid, models, refs, self.cfg.mode, self.rates, marks=tuple(marks), to_end=not starts_only
        )
        carries = jax.tree.map(np.asarray, carries)  # fetched from the devices they were laid over
        for j, (i, n) in enumerate(rows):
            own = [marks.index(m) for m in range(0, n, n // sc.windows)]
            out[i] = (jax.tree.map(lambda x: x[j, :n], traces), jax.tree.map(lambda x: x[j, own], carries))
        return out

    def refresh(self, z) -> None:
        """Renew the windows' start states from a forward pass over the whole paths at ``z``, or load the states an
        earlier run kept for the same problem and gains (:mod:`pusupu_jax.tune.starts`; counted in
        ``starts_loaded``)."""

        def computed():
            runs = self.run_paths(z, starts_only=True)
            return jax.tree.map(lambda *c: jnp.concatenate(c), *[carries for _, carries in runs])

        self.starts, loaded = kept_starts.kept(self._starts_file(z), lambda: self.starts_structure(z), computed)
        self.starts_loaded += loaded
        self._starts_z = {k: np.asarray(v) for k, v in z.items()}

    def _starts_file(self, z) -> Path | None:
        """Where the start states at ``z`` are kept: named by everything they depend on (:mod:`.starts`)."""
        try:
            parts = (
                structure_key(self),
                describe(self.space.start),
                describe({k: np.asarray(v) for k, v in z.items()}),
                describe([(models, refs) for _, models, refs in self.scenarios.groups.values()]),
                f"devices={len(jax.devices())}",
            )
        except UnstableKey:
            return None
        return kept_starts.path_for(fingerprint(parts, (HERE,)))

    def _baseline_file(self, z0) -> Path | None:
        """Beside the start states at ``z0``: the terms at the start are the gradient program's, from those states and
        the windows of the same scenario arrays, which that file's name already hashes."""
        path = self._starts_file(z0)
        return None if path is None else path.with_name(f"{path.stem}-terms.npz")

    def z0(self) -> dict:
        return self.space.z0()

    def scenario_terms(self, z, starts, windows, start) -> tuple[dict, object]:
        """Every objective term of every scenario over its ``windows`` (models, references, paths), ``{term: (S,)}``,
        and the window traces, at ``z`` from the start point ``start``."""
        servo, hybrid = self.space.apply(z, start)
        sc = self.scenarios

        def one(servo, hybrid, model, reference, init):
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

        # The gains go to every window as a row of their own: closed over, the reverse pass would sum their
        # gradient over the windows inside every step of the scan, which laid over devices is an all-reduce per
        # step (each device waiting on the others); as rows, the sum is taken once, after the scan.
        rows = jax.tree.leaves(starts)[0].shape[0]
        gains = jax.tree.map(lambda x: jnp.broadcast_to(x, (rows, *jnp.shape(x))), (servo, hybrid))
        gains, models, reference, starts = devices.spread_rows((gains, windows[0], windows[1], starts), self.mesh)
        traces = jax.vmap(one)(*gains, models, reference, starts)
        path = windows[2]
        S, K = len(sc.names), sc.windows
        joined = jax.tree.map(lambda x: join_windows(x, S, K), traces)
        path = join_windows(path, S, K)
        terms = jax.vmap(
            lambda tr, p: objectives.terms(
                tr, servo, p, self.rates.dt_position, sharpness_force=self.cfg.sharpness_force
            )
        )(joined, path)
        return terms, traces

    def objective(self, z, baseline, starts, windows, start):
        """``(J, aux)``; ``baseline`` holds each scenario's terms at the start (the normalisers); ``windows`` the
        windows' models, references and paths, and the margins' loads (stacked, :attr:`loads`); ``start`` the start
        point ``(servo0, hybrid0)`` (:attr:`Space.start`) that gives the fields not tuned."""
        t, traces = self.scenario_terms(z, starts, windows, start)
        per = scenario_objective(self.cfg, t, baseline)
        servo = self.space.apply(z, start)[0]
        if len(windows) > 4:  # on each machine drawn (its drive values in both the plant and the controller)
            margins = jax.vmap(lambda d: envelope_margins(servo.replace(**d), windows[3], mode=self.cfg.mode))(
                windows[4]
            )
        else:
            margins = envelope_margins(servo, windows[3], mode=self.cfg.mode)
        return aggregate(self.cfg, per, margins), {"scenarios": per, "terms": t}

    def value_and_grad(self, z):
        return self._value_and_grad(z, self.start_baseline(), self.starts, self.windows, self.space.start)

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


_GRADIENTS: dict = {}  # structure key -> the compiled gradient shared by the Problems of that structure


def structure_key(problem: WindowStarts, *layout) -> str:
    """A stable description (:func:`pusupu_jax.programs.describe`) of what a problem's objective reads from it besides
    its arguments: the configuration's settings that reach the program (:data:`~.config.OBJECTIVE_SETTINGS`), the
    tuned fields and the structure of their start point (``space``: the start's values are an argument), the nominal
    plant's options, the rates, the number of rows, and ``layout`` (a subclass's own: a batch's load of the margins),
    with the problem's class.  So a run with other iterations, learning rate, paths, seeds, payloads, start gains or
    drives (another machine of the same mechanism: its model arrays are arguments too) loads the program an earlier
    run traced."""
    space = problem.space
    # the weights' order too: the objective sums its terms in it, and describe sorts a dict's keys
    return describe(
        (
            type(problem),
            {k: getattr(problem.cfg, k) for k in OBJECTIVE_SETTINGS},
            tuple(problem.cfg.weights),
            problem.scenarios.plant.options,
            problem.rates,
            problem.rows,
            1 if problem.mesh is None else problem.mesh.size,
            space.fields,
            space.shared,
            jax.tree.structure(space.start),
            layout,
        )
    )


def _shared_gradient(problem: Problem) -> Program:
    """The jitted ``value_and_grad`` of ``problem.objective``, or that of an earlier Problem of the same structure.

    The objective reads from its Problem only what :func:`structure_key` holds; the scenarios' windows, start states,
    normalisers and the start point are arguments.  So Problems that differ only in their scenarios (seeds, payloads,
    geometry arrays, paths) or their start gains share one trace and one compile: tracing the gradient of the MJX
    rollout takes about half a minute on this CPU, each time a new function is jitted.  The same key names the traced
    program on disk (:class:`pusupu_jax.programs.Program`), so that a later process loads it instead of tracing.
    """
    key = structure_key(problem)
    if key not in _GRADIENTS:
        while len(_GRADIENTS) >= GRADIENTS_KEPT:
            _GRADIENTS.pop(next(iter(_GRADIENTS)))
        # the file's name is taken again when it is traced: a configuration whose dicts (weights, bounds) were edited
        # in place since this Problem was built is traced under its own name, not under this key's
        _GRADIENTS[key] = Program(
            value_and_grad(problem.objective, problem.cfg.gradient),
            lambda: structure_key(problem),
            sources=(HERE,),
            mesh=problem.mesh,
        )
    return _GRADIENTS[key]
