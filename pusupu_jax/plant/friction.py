"""Drive-train friction of each axis, at the slider: one law for every plant.

``F = coulomb tanh(v / v_coulomb) + viscous v`` [N], opposing the slider's speed ``v`` [m/s]
(:class:`~pusupu_jax.params.ServoParams` fields ``coulomb`` [N], ``viscous`` [N s/m],
``v_coulomb`` [m/s]).  The tanh is a smooth Coulomb law, so gradients pass through a velocity
reversal; MuJoCo's ``frictionloss`` is not used, since it lives in the constraint solver and is
not smooth.

The MJX machine and the simulated robot (C MuJoCo) apply :func:`slider_friction` as a force on
each slide joint.  The single-axis plant integrates the viscous part exactly with its linear
mechanics (``b_eff``) and adds :func:`coulomb_friction`, the same law split where it is linear.
"""

from __future__ import annotations

import jax.numpy as jnp


def coulomb_friction(servo, v):
    """The Coulomb part ``coulomb tanh(v / v_coulomb)`` [N] at slider speeds ``v`` [m/s] ``(..., 6)``."""
    return servo.coulomb * jnp.tanh(v / servo.v_coulomb)


def slider_friction(servo, v):
    """The whole friction force [N] opposing slider speeds ``v`` [m/s] ``(..., 6)``: Coulomb plus viscous."""
    return coulomb_friction(servo, v) + servo.viscous * v
