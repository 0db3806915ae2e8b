"""Drive-train friction of each axis, at the slider: one law for every plant.

``F = coulomb tanh(v / v_coulomb) + viscous v`` [N], opposing the slider's speed ``v`` [m/s]
(:class:`~pusupu_jax.params.ServoParams` fields ``coulomb`` [N], ``viscous`` [N s/m],
``v_coulomb`` [m/s]).  The tanh is a smooth Coulomb law, so gradients pass through a velocity
reversal; MuJoCo's ``frictionloss`` is not used, since it lives in the constraint solver and is
not smooth.

The MJX machine (:meth:`~pusupu_jax.plant.mjx_plant.MJXPlant.step`) and the simulated robot
(C MuJoCo, :class:`pusupu_jax.sim_robot.robot.RobotModel`) apply ``-slider_friction`` as a force on each
slide joint, beside the motor's force, evaluated at the slider speeds at the start of each
mechanical step.  The single-axis plant integrates the viscous part exactly with its linear
mechanics (``b_eff``) and adds :func:`coulomb_friction`, the same law split where it is linear.

The functions take traced or JAX arrays (the plants' steps) and numpy arrays alike: with numpy
parameters and speeds they compute in numpy, so the simulated robot's host-side step (every
velocity period, 4 kHz by default) pays no JAX dispatch: 2 us a call on the 2-core CPU.
"""

from __future__ import annotations

from dataclasses import dataclass
from types import ModuleType
from typing import TYPE_CHECKING, Any

import jax
import jax.numpy as jnp
import numpy as np

if TYPE_CHECKING:
    from jax.typing import ArrayLike

    from ..params import ServoParams


@jax.tree_util.register_dataclass
@dataclass(frozen=True)
class Friction:
    """The law's parameters per axis ``(..., 6)``: ``coulomb`` [N], ``viscous`` [N s/m], ``v_coulomb`` [m/s]."""

    coulomb: Any
    viscous: Any
    v_coulomb: Any

    @classmethod
    def of(cls, servo: ServoParams) -> "Friction":
        """The friction fields of ``servo`` (a :class:`~pusupu_jax.params.ServoParams`), as they are (traced or not)."""
        return cls(servo.coulomb, servo.viscous, servo.v_coulomb)


def _array_module(*arrays: object) -> ModuleType:
    """numpy when every input is a numpy array or a number, jax.numpy otherwise (JAX or traced arrays)."""
    return np if all(isinstance(a, (np.ndarray, np.generic, float, int)) for a in arrays) else jnp


def coulomb_friction(friction: Friction | ServoParams, v: ArrayLike) -> Any:
    """The Coulomb part ``coulomb tanh(v / v_coulomb)`` [N] at slider speeds ``v`` [m/s] ``(..., 6)``.

    ``friction``: a :class:`Friction` or anything with its fields (a ``ServoParams``)."""
    xp = _array_module(friction.coulomb, friction.v_coulomb, v)
    return friction.coulomb * xp.tanh(v / friction.v_coulomb)


def slider_friction(friction: Friction | ServoParams, v: ArrayLike) -> Any:
    """The whole friction force [N] opposing slider speeds ``v`` [m/s] ``(..., 6)``: Coulomb plus viscous."""
    return coulomb_friction(friction, v) + friction.viscous * v
