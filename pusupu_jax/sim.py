"""The cascade and a plant over a reference, as one jitted scan of nested scans.

Time structure (static, from :class:`~pusupu_jax.params.LoopRates`): the outer scan runs
at the rate of the outermost closed loop; inside each position period the velocity loop
runs ``n_position`` times; inside each velocity period the plant's mechanics steps
``n_velocity / n_mech`` times; inside each mechanical step the current loop and the
electrical model tick ``n_mech`` times with the motor speed held, and the mechanics then
advances with the mean motor torque of those ticks.

Measurements are taken at the start of each period (sample, then compute, then hold), so
each loop sees the plant through a zero-order hold, as a digital drive does.

:func:`rollout` is the pure function (jit-, vmap- and grad-able); :func:`simulate` is
the host-side entry point that validates inputs, converts slider references to motor
angles and dispatches to a cached jitted (and, for batched parameters, vmapped) rollout.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from . import hybrid as hybrid_law
from . import loops
from .params import AxisLoad, LoopRates, ParameterError, ServoParams, validate
from .plant import AxisPlant
from .plant.axis import screw_ratio

OUTER_LOOPS = ("current", "velocity", "imc", "pid", "hybrid")
MODES = ("imc", "pid")


@jax.tree_util.register_dataclass
@dataclass(frozen=True)
class Trace:
    """A rollout sampled at the start of every outer-loop period; arrays are ``(..., N, n_axes)``.

    ``reference`` and ``command`` are in the outer loop's units: position loops take a
    motor angle [rad] and command a speed [rad/s]; the velocity loop takes [rad/s] and
    commands a current [A]; the current loop takes [A] and commands a voltage [V].
    """

    t: Any  # s, (N,)
    reference: Any
    command: Any
    theta: Any  # motor angle, rad
    omega: Any  # motor speed, rad/s
    position: Any  # slider position, m
    velocity: Any  # slider velocity, m/s
    current: Any  # armature current, A
    torque: Any  # motor torque Kt*I, N m
    state: Any  # every controller and electrical state (pytree)
    observation: Any  # what the plant's observe() keeps (pytree)


def initial_state(drive: loops.Drive, plant, aux, outer: str) -> dict:
    """The scan carry: named states of the plant, the electrical model and every closed loop."""
    c = dict(plant=plant.init(aux), electrical=loops.electrical_init(drive.electrical),
             current=loops.pi_loop_init(drive.current))
    if outer != "current":
        c["velocity"] = loops.pi_loop_init(drive.velocity)
    if outer in ("imc", "hybrid"):
        c["position"] = loops.imc_init(drive.imc)
    elif outer == "pid":
        c["position"] = loops.pid_init(drive.pid)
    if outer == "hybrid":
        c["force"] = hybrid_law.init()
    return c


def rollout(params: ServoParams, plant_params, reference, *, plant=AxisPlant(), rates: LoopRates = LoopRates(),
            outer: str = "imc", remat: bool = False, hybrid: hybrid_law.HybridGains | None = None) -> Trace:
    """Run the cascade closed up to ``outer`` against ``plant`` (pure; jit with plant, rates, outer, remat static).

    ``reference`` has shape ``(N, n_axes)`` in the outer loop's units, one sample per
    outer period: motor angle [rad] for 'imc' and 'pid', motor speed [rad/s] for
    'velocity', current [A] for 'current' (one per mechanical step).

    ``outer='hybrid'`` is the force/position hybrid control of :mod:`pusupu_jax.hybrid`:
    ``reference`` is a :class:`~pusupu_jax.hybrid.HybridReference` and ``hybrid`` its
    :class:`~pusupu_jax.hybrid.HybridGains`.  Every axis runs the IMC cascade, but the
    current reference of axis ``FORCE_AXIS`` is replaced by ``F_6 r / (eta Kt)`` (clamped
    to its ``I_max``), so that axis's position and velocity controllers run without
    effect; ``state['force']`` records ``rho``, ``rho'`` and ``F_6`` [N].  ``remat=True``
    recomputes each outer period in the backward pass instead of storing its inner steps
    (``jax.checkpoint``): reverse-mode memory then grows with the number of outer periods
    only, for about one extra forward pass.
    """
    if outer not in OUTER_LOOPS:
        raise ValueError(f"rollout: expected outer in {OUTER_LOOPS}, got {outer!r}")
    drive = loops.discretize(params, rates)
    aux = plant.prepare(params, plant_params, rates.dt_mech)
    n_mech_steps = rates.n_velocity // rates.n_mech
    if (outer == "hybrid") != (hybrid is not None):
        raise ValueError("rollout: hybrid gains are needed exactly when outer='hybrid'")
    r = screw_ratio(params)

    def record(c, ref, command):
        theta, omega = plant.measure(aux, c["plant"])
        x, v = plant.slider(aux, c["plant"])
        i = loops.electrical_current(c["electrical"])
        return dict(reference=ref.theta if outer == "hybrid" else ref, command=command, theta=theta, omega=omega,
                    position=x, velocity=v, current=i, torque=drive.Kt * i,
                    state={k: s for k, s in c.items() if k != "plant"}, observation=plant.observe(aux, c["plant"]))

    def mech_step(c, i_ref):
        _, omega = plant.measure(aux, c["plant"])

        def tick(ce, _):
            xe, sc = ce
            sc, u = loops.pi_loop_step(drive.current, sc, i_ref, loops.electrical_current(xe),
                                       drive.emf_gain * omega)
            torque = drive.Kt * loops.electrical_current(xe)
            return (loops.electrical_step(drive.electrical, xe, u, omega), sc), (torque, u)

        (xe, sc), (torques, u) = jax.lax.scan(tick, (c["electrical"], c["current"]), None, length=rates.n_mech)
        c = dict(c, plant=plant.step(aux, c["plant"], jnp.mean(torques, axis=0)), electrical=xe, current=sc)
        return c, u[0]

    def velocity_period(c, w_ref, i_force=None):
        _, omega = plant.measure(aux, c["plant"])
        sv, i_ref = loops.pi_loop_step(drive.velocity, c["velocity"], w_ref, omega)
        if i_force is not None:
            limit = params.I_max[..., hybrid_law.FORCE_AXIS]
            i_ref = i_ref.at[..., hybrid_law.FORCE_AXIS].set(jnp.clip(i_force, -limit, limit))
        c = dict(c, velocity=sv)
        c, _ = jax.lax.scan(lambda cc, _: mech_step(cc, i_ref), c, None, length=n_mech_steps)
        return c, i_ref

    def position_period(c, ref):
        theta_ref = ref.theta if outer == "hybrid" else ref
        theta, _ = plant.measure(aux, c["plant"])
        step, coefficients = (loops.pid_step, drive.pid) if outer == "pid" else (loops.imc_step, drive.imc)
        sp, w_ref = step(coefficients, c["position"], theta_ref, theta)
        c = dict(c, position=sp)
        i_force = None
        if outer == "hybrid":
            sf, force = hybrid_law.step(hybrid, c["force"], (theta_ref - theta) * r, ref.coupling, ref.force_ff,
                                        rates.dt_position)
            c = dict(c, force=sf)
            k = hybrid_law.FORCE_AXIS
            i_force = force * r[..., k] / (params.eta[..., k] * drive.Kt[..., k])
        c, _ = jax.lax.scan(lambda cc, _: velocity_period(cc, w_ref, i_force), c, None, length=rates.n_position)
        return c, w_ref

    period, dt = {"current": (mech_step, rates.dt_mech), "velocity": (velocity_period, rates.dt_velocity)}.get(
        outer, (position_period, rates.dt_position))

    def body(c, ref):
        start = c
        c, command = period(c, ref)
        return c, record(start, ref, command)

    if remat:
        body = jax.checkpoint(body)

    _, rec = jax.lax.scan(body, initial_state(drive, plant, aux, outer), reference)
    t = jnp.arange(rec["reference"].shape[0]) * dt
    return Trace(t=t, **rec)


_rollout_jit = jax.jit(rollout, static_argnames=("plant", "rates", "outer", "remat"))


@functools.lru_cache(maxsize=None)
def _batched_rollout(plant, rates, outer, load_axis):
    return jax.jit(jax.vmap(functools.partial(rollout, plant=plant, rates=rates, outer=outer),
                            in_axes=(0, load_axis, 0)))


def simulate(params: ServoParams | None = None, reference=None, *, load=None, plant=AxisPlant(),
             rates: LoopRates = LoopRates(), mode: str = "imc") -> Trace:
    """Simulate the position-controlled machine (host-side entry point).

    ``reference``: slider positions [m], shape ``(N,)`` (same for every axis) or
    ``(N, n_axes)``, one sample per position-loop period ``rates.dt_position``; the
    machine starts at rest at zero.  ``mode``: 'imc' (2-DOF IMC) or 'pid' (baseline).
    ``params`` with a leading batch dimension ``(B, n_axes)`` runs a vmapped batch
    (``load`` batched alike or shared).  Returns a :class:`Trace`.
    """
    params = ServoParams.table1() if params is None else params
    load = AxisLoad.default() if load is None else load
    if mode not in MODES:
        raise ParameterError(f"mode: expected one of {MODES}, got {mode!r}")
    validate(params)
    validate(load)
    ref = np.asarray(reference, dtype=float) if reference is not None else None
    if ref is None or ref.ndim not in (1, 2) or ref.shape[0] < 1 or (ref.ndim == 2 and ref.shape[1] != plant.n_axes):
        raise ParameterError(f"reference: expected slider positions of shape (N,) or (N, {plant.n_axes}), "
                             f"got {None if ref is None else ref.shape}")
    if not np.isfinite(ref).all():
        raise ParameterError("reference: expected finite slider positions [m], found NaN or inf")
    if ref.ndim == 1:
        ref = np.repeat(ref[:, None], plant.n_axes, axis=1)
    theta_ref = jnp.asarray(ref) / screw_ratio(params)[..., None, :]
    if np.ndim(params.lambda1) == 1:
        return _rollout_jit(params, load, theta_ref, plant=plant, rates=rates, outer=mode)
    load_axis = 0 if np.ndim(load.mass) == 2 else None
    return _batched_rollout(plant, rates, mode, load_axis)(params, load, theta_ref)
