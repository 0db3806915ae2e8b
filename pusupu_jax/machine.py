"""Simulating the whole machine: platform paths through inverse kinematics into the cascade and the MJX plant.

Host-side entry point :func:`simulate_machine`: checks the path against the machine
before anything runs (:func:`pusupu_jax.paths.check_path`: reachability, stroke,
conditioning, motor speeds and torques), turns it into branch
references with the nominal inverse kinematics, runs the jitted co-simulation and
reports the metrics of ``pusupu sim --plant mjx``.
"""

from __future__ import annotations

import dataclasses
import functools
import time
from collections.abc import Iterable
from typing import TYPE_CHECKING, Any

import jax
import jax.numpy as jnp
import numpy as np
import numpy.typing as npt

from . import compliance as compliance_law
from . import hybrid as hybrid_law
from . import paths
from .cascade import POSITION_MODES, control_mode
from .objectives import branch_force
from .params import LoopRates, ParameterError, ServoParams, stack, validate
from .plant import PlantDrives, dynamics, kinematics
from .plant.axis import screw_ratio
from .plant.geometry import Geometry
from .plant.mjx_plant import MJXPlant
from .plant.model import ModelOptions
from .chunked import run_chunked
from .metrics import HybridFigures, MachineMetrics

if TYPE_CHECKING:
    from .trace import Trace

MACHINE_MODES = POSITION_MODES


def machine_rates(options: ModelOptions = ModelOptions(), rates: LoopRates = LoopRates()) -> LoopRates:
    """``rates`` with the mechanical step set to the model's timestep (ParameterError when it is not a whole number of
    current-loop ticks, or not a divisor of the velocity period)."""
    n_mech = rates.f_current * options.timestep
    if abs(n_mech - round(n_mech)) > 1e-9 or round(n_mech) < 1:
        raise ParameterError(
            f"rates.f_current: expected a multiple of {1 / options.timestep:g} Hz (the machine's "
            f"{options.timestep * 1e3:g} ms mechanical step a whole number of current-loop ticks), "
            f"got {rates.f_current:g} Hz"
        )
    return dataclasses.replace(rates, n_mech=int(round(n_mech)))


@functools.lru_cache(maxsize=8)
def machine_plant(options: ModelOptions = ModelOptions()) -> MJXPlant:
    """The default-geometry MJX plant for ``options``, built once per options (a static jit argument)."""
    return MJXPlant.create(Geometry.default(), options)


def machine_reference(
    servo: ServoParams,
    path: npt.ArrayLike,
    mode: str,
    *,
    options: ModelOptions = ModelOptions(),
    rates: LoopRates = LoopRates(),
    geom: Geometry | None = None,
) -> jax.Array | hybrid_law.HybridReference:
    """The rollout reference for platform poses ``path`` (``(N, 5)``, one per position period), checked first against
    the machine (:func:`pusupu_jax.paths.check_path`: workspace, motor speeds and torques).

    Branch references are the nominal inverse kinematics as motor angles from home [rad],
    ``(N, 6)``; for 'hybrid' a :class:`~pusupu_jax.hybrid.HybridReference` that adds
    branch 6's minimum-norm inverse-dynamics force and the coupling row along the path.
    """
    if mode not in MACHINE_MODES:
        raise ValueError(f"mode: expected one of {tuple(map(str, MACHINE_MODES))}, got {mode!r}")
    geom = Geometry.default() if geom is None else geom
    paths.check_path(path, servo, rates.dt_position, geom, options)
    s_home = kinematics.inverse_kinematics(geom, jnp.asarray(geom.home))
    s_ref = np.asarray(kinematics.inverse_kinematics(geom, jnp.asarray(path)) - s_home)
    theta = jnp.asarray(s_ref / np.asarray(screw_ratio(servo)))
    if not control_mode(mode).hybrid:
        return theta
    force, J = dynamics.inverse_dynamics_forces(servo, path, rates.dt_position, geom, options)
    return hybrid_law.HybridReference(
        theta, jnp.asarray(force[:, hybrid_law.FORCE_AXIS]), jnp.asarray(dynamics.coupling_row(J))
    )


@dataclasses.dataclass(frozen=True, eq=False)
class Scenario:
    """One run of the machine: platform poses ``path`` ``(N, 5)`` (one per position period) on the machine
    built with ``options`` (seeded kinematic errors, payload) and the nominal ``geometry`` (None: the default, see
    :meth:`Geometry.default`); ``name`` labels it in reports; ``drives``: drive values of the machine's own where it
    differs from its machine file, what the host is told (:class:`~pusupu_jax.plant.PlantDrives`), or None."""

    path: np.ndarray
    options: ModelOptions = ModelOptions()
    name: str = ""
    geometry: Geometry | None = None
    drives: dict[str, Any] | None = None


