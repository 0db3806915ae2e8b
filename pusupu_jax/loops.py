"""The servo cascade of one drive (paper eq. 1-9) as discrete-time pure step functions.

:func:`discretize` turns :class:`~pusupu_jax.params.ServoParams` into a
:class:`Drive` (a pytree of discrete coefficients at the loop rates, computed once
per rollout, differentiable in every parameter); each loop is then an ``init``/``step``
pair ``step(coeffs, state, ref, meas) -> (state, out)``, vectorised over axes (and any
leading batch dimensions).  The hardware bridge runs these same functions.

Loops and their signals (motor side; Fig. 2 of the paper):

* current loop, at ``rates.f_current``: reference filter ``1/(Tcf s+1)`` (eq. 5) on
  ``I_r`` [A], feedback filter ``Kcf/(Tcf s+1)`` (eq. 4) on the measured current,
  PI ``Ki(Ti s+1)/(Ti s)`` (eq. 1) plus the back-EMF feedforward
  ``emf_ff Ke w / Kn`` giving the inverter command ``u`` [V], clamped to ``+-V_max/Kn``
  with conditional-integration anti-windup;
* electrical model, at the same rate (zero-order hold, exact for held inputs):
  inverter ``Kn/(Tn s+1)`` (eq. 2) and armature ``1/(R+Ls)`` (eq. 3) driven by
  ``Kn u - Ke w``; motor torque ``Te = Kt Im`` [N m];
* velocity loop, every ``n_velocity`` ticks: filters ``1/(Tw s+1)`` (eq. 8) and
  ``Kw/(Tw s+1)`` (eq. 7), PI ``Kv(Tv s+1)/(Tv s)`` (eq. 6) giving ``I_r``, clamped to
  ``+-I_max`` with anti-windup;
* position loop, every ``n_velocity*n_position`` ticks, giving the velocity reference
  [rad/s] from the motor-angle reference [rad]: 2-DOF IMC
  ``w_r = C2 (C1 theta' - theta)`` with ``C2 = (3 l2 s+1)(T0 s+1) / (3 l2^2 s (l2/3 s+1))``
  (eq. 9) and the prefilter ``C1`` in one of two forms (``ServoParams.imc_form``, see
  :func:`imc_c1` and ``docs/imc.md``); or the PID baseline ``Kp + Ki/s + Kd s/(Tf s+1)`` on
  ``theta' - theta``, plus the velocity feedforward ``Kff (theta'_k - theta'_{k-1})/dt``
  ('pid_ff', the industry-standard baseline) or alone ('pid': the same with ``Kff = 0``).

The current and velocity loops have the same structure (reference filter, feedback
filter, clamped PI) and share :class:`PILoop` and :func:`pi_loop_step`.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import numpy.typing as npt
from jax.typing import ArrayLike

from . import lti
from .lti import LTI
from .params import LoopRates, ServoParams
from .plant.axis import screw_ratio


@jax.tree_util.register_dataclass
@dataclass(frozen=True)
class PILoop:
    """Discrete reference filter, feedback filter and PI with an output limit (same units as the output)."""

    ref_filter: LTI
    fb_filter: LTI
    pi: LTI
    limit: Any


@jax.tree_util.register_dataclass
@dataclass(frozen=True)
class IMC:
    """Discrete 2-DOF IMC controllers: prefilter C1 and feedback C2 (eq. 9)."""

    c1: LTI
    c2: LTI


@jax.tree_util.register_dataclass
@dataclass(frozen=True)
class RosPID:
    """ROS's PID (control_toolbox ``Pid`` in ``pid_controller``) on the position loop, from the PID fields."""

    p: Any  # 1/s
    i: Any  # 1/s^2, inside the integral
    d: Any  # 1, on the velocity error
    ff: Any  # 1, on the reference velocity
    limit: Any  # rad/s: output and integral clamps, V_max / Ke
    dt: Any  # s: the controller_manager period (the position loop's)


