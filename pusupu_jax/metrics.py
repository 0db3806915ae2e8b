"""Tracking metrics: the single-axis ones of a :class:`~pusupu_jax.trace.Trace` of a position mode (differentiable JAX),
and the names of a machine run's metrics (:class:`Metric`)."""

from __future__ import annotations

import enum
from typing import TYPE_CHECKING

import jax
import jax.numpy as jnp

from .plant.axis import screw_ratio

if TYPE_CHECKING:
    from .params import ServoParams
    from .trace import Trace


class Metric(enum.StrEnum):
    """A metric's key in a run's report (JSON and Python dicts alike)."""

    RMS_TRACKING_ERROR_MM = "rms_tracking_error_mm"  # platform position error, RMS over the run [mm]
    MAX_TRACKING_ERROR_MM = "max_tracking_error_mm"  # platform position error, largest [mm]
    BRANCH_RMS_ERROR_MM = "branch_rms_error_mm"  # per branch: slider error, RMS [mm]
    BRANCH_REVERSAL_ERROR_MM = "branch_reversal_error_mm"  # per branch: largest slider error just after a reversal
    MOTOR_TORQUE_PEAK_NM = "motor_torque_peak_nm"  # per branch: largest motor torque [N m]
    BRANCH_FORCE_PEAK_N = "branch_force_peak_n"  # per branch: largest force along the rod [N]
    SYNC_ERROR_RHO = "sync_error_rho"  # the synchronous error of eq. 11 at the end [mm s]
    LOOP_CLOSURE_RESIDUAL_MAX_MM = "loop_closure_residual_max_mm"  # largest loop-closure residual of the model [mm]


def safe_sqrt(x: jax.Array) -> jax.Array:
    """``sqrt`` with a zero (not NaN) derivative at 0, in forward and reverse mode (an error exactly 0 at rest)."""
    positive = x > 0
    return jnp.where(positive, jnp.sqrt(jnp.where(positive, x, 1.0)), 0.0)


def tracking_error(trace: Trace, params: ServoParams) -> jax.Array:
    """Slider position error ``x - x_ref`` [m], shape ``(..., N, n_axes)``."""
    error: jax.Array = (trace.theta - trace.reference) * screw_ratio(params)[..., None, :]
    return error


def summary(trace: Trace, params: ServoParams) -> dict[str, list[float]]:
    """Per-axis tracking metrics (host-side floats): RMS and max error [mm], peak current [A] and torque [N m]."""
    e = tracking_error(trace, params)
    per_axis = {
        "rms_error_mm": jnp.sqrt(jnp.mean(e**2, axis=-2)) * 1e3,
        "max_error_mm": jnp.max(jnp.abs(e), axis=-2) * 1e3,
        "peak_current_a": jnp.max(jnp.abs(trace.current), axis=-2),
        "peak_torque_nm": jnp.max(jnp.abs(trace.torque), axis=-2),
    }
    return {k: [float(x) for x in jnp.ravel(v)] for k, v in per_axis.items()}


def step_summary(trace: Trace, params: ServoParams, tolerance: float = 0.02) -> dict[str, list[float | None]]:
    """Per-axis step metrics against the final reference: overshoot [%] and settling time [s].

    The settling time is when the error last leaves ``tolerance`` times the step; None if
    the error is still outside at the end of the trace.
    """
    e = tracking_error(trace, params)
    final = trace.reference[..., -1, :] * screw_ratio(params)
    x = final + e
    overshoot = jnp.maximum(jnp.max(x, axis=-2) / final - 1.0, 0.0) * 100
    outside = jnp.abs(e) > tolerance * jnp.abs(final)
    last = jnp.max(jnp.where(outside, jnp.arange(e.shape[-2])[:, None], -1), axis=-2)
    n, dt = e.shape[-2], float(trace.t[1] - trace.t[0])
    return {
        "overshoot_pct": [float(v) for v in jnp.ravel(overshoot)],
        "settling_time_s": [None if int(k) == n - 1 else (int(k) + 1) * dt for k in jnp.ravel(last)],
    }