def with_drives(models: list[Any], drives: list[dict[str, Any] | None], where: str) -> list[Any]:
    """Each of a batch's ``models`` with its scenario's ``drives`` as a :class:`~pusupu_jax.plant.PlantDrives`, or as
    it is where None; ``where`` names the caller in the ValueError for a batch that gives them to some scenarios only
    (its members must share one structure)."""
    if len({d is None for d in drives}) > 1:
        raise ValueError(f"{where}: expected drive values for every scenario or for none")
    return [m if d is None else PlantDrives(m, d) for m, d in zip(models, drives)]


@dataclasses.dataclass(frozen=True)
class MachineRun:
    """One scenario's run on the machine (:func:`simulate_scenarios`): the scenario's ``name`` (None for
    :func:`simulate_machine`'s single path), the control ``mode``, the IMC form, how it started, its seeded kinematic
    errors and payload [kg], its :class:`~pusupu_jax.metrics.MachineMetrics`, and the batch's wall time [s]
    (compile included)."""

    name: str | None
    mode: str
    imc_form: str
    start: str
    kin_error_seed: int | None
    payload_kg: float
    metrics: MachineMetrics
    wall_s: float

    def to_json(self) -> dict[str, Any]:
        """Plain data (``pusupu sim --json``'s, and the experiments'): the scenario, the metrics, the wall time."""
        d: dict[str, Any] = {} if self.name is None else {"name": self.name}
        d |= {
            "mode": self.mode,
            "imc_form": self.imc_form,
            "start": self.start,
            "kin_error_seed": self.kin_error_seed,
            "payload_kg": self.payload_kg,
        }
        return d | self.metrics.to_json() | {"wall_s": self.wall_s}


def simulate_scenarios(
    servo: ServoParams,
    scenarios: Iterable[Scenario],
    *,
    mode: str = "imc",
    rates: LoopRates = LoopRates(),
    hybrid: hybrid_law.HybridGains | None = None,
    start: str = "rest",
    compliance: compliance_law.AdmittanceGains | None = None,
    force_setpoint: npt.ArrayLike | None = None,
) -> list[tuple[MachineRun, dict[str, Any]]]:
    """Run several :class:`Scenario` on the machine as one vmapped batch; per scenario, its :class:`MachineRun` and
    arrays for plots.

    The batch runs in calls of :func:`~pusupu_jax.chunked.run_chunked`'s compiled program of
    ``CHUNK`` periods: one compile per mode and batch size, whatever the paths' length.

    The scenarios differ in their model's arrays (:meth:`MJXPlant.variant`: seeded errors,
    payloads) and their paths; shorter paths are padded with their last pose (the machine
    holding still) to the longest, and every metric is taken over each path's own length.
    ``servo`` (and, in hybrid mode, ``hybrid``) is shared, or has a leading axis of one
    parameter set per scenario (a gain sweep).  ``options`` may differ only in
    ``kin_error_seed``, the payload (``payload``, ``payload_com``, ``payload_inertia``) and the
    contact scene's arrays (``surface_tilt``, ``hole_offset``); geometries may differ (each a variant
    of the default structure).  ``compliance``: the admittance
    of :mod:`pusupu_jax.compliance` around the position loops (the scenarios' models need
    contacts), holding the contact force ``force_setpoint`` [N] on the tool (world axes;
    ``(3,)``, or ``(N, 3)`` along the longest path; default zero).  Returns ``[(run, arrays)]``: each scenario's
    :class:`MachineRun` and arrays for plots, as :func:`simulate_machine`.
    """
    if mode not in MACHINE_MODES:
        raise ValueError(f"mode: expected one of {tuple(map(str, MACHINE_MODES))}, got {mode!r}")
    scenarios = list(scenarios)
    validate(servo)
    batched = np.ndim(servo.lambda1) == 2
    if batched and np.shape(servo.lambda1)[0] != len(scenarios):
        raise ValueError(
            f"servo: expected one parameter set or {len(scenarios)} (one per scenario), "
            f"got {np.shape(servo.lambda1)[0]}"
        )
    if control_mode(mode).hybrid:
        hybrid = hybrid_law.HybridGains() if hybrid is None else hybrid
        hybrid_law.validate_gains(hybrid, bounded=False)  # a gain file's bounds are checked where one is read
    nominal = dataclasses.replace(
        scenarios[0].options,
        kin_error_seed=None,
        payload=0.0,
        payload_com=(0.0, 0.0, 0.0),
        payload_inertia=(0.0, 0.0, 0.0),
    )
    rates = machine_rates(nominal, rates)
    if compliance is not None:
        if not nominal.contacts:
            raise ValueError("compliance: expected scenarios whose models have contacts (ModelOptions.contacts)")
        compliance_law.validate_gains(compliance, rates.dt_position)
    plant = machine_plant(nominal)
    length = max(len(sc.path) for sc in scenarios)

    def pick(tree: Any, k: int) -> Any:
        return jax.tree.map(lambda x: np.asarray(x)[k], tree)

    servos = [pick(servo, k) if batched else servo for k in range(len(scenarios))]
    hybrid_axis = 0 if hybrid is not None and control_mode(mode).hybrid and np.ndim(hybrid.m6) == 1 else None
    hybrids = [pick(hybrid, k) if hybrid_axis == 0 else hybrid for k in range(len(scenarios))]
    models, references = [], []
    for sc, sv in zip(scenarios, servos):
        padded = np.concatenate([sc.path, np.repeat(sc.path[-1:], length - len(sc.path), axis=0)])
        # the rollout reference's pytree: angles, a HybridReference or a ComplianceReference (and below their slices)
        reference: Any = machine_reference(sv, padded, mode, options=sc.options, rates=rates, geom=sc.geometry)
        if compliance is not None:
            setpoint = np.zeros(3) if force_setpoint is None else np.asarray(force_setpoint, dtype=float)
            if setpoint.shape not in ((3,), (length, 3)) or not np.isfinite(setpoint).all():
                raise ValueError(
                    f"force_setpoint: expected finite forces [N] of shape (3,) or ({length}, 3), got "
                    f"shape {setpoint.shape}"
                )
            setpoint = np.broadcast_to(setpoint, (length, 3))
            reference = compliance_law.ComplianceReference(jnp.asarray(padded), jnp.asarray(setpoint), reference)
        references.append(reference)
        models.append(plant.variant(sc.options, sc.geometry))
    models = with_drives(models, [sc.drives for sc in scenarios], "simulate_scenarios")
    t0 = time.perf_counter()
    traces, _ = run_chunked(
        servo,
        stack(models),
        stack(references),
        plant=plant,
        rates=rates,
        outer=mode,
        hybrid=hybrid if control_mode(mode).hybrid else None,
        start=start,
        compliance=None if compliance is None else (compliance, scenarios[0].geometry or Geometry.default()),
        params_axis=0 if batched else None,
        hybrid_axis=hybrid_axis,
    )
    wall = time.perf_counter() - t0
    out = []
    for k, sc in enumerate(scenarios):
        n = len(sc.path)
        trace = jax.tree.map(lambda x: np.asarray(x)[k, :n], traces)
        reference = jax.tree.map(lambda x: np.asarray(x)[:n], references[k])
        if compliance is not None:
            reference = reference.inner
        result, arrays = machine_metrics(trace, servos[k], sc.path, reference, mode, rates.dt_position, hybrids[k])
        run = MachineRun(
            sc.name, str(mode), servo.imc_form, start, sc.options.kin_error_seed, sc.options.payload, result, wall
        )
        out.append((run, arrays))
    return out