@jax.tree_util.register_dataclass
@dataclass(frozen=True)
class Drive:
    """Every discrete coefficient of the cascade at its loop rate (one value per axis)."""

    current: PILoop
    velocity: PILoop
    imc: IMC
    pid: LTI
    velocity_ff: Any  # 1/s: Kff / dt_position, the pid_ff feedforward on the reference's backward difference
    ros: RosPID
    electrical: LTI  # states (inverter voltage [V], armature current [A]); inputs (u [V], w [rad/s])
    Kt: Any  # N m / A
    emf_gain: Any  # V/(rad/s): back-EMF feedforward emf_ff*Ke/Kn
    screw: Any  # m/rad: slider travel per motor radian, lead / 2 pi
    force_current: Any  # A/N: the current that pushes a slider force, r / (eta Kt)
    dt_position: Any  # s: the position loop's period


class PIState(NamedTuple):
    ref: Any
    fb: Any
    pi: Any


class IMCState(NamedTuple):
    c1: Any
    c2: Any


def first_order(gain: ArrayLike, tau: ArrayLike) -> LTI:
    """``gain / (tau s + 1)``; state: the filtered input ``x' = (u - x)/tau``, output ``gain x``."""
    return lti.ss([[-1.0 / tau]], [[1.0 / tau]], [[gain]], [[0.0 * tau]])


def lead_lag(a: ArrayLike, b: ArrayLike) -> LTI:
    """``(a s + 1)/(b s + 1)``; state: the input low-passed with ``b``, output ``(a/b) u + (1 - a/b) x``."""
    return lti.ss([[-1.0 / b]], [[1.0 / b]], [[1.0 - a / b]], [[a / b]])


def pi_controller(k: ArrayLike, ti: ArrayLike) -> LTI:
    """``k (ti s + 1) / (ti s)``; state: the integral term ``x' = (k/ti) e`` (in output units), output ``k e + x``."""
    return lti.ss([[0.0 * k]], [[k / ti]], [[1.0 + 0.0 * k]], [[k]])


def imc_c1(lambda1: ArrayLike, lambda2: ArrayLike, form: str = "full") -> LTI:
    """The 2-DOF IMC prefilter, in one of two forms (``docs/imc.md`` derives both).

    * ``'printed'``: eq. 9 as printed, ``C1 = (3 l1 s + 1)/(3 l2 s + 1)``.  With the loop's
      own response ``f_d = (3 l2 s+1)/(l2 s+1)^3`` the reference response is
      ``(3 l1 s+1)/(l2 s+1)^3``: lambda1 only moves a zero, and a ramp lags ``3 (l2 - l1)``.
    * ``'full'`` (default): ``C1 = f_r / f_d = (3 l1 s+1)(l2 s+1)^3 / ((l1 s+1)^3 (3 l2 s+1))``,
      so that the reference response is ``f_r = (3 l1 s+1)/(l1 s+1)^3``: lambda1 sets tracking
      and lambda2 disturbance rejection, as section 2.2 says (no ramp lag: type 2).  The printed
      form is this with the factor ``(l2 s+1)^3/(l1 s+1)^3`` missing.

    Realised as lead-lag sections in series (states: the reference low-passed, in rad).
    """
    printed = lead_lag(3.0 * lambda1, 3.0 * lambda2)
    if form == "printed":
        return printed
    if form != "full":
        raise ValueError(f"imc_c1: expected form 'full' or 'printed', got {form!r}")
    section = lead_lag(lambda2, lambda1)
    return lti.series(section, section, section, printed)


