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
  ``w_r = C2 (C1 theta' - theta)`` with ``C1 = (3 l1 s+1)/(3 l2 s+1)`` and
  ``C2 = (3 l2 s+1)(T0 s+1) / (3 l2^2 s (l2/3 s+1))`` (eq. 9), or the PID baseline
  ``Kp + Ki/s + Kd s/(Tf s+1)`` on ``theta' - theta``.

The current and velocity loops have the same structure (reference filter, feedback
filter, clamped PI) and share :class:`PILoop` and :func:`pi_loop_step`.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp

from . import lti
from .lti import LTI
from .params import LoopRates, ServoParams


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
class Drive:
    """Every discrete coefficient of the cascade at its loop rate (one value per axis)."""

    current: PILoop
    velocity: PILoop
    imc: IMC
    pid: LTI
    electrical: LTI  # states (inverter voltage [V], armature current [A]); inputs (u [V], w [rad/s])
    Kt: Any  # N m / A
    emf_gain: Any  # V/(rad/s): back-EMF feedforward emf_ff*Ke/Kn


class PIState(NamedTuple):
    ref: Any
    fb: Any
    pi: Any


class IMCState(NamedTuple):
    c1: Any
    c2: Any


def first_order(gain, tau) -> LTI:
    """``gain / (tau s + 1)``."""
    return lti.tf([gain], [tau, 1.0])


def pi_controller(k, ti) -> LTI:
    """``k (ti s + 1) / (ti s)``."""
    return lti.tf([k * ti, k], [ti, 0.0])


def imc_c1(lambda1, lambda2) -> LTI:
    """Eq. 9, ``C1 = (3 l1 s + 1)/(3 l2 s + 1)``."""
    return lti.tf([3.0 * lambda1, 1.0], [3.0 * lambda2, 1.0])


def imc_c2(lambda2, T0) -> LTI:
    """Eq. 9, ``C2 = (3 l2 s+1)(T0 s+1) / (3 l2^2 s (l2/3 s + 1))``, expanded in powers of s."""
    num = [3.0 * lambda2 * T0, 3.0 * lambda2 + T0, 1.0]
    den = [lambda2**3, 3.0 * lambda2**2, 0.0]
    return lti.tf(num, den)


def pid_controller(kp, ki, kd, tf_) -> LTI:
    """``kp + ki/s + kd s/(tf s + 1)`` over the common denominator ``s (tf s + 1)``."""
    return lti.tf([kp * tf_ + kd, kp + ki * tf_, ki], [tf_, 1.0, 0.0])


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

    def pi_loop(k, ti, k_fb, tau, limit, dt):
        return PILoop(lti.c2d(first_order(jnp.ones_like(tau), tau), dt, m),
                      lti.c2d(first_order(k_fb, tau), dt, m),
                      lti.c2d(pi_controller(k, ti), dt, m), limit)

    dt_p = rates.dt_position
    return Drive(
        current=pi_loop(p.Ki, p.Ti, p.Kcf, p.Tcf, p.V_max / p.Kn, rates.dt_current),
        velocity=pi_loop(p.Kv, p.Tv, p.Kw, p.Tw, p.I_max, rates.dt_velocity),
        imc=IMC(lti.c2d(imc_c1(p.lambda1, p.lambda2), dt_p, m), lti.c2d(imc_c2(p.lambda2, p.T0), dt_p, m)),
        pid=lti.c2d(pid_controller(p.Kp_pid, p.Ki_pid, p.Kd_pid, p.Tf_pid), dt_p, m),
        electrical=lti.c2d(electrical_model(p), rates.dt_current, "zoh"),
        Kt=p.Kt,
        emf_gain=p.emf_ff * p.Ke / p.Kn,
    )


# ---------------------------------------------------------------- init / step pairs

def pi_loop_init(c: PILoop) -> PIState:
    return PIState(lti.zeros_state(c.ref_filter), lti.zeros_state(c.fb_filter), lti.zeros_state(c.pi))


def pi_loop_step(c: PILoop, s: PIState, ref, meas, feedforward=0.0):
    """One sample of a filtered PI loop (current: A -> V; velocity: rad/s -> A).

    ``feedforward`` is added to the PI output; the sum is clamped to ``+-c.limit``; while clamped, the PI state is frozen when
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


def imc_init(c: IMC) -> IMCState:
    return IMCState(lti.zeros_state(c.c1), lti.zeros_state(c.c2))


def imc_step(c: IMC, s: IMCState, theta_ref, theta):
    """2-DOF IMC (eq. 9): ``w_r = C2 (C1 theta_ref - theta)``; angles [rad], output [rad/s]."""
    x1, r1 = lti.step_siso(c.c1, s.c1, theta_ref)
    x2, w_ref = lti.step_siso(c.c2, s.c2, r1 - theta)
    return IMCState(x1, x2), w_ref


def pid_init(c: LTI):
    return lti.zeros_state(c)


def pid_step(c: LTI, s, theta_ref, theta):
    """PID baseline on the position error [rad] -> velocity reference [rad/s]."""
    return lti.step_siso(c, s, theta_ref - theta)


def electrical_init(c: LTI):
    return lti.zeros_state(c)


def electrical_current(x):
    """Armature current [A] of an electrical state."""
    return x[..., 1]


def electrical_step(c: LTI, x, u, omega):
    """Advance the inverter and armature one tick with command ``u`` [V] and speed ``omega`` [rad/s] held."""
    return lti.update(c, x, jnp.stack([u, omega], axis=-1))