def simulate_machine(
    servo: ServoParams,
    path: npt.ArrayLike,
    *,
    mode: str = "imc",
    options: ModelOptions = ModelOptions(),
    rates: LoopRates = LoopRates(),
    hybrid: hybrid_law.HybridGains | None = None,
    start: str = "rest",
    geom: Geometry | None = None,
) -> tuple[MachineRun, dict[str, Any]]:
    """Run platform poses ``path`` (``(N, 5)``, one per position period) on the machine of nominal geometry ``geom``
    (None: the default).

    ``hybrid``: the gains of eq. 14 for ``mode='hybrid'`` (default :class:`~pusupu_jax.hybrid.HybridGains`).
    ``start``: 'rest' (the machine held still by its drives at t = 0) or 'zero' (every controller state zero).
    Returns ``(run, arrays)``: its :class:`MachineRun` (``name`` None; see ``pusupu sim --plant mjx``) and arrays for
    plots (``t``, ``reference``, ``platform`` positions [m], ``branch_force`` [N]).  A batch of one
    :func:`simulate_scenarios`: seeded errors and payloads share the nominal machine's compile.
    """
    result, arrays = simulate_scenarios(
        servo, [Scenario(np.asarray(path), options, geometry=geom)], mode=mode, rates=rates, hybrid=hybrid, start=start
    )[0]
    return dataclasses.replace(result, name=None), arrays


REVERSAL_WINDOW_S = 0.1  # s after a reversal of a slider's reference speed in which its error counts as the glitch