def filtered_pid(kp: ArrayLike, ki: ArrayLike, kd: ArrayLike, tau: ArrayLike) -> LTI:
    """``(kp + ki/s + kd s) / (tau s + 1)``; states: the integral term ``I' = ki e`` and the filtered output ``v``.

    ``v' = ((kp - kd/tau) e + I - v)/tau``, output ``(kd/tau) e + v``: both states in output units.
    """
    z = 0.0 * tau
    return lti.ss([[z, z], [1.0 / tau, -1.0 / tau]], [[ki], [(kp - kd / tau) / tau]], [[z, 1.0 + z]], [[kd / tau]])


def imc_c2(lambda2: ArrayLike, T0: ArrayLike) -> LTI:
    """Eq. 9, ``C2 = (3 l2 s+1)(T0 s+1) / (3 l2^2 s (l2/3 s + 1))``: the PID ``Kp = (3 l2 + T0)/(3 l2^2)``,
    ``Ki = 1/(3 l2^2)``, ``Kd = T0/l2`` behind the filter ``1/((l2/3) s + 1)`` (:func:`filtered_pid`)."""
    return filtered_pid(
        (3.0 * lambda2 + T0) / (3.0 * lambda2**2), 1.0 / (3.0 * lambda2**2), T0 / lambda2, lambda2 / 3.0
    )


def pid_controller(
    kp: ArrayLike, ki: ArrayLike, kd: jax.Array | npt.NDArray[np.floating[Any]] | float, tf_: ArrayLike
) -> LTI:
    """``kp + ki/s + kd s/(tf s + 1)``; states: the integral term ``I' = ki e`` and the input low-passed ``e_f``.

    Output ``kp e + I + (kd/tf)(e - e_f)``.
    """
    z = 0.0 * tf_
    return lti.ss([[z, z], [z, -1.0 / tf_]], [[ki], [1.0 / tf_]], [[1.0 + z, -kd / tf_]], [[kp + kd / tf_]])


def electrical_model(p: ServoParams) -> LTI:
    """Continuous inverter + armature: ``v' = (Kn u - v)/Tn``, ``L i' = v - R i - Ke w``; output ``i``."""
    z = jnp.zeros_like(p.R)
    A = jnp.stack([jnp.stack([-1.0 / p.Tn, z], -1), jnp.stack([1.0 / p.L, -p.R / p.L], -1)], -2)
    B = jnp.stack([jnp.stack([p.Kn / p.Tn, z], -1), jnp.stack([z, -p.Ke / p.L], -1)], -2)
    C = jnp.stack([z, jnp.ones_like(z)], -1)[..., None, :]
    D = jnp.zeros(z.shape + (1, 2))
    return LTI(A, B, C, D)


def discretize(p: ServoParams, rates: LoopRates) -> Drive:
    """All loops at their rates: controllers and filters with ``rates.method``, the electrical part with ZOH."""
    m = rates.method

    def pi_loop(k: ArrayLike, ti: ArrayLike, k_fb: ArrayLike, tau: ArrayLike, limit: ArrayLike, dt: float) -> PILoop:
        return PILoop(
            lti.c2d(first_order(jnp.ones_like(tau), tau), dt, m),
            lti.c2d(first_order(k_fb, tau), dt, m),
            lti.c2d(pi_controller(k, ti), dt, m),
            limit,
        )

    dt_p = rates.dt_position
    return Drive(
        current=pi_loop(p.Ki, p.Ti, p.Kcf, p.Tcf, p.V_max / p.Kn, rates.dt_current),
        velocity=pi_loop(p.Kv, p.Tv, p.Kw, p.Tw, p.I_max, rates.dt_velocity),
        imc=IMC(lti.c2d(imc_c1(p.lambda1, p.lambda2, p.imc_form), dt_p, m), lti.c2d(imc_c2(p.lambda2, p.T0), dt_p, m)),
        pid=lti.c2d(pid_controller(p.Kp_pid, p.Ki_pid, p.Kd_pid, p.Tf_pid), dt_p, m),
        velocity_ff=p.Kff_pid / dt_p,
        ros=RosPID(p.Kp_pid, p.Ki_pid, p.Kd_pid, p.Kff_pid, p.V_max / p.Ke, dt_p),
        **_motor(p, rates),
        screw=screw_ratio(p),
        force_current=screw_ratio(p) / (p.eta * p.Kt),
        dt_position=dt_p,
    )


