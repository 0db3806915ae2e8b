"""Single-axis plant: motor rotor + ball screw + lumped load mass, with gravity and friction (no MJX).

Motor side, per axis (``r = lead / 2 pi`` [m/rad], efficiency ``eta``)::

    J_eff w' = Te - b_eff w - tau_ext,   theta' = w
    J_eff = J + m r^2 / eta,   b_eff = c_v r^2 / eta
    tau_ext = (r / eta) (m g sin(inclination) + F_c tanh(v / v_c)),   v = r w

with the drive train's friction ``F_c tanh(v / v_c) + c_v v`` of :mod:`pusupu_jax.plant.friction` (the
machine's ``ServoParams`` fields ``coulomb``, ``viscous``, ``v_coulomb``).

The linear part is integrated exactly (zero-order hold of ``Te`` and ``tau_ext`` over the
step, matrix exponential); the nonlinear load ``tau_ext`` is evaluated at the start of
each step (exponential Euler), so with no Coulomb friction the plant is exactly the ZOH
sampling of the linear model that :mod:`pusupu_jax.analysis` builds.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import jax
import jax.numpy as jnp

from .. import lti
from ..params import N_AXES, AxisLoad, ServoParams
from ..programs import describe
from .friction import Friction, coulomb_friction


@jax.tree_util.register_dataclass
@dataclass(frozen=True)
class AxisAux:
    step: lti.LTI  # discrete mechanics, states (theta, w), inputs (Te, tau_ext)
    r: Any  # m/rad
    load_force: Any  # N, gravity component along the rail
    friction: Friction  # the drive train's friction law's parameters
    eta: Any


@dataclass(frozen=True)
class AxisPlant:
    """Six independent single-axis plants (see the module docstring)."""

    n_axes: int = N_AXES

    def key(self) -> str:
        """A stable description of all that the traced functions read from this plant (its axis count), for the
        names of the traced programs kept on disk (:mod:`pusupu_jax.programs`)."""
        return describe(self)

    def prepare(self, servo: ServoParams, load: AxisLoad, dt: float) -> AxisAux:
        return AxisAux(
            lti.c2d(mechanics(servo, load), dt, "zoh"),
            screw_ratio(servo),
            load.mass * load.g * jnp.sin(load.inclination),
            Friction.of(servo),
            servo.eta,
        )

    def init(self, aux: AxisAux) -> jax.Array:
        return jnp.zeros(aux.r.shape + (2,))

    def statics(self, aux: AxisAux, state: jax.Array) -> jax.Array:
        """The slider force [N] that holds each axis still in ``state``: gravity along the rail (friction is 0 at
        rest), ``(..., n_axes)``."""
        force: jax.Array = aux.load_force * jnp.ones_like(state[..., 0])
        return force

    def holding_torque(
        self, aux: AxisAux, statics: jax.Array, force_axis: int | None = None, force: Any = None
    ) -> jax.Array:
        """Motor torques [N m] that hold each axis still against its :meth:`statics`.

        The axes are independent: ``force_axis`` (pushing a slider force ``force`` [N]) leaves the others as they are.
        """
        torque: jax.Array = aux.r / aux.eta * statics
        if force_axis is None:
            return torque
        return torque.at[..., force_axis].set(force * aux.r[..., force_axis] / aux.eta[..., force_axis])

    def measure(self, aux: AxisAux, state: jax.Array) -> tuple[jax.Array, jax.Array]:
        return state[..., 0], state[..., 1]

    def step(self, aux: AxisAux, state: jax.Array, torque: jax.Array) -> jax.Array:
        v = aux.r * state[..., 1]
        tau_ext = aux.r / aux.eta * (aux.load_force + coulomb_friction(aux.friction, v))
        return lti.update(aux.step, state, jnp.stack([torque, tau_ext], axis=-1))

    def slider(self, aux: AxisAux, state: jax.Array) -> tuple[jax.Array, jax.Array]:
        return aux.r * state[..., 0], aux.r * state[..., 1]

    def observe(self, aux: AxisAux, state: jax.Array) -> tuple[()]:
        """Nothing: the state is the motor angle and speed, which the trace already holds."""
        return ()


def screw_ratio(servo: ServoParams) -> Any:
    """Slider travel per motor radian ``lead / 2 pi`` [m/rad]."""
    return servo.lead / (2.0 * jnp.pi)


def mechanics(servo: ServoParams, load: AxisLoad) -> lti.LTI:
    """Continuous linear mechanics: states (theta [rad], w [rad/s]), inputs (Te, tau_ext) [N m]."""
    r = screw_ratio(servo)
    j_eff = servo.J + load.mass * r**2 / servo.eta
    b_eff = servo.viscous * r**2 / servo.eta
    z, one = jnp.zeros_like(j_eff), jnp.ones_like(j_eff)
    A = jnp.stack([jnp.stack([z, one], -1), jnp.stack([z, -b_eff / j_eff], -1)], -2)
    B = jnp.stack([jnp.stack([z, z], -1), jnp.stack([1.0 / j_eff, -1.0 / j_eff], -1)], -2)
    C = jnp.broadcast_to(jnp.eye(2), z.shape + (2, 2))
    return lti.LTI(A, B, C, jnp.zeros(z.shape + (2, 2)))