def reversals(s_ref: npt.ArrayLike) -> list[np.ndarray]:
    """Per branch, the samples where its reference speed reverses: the first sample moving the other way (the sign
    of ``diff(s_ref)`` changes; stretches at rest skipped).  ``s_ref``: ``(N, 6)`` [m]."""
    v = np.diff(np.asarray(s_ref), axis=0)
    out = []
    for b in range(v.shape[1]):
        moving = np.flatnonzero(np.abs(v[:, b]) > 1e-12)
        sign = np.sign(v[moving, b])
        out.append(moving[1:][sign[1:] != sign[:-1]] + 1)
    return out


def reversal_error(
    e_branch: npt.ArrayLike, s_ref: npt.ArrayLike, dt: float, window_s: float = REVERSAL_WINDOW_S
) -> list[float | None]:
    """Per branch, the largest slider error |e| [m] within ``window_s`` after any reversal of its reference speed
    (:func:`reversals`), where the drive train's Coulomb friction changes sign and the classic glitch of a reversal
    shows; None for a branch whose reference never reverses.  ``e_branch``, ``s_ref``: ``(N, 6)`` [m], one row per
    position period of ``dt`` [s]."""
    e = np.abs(np.asarray(e_branch))
    n = max(int(round(window_s / dt)), 1)
    return [max(float(e[k : k + n, b].max()) for k in at) if len(at) else None for b, at in enumerate(reversals(s_ref))]


def machine_metrics(
    trace: Trace,
    servo: ServoParams,
    path: np.ndarray,
    reference: Any,
    mode: str,
    dt: float,
    hybrid: hybrid_law.HybridGains | None = None,
) -> tuple[MachineMetrics, dict[str, Any]]:
    """The metrics of ``pusupu sim --plant mjx`` from a machine trace (host-side), and arrays for plots.

    ``reference``: the rollout reference of the run (see :func:`machine_reference`); branch errors are taken
    against the angles the trace recorded (under compliance, the recomputed ones), and ``reference`` serves
    hybrid mode's ``F_q``.
    """
    r = np.asarray(screw_ratio(servo))
    s_ref = np.asarray(trace.reference) * r  # the angles followed (under compliance, the recomputed ones)
    platform = np.asarray(trace.observation["platform_pos"])
    e_platform = np.linalg.norm(platform - np.asarray(path)[:, :3], axis=1)
    e_branch = np.asarray(trace.position) - s_ref
    torque = np.asarray(trace.torque)
    force = np.asarray(branch_force(trace, servo))
    rho = hybrid_law.synchronous_error(jnp.asarray(e_branch), dt)
    residual = np.asarray(trace.observation["closure_residual"])
    figures = None
    if control_mode(mode).hybrid:
        assert hybrid is not None  # a hybrid run has its gains
        # the state is recorded at the start of each period, so F_6 of period k shows at k + 1
        f_rho = np.asarray(trace.state.force.force)[1:] - np.asarray(reference.force_ff)[:-1]
        figures = HybridFigures(
            form=hybrid.form,
            gains={f.name: float(getattr(hybrid, f.name)) for f in hybrid_law.gain_fields()},
            force_ff_peak_n=float(np.abs(np.asarray(reference.force_ff)).max()),
            f_rho_rms_n=float(np.sqrt(np.mean(f_rho**2))),
            f_rho_peak_n=float(np.abs(f_rho).max()),
        )
    result = MachineMetrics(
        duration_s=len(path) * dt,
        rms_tracking_error_mm=float(np.sqrt(np.mean(e_platform**2)) * 1e3),
        max_tracking_error_mm=float(e_platform.max() * 1e3),
        branch_rms_error_mm=(np.sqrt(np.mean(e_branch**2, axis=0)) * 1e3).tolist(),
        branch_reversal_error_mm=[None if x is None else x * 1e3 for x in reversal_error(e_branch, s_ref, dt)],
        motor_torque_peak_nm=np.abs(torque).max(axis=0).tolist(),
        branch_force_peak_n=np.abs(force).max(axis=0).tolist(),
        sync_error_rho=float(rho[-1]) * 1e3,  # mm s
        loop_closure_residual_max_mm=float(residual.max() * 1e3),
        hybrid=figures,
    )
    observed = {
        k: np.asarray(trace.observation[k])
        for k in ("contact_force", "compliance_offset", "platform_mat")
        if k in trace.observation
    }
    return result, {
        "t": np.asarray(trace.t),
        "reference": np.asarray(path)[:, :3],
        "platform": platform,
        "branch_force": force,
        "drive": {  # per axis, as the bridge's feedback logs them (pusupu_jax.run_log)
            "reference_rad": np.asarray(trace.reference),
            "position_rad": np.asarray(trace.theta),
            "velocity_rad_s": np.asarray(trace.omega),
            "torque_nm": torque,
            "current_a": np.asarray(trace.current),
        },
        "reversal_t": np.asarray(trace.t)[np.unique(np.concatenate(reversals(s_ref)))],  # s, any branch's
    } | observed