def on_machine(drive: Drive, p: ServoParams, rates: LoopRates) -> Drive:
    """``drive`` on a motor whose values are ``p``'s: its electrical model (``R``, ``L``, ``Ke``, the inverter), its
    torque constant ``Kt`` [N m/A], and the drive's own back-EMF feedforward ``emf_ff Ke / Kn`` [V/(rad/s)] (a drive
    commissioned with its motor's data, as the simulated robot's drives are) from ``p``; what the host computes from
    the machine file keeps ``drive``'s, the values it was told (:func:`discretize`): the hybrid force law's current
    ``r / (eta Kt)`` [A/N] and ROS's PID clamp ``V_max / Ke`` [rad/s]."""
    return dataclasses.replace(drive, **_motor(p, rates))


def _motor(p: ServoParams, rates: LoopRates) -> dict[str, Any]:
    """The :class:`Drive` fields of the motor and of what its drive knows of it (:func:`on_machine`)."""
    return {
        "electrical": lti.c2d(electrical_model(p), rates.dt_current, "zoh"),
        "Kt": p.Kt,
        "emf_gain": p.emf_ff * p.Ke / p.Kn,
    }


# ---------------------------------------------------------------- init / step pairs


def pi_loop_init(c: PILoop) -> PIState:
    return PIState(lti.zeros_state(c.ref_filter), lti.zeros_state(c.fb_filter), lti.zeros_state(c.pi))


def pi_loop_step(
    c: PILoop, s: PIState, ref: jax.Array, meas: jax.Array, feedforward: ArrayLike = 0.0
) -> tuple[PIState, jax.Array]:
    """One sample of a filtered PI loop (current: A -> V; velocity: rad/s -> A).

    ``feedforward`` is added to the PI output; the sum is clamped to ``+-c.limit``; while clamped, the PI state is
    frozen when
    the error drives further into the limit (conditional-integration anti-windup).
    """
    x_ref, r = lti.step_siso(c.ref_filter, s.ref, ref)
    x_fb, y = lti.step_siso(c.fb_filter, s.fb, meas)
    e = r - y
    x_pi, out = lti.step_siso(c.pi, s.pi, e)
    out = out + feedforward
    clamped = jnp.clip(out, -c.limit, c.limit)
    hold = e * (out - clamped) > 0
    x_pi = jnp.where(hold[..., None], s.pi, x_pi)
    return PIState(x_ref, x_fb, x_pi), clamped


def pi_loop_rest(c: PILoop, ref: jax.Array, meas: jax.Array, out: ArrayLike) -> PIState:
    """The state of a PI loop that has held ``out`` for a long time with constant ``ref`` and ``meas``.

    Both filters sit at their steady values and the PI's integrator holds ``out`` (its error
    must then be zero: ``ref`` and ``meas`` at the ratio of the feedback and reference filter gains).
    """
    return PIState(
        lti.dc_state(c.ref_filter, ref[..., None]),
        lti.dc_state(c.fb_filter, meas[..., None]),
        lti.integrator_state(c.pi, out),
    )


def imc_rest(c: IMC, theta0: ArrayLike) -> IMCState:
    """The IMC at rest with the reference held at ``theta0`` [rad] and zero error (``theta0 = 0``: all zero)."""
    theta0 = jnp.broadcast_to(jnp.asarray(theta0, c.c1.A.dtype), c.c1.A.shape[:-2])
    return IMCState(lti.dc_state(c.c1, theta0[..., None]), lti.zeros_state(c.c2))


