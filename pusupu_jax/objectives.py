"""Differentiable objective terms over a machine rollout (JAX), for the tuner.

Every term is a scalar in physical units, smooth almost everywhere, computed from a
:class:`~pusupu_jax.trace.Trace` of the MJX machine and the platform path it followed:

* ``track_rms`` [m]: RMS platform position error; ``track_max`` [m]: its smooth maximum;
* ``branch_rms`` [m]: RMS slider error over all branches; ``branch_max`` [m]: its smooth maximum;
* ``force_peak`` [N]: smooth peak of the branch forces over time and branches;
* ``balance`` [1]: spread of the per-branch smooth force peaks (standard deviation / mean);
* ``rho`` [m s]: the synchronous error of eq. 12 (RMS form) at the end of the run;
* ``effort`` [A^2]: mean squared motor current;
* ``saturation`` [1]: mean squared excess of the current over ``sat_fraction * I_max``
  (the velocity PI's clamp) and of the back-EMF over ``sat_fraction * V_max``.

:func:`smooth_max` is ``logsumexp(k x) / k``: never below the true maximum, and above it by
at most ``log(n) / k`` for ``n`` samples, so it approaches the peak as the sharpness ``k``
grows (a parameter: too sharp and its gradient reaches only the single largest sample).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import jax
import jax.numpy as jnp

from .hybrid import synchronous_error
from .metrics import safe_sqrt, tracking_error
from .plant.axis import screw_ratio

if TYPE_CHECKING:
    from .params import ServoParams
    from .trace import Trace

TERMS = ("track_rms", "track_max", "branch_rms", "branch_max", "force_peak", "balance", "rho", "effort", "saturation")


def smooth_max(x: jax.Array, sharpness: float, axis: int | tuple[int, ...] | None = None) -> jax.Array:
    """``logsumexp(sharpness * x) / sharpness`` over ``axis`` (all axes by default); units of ``x``."""
    return jax.nn.logsumexp(sharpness * x, axis=axis) / sharpness


def branch_force(trace: Trace, servo: ServoParams) -> jax.Array:
    """Slider force of each branch ``eta Kt i / r`` [N], shape ``(..., N, 6)``."""
    force: jax.Array = trace.torque * servo.eta / screw_ratio(servo)
    return force


def terms(
    trace: Trace,
    servo: ServoParams,
    path: jax.Array,
    dt: float,
    sharpness_force: float = 1.0,
    sharpness_error: float = 2000.0,
    sat_fraction: float = 0.95,
) -> dict[str, jax.Array]:
    """Every objective term of a machine trace (see the module docstring).

    ``path``: the platform poses ``(N, 5)`` the machine was asked to follow (one per
    position period ``dt`` [s]); ``sharpness_force`` [1/N] and ``sharpness_error`` [1/m]
    set the smooth maxima.
    """
    error_sq = jnp.sum((trace.observation["platform_pos"] - path[:, :3]) ** 2, axis=-1)  # m^2
    error = safe_sqrt(error_sq)  # exactly 0 at the start
    force = jnp.abs(branch_force(trace, servo))
    branch_error = tracking_error(trace, servo)
    per_branch = smooth_max(force, sharpness_force, axis=0)
    excess_i = jax.nn.relu(jnp.abs(trace.current) - sat_fraction * servo.I_max) / servo.I_max
    excess_v = jax.nn.relu(jnp.abs(servo.Ke * trace.omega) - sat_fraction * servo.V_max) / servo.V_max
    return {
        "track_rms": jnp.sqrt(jnp.mean(error_sq)),
        "track_max": smooth_max(error, sharpness_error),
        "branch_rms": jnp.sqrt(jnp.mean(branch_error**2)),
        "branch_max": smooth_max(jnp.abs(branch_error), sharpness_error),
        "force_peak": smooth_max(force, sharpness_force),
        "balance": jnp.std(per_branch) / jnp.mean(per_branch),
        "rho": synchronous_error(branch_error, dt)[-1],
        "effort": jnp.mean(trace.current**2),
        "saturation": jnp.mean(excess_i**2) + jnp.mean(excess_v**2),
    }