def imc_step(c: IMC, s: IMCState, theta_ref: jax.Array, theta: jax.Array) -> tuple[IMCState, jax.Array]:
    """2-DOF IMC (eq. 9): ``w_r = C2 (C1 theta_ref - theta)``; angles [rad], output [rad/s]."""
    x1, r1 = lti.step_siso(c.c1, s.c1, theta_ref)
    x2, w_ref = lti.step_siso(c.c2, s.c2, r1 - theta)
    return IMCState(x1, x2), w_ref


class PIDFFState(NamedTuple):
    pid: Any
    previous_ref: Any  # the last motor-angle reference, rad


def pid_ff_init(c: LTI, theta_ref0: ArrayLike = 0.0) -> PIDFFState:
    """The PID at rest, the reference held at ``theta_ref0`` [rad] before the first sample."""
    x = lti.zeros_state(c)
    return PIDFFState(x, jnp.broadcast_to(jnp.asarray(theta_ref0, x.dtype), x.shape[:-1]))


def pid_ff_step(
    c: LTI, velocity_ff: ArrayLike, s: PIDFFState, theta_ref: jax.Array, theta: jax.Array
) -> tuple[PIDFFState, jax.Array]:
    """PID plus velocity feedforward: ``w_r = PID(theta_ref - theta) + Kff (theta_ref - previous)/dt`` [rad/s]; the
    PID baseline alone is this at ``velocity_ff = 0``."""
    x, w_pid = lti.step_siso(c, s.pid, theta_ref - theta)
    return PIDFFState(x, theta_ref), w_pid + velocity_ff * (theta_ref - s.previous_ref)


class RosPIDState(NamedTuple):
    integral: Any  # the I term, rad/s
    previous_ref: Any  # the last motor-angle reference, rad


def ros_pid_init(c: RosPID, theta_ref0: ArrayLike = 0.0) -> RosPIDState:
    z = jnp.zeros_like(c.p)
    return RosPIDState(z, z + theta_ref0)


def ros_pid_step(
    c: RosPID, s: RosPIDState, theta_ref: jax.Array, theta: jax.Array, omega: jax.Array
) -> tuple[RosPIDState, jax.Array]:
    """control_toolbox's PID as ``pid_controller`` runs it with position and velocity interfaces [rad, rad/s].

    ``u = clamp(p e + I + d (w_ref - w))``, command ``ff w_ref + u`` with ``w_ref`` the reference's
    backward difference; then ``I += dt i e`` unless conditional integration holds it (clamped and the
    error pushing further), and ``I`` is clamped.  No derivative filter, no output filter, no prefilter.
    """
    w_ref = (theta_ref - s.previous_ref) / c.dt
    e = theta_ref - theta
    unsat = c.p * e + s.integral + c.d * (w_ref - omega)
    u = jnp.clip(unsat, -c.limit, c.limit)
    hold = (unsat != u) & (e * unsat > 0)
    integral = jnp.clip(jnp.where(hold, s.integral, s.integral + c.dt * c.i * e), -c.limit, c.limit)
    return RosPIDState(integral, theta_ref), c.ff * w_ref + u


def electrical_init(c: LTI) -> jax.Array:
    return lti.zeros_state(c)


def electrical_rest(c: LTI, current: jax.Array) -> tuple[jax.Array, jax.Array]:
    """Inverter and armature at rest (motor still) carrying ``current`` [A]; returns ``(state, command u [V])``."""
    unit = lti.dc_state(c, jnp.stack([jnp.ones_like(current), jnp.zeros_like(current)], axis=-1))
    u = current / electrical_current(unit)
    return unit * u[..., None], u


def electrical_current(x: jax.Array) -> jax.Array:
    """Armature current [A] of an electrical state."""
    return x[..., 1]


def electrical_step(c: LTI, x: jax.Array, u: jax.Array, omega: jax.Array) -> jax.Array:
    """Advance the inverter and armature one tick with command ``u`` [V] and speed ``omega`` [rad/s] held."""
    return lti.update(c, x, jnp.stack([u, omega], axis=-1))
