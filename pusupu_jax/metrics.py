"""Tracking metrics: the single-axis ones of a :class:`~pusupu_jax.trace.Trace` of a position mode (differentiable JAX),
and a machine run's (:class:`MachineMetrics`, named by :class:`Metric`)."""

from __future__ import annotations

import dataclasses
import enum
from typing import TYPE_CHECKING, Any

import jax
import jax.numpy as jnp

from .plant.axis import screw_ratio

if TYPE_CHECKING:
    from .params import ServoParams
    from .trace import Trace


class Metric(enum.StrEnum):
    """A machine run's metric: the name of its :class:`MachineMetrics` attribute and its key in the JSON written.
    The highest branch force peak is derived from the six peaks: a property, written by the tune reports only."""

    RMS_TRACKING_ERROR_MM = "rms_tracking_error_mm"  # platform position error, RMS over the run [mm]
    MAX_TRACKING_ERROR_MM = "max_tracking_error_mm"  # platform position error, largest [mm]
    BRANCH_RMS_ERROR_MM = "branch_rms_error_mm"  # per branch: slider error, RMS [mm]
    BRANCH_REVERSAL_ERROR_MM = "branch_reversal_error_mm"  # per branch: largest slider error just after a reversal
    MOTOR_TORQUE_PEAK_NM = "motor_torque_peak_nm"  # per branch: largest motor torque [N m]
    BRANCH_FORCE_PEAK_N = "branch_force_peak_n"  # per branch: largest force along the rod [N]
    SYNC_ERROR_RHO = "sync_error_rho"  # the synchronous error of eq. 11 at the end [mm s]
    LOOP_CLOSURE_RESIDUAL_MAX_MM = "loop_closure_residual_max_mm"  # largest loop-closure residual of the model [mm]
    HIGHEST_BRANCH_FORCE_PEAK_N = "highest_branch_force_peak_n"  # the highest of the six branch force peaks [N]


@dataclasses.dataclass(frozen=True)
class HybridFigures:
    """What a hybrid run adds (eq. 14): the law's ``form`` and ``gains``, the feedforward force's peak [N] and the
    force-loop error ``F_rho``'s RMS and peak [N]."""

    form: str
    gains: dict[str, float]
    force_ff_peak_n: float
    f_rho_rms_n: float
    f_rho_peak_n: float

    def to_json(self) -> dict[str, Any]:
        """Plain data: the form, each gain by name, then the three forces."""
        return {"form": self.form, **self.gains} | {
            "force_ff_peak_n": self.force_ff_peak_n,
            "f_rho_rms_n": self.f_rho_rms_n,
            "f_rho_peak_n": self.f_rho_peak_n,
        }

    @classmethod
    def from_json(cls, d: dict[str, Any]) -> HybridFigures:
        """The record of :meth:`to_json`'s data."""
        forces = ("force_ff_peak_n", "f_rho_rms_n", "f_rho_peak_n")
        gains = {k: float(v) for k, v in d.items() if k != "form" and k not in forces}
        return cls(str(d["form"]), gains, *(float(d[k]) for k in forces))


@dataclasses.dataclass(frozen=True)
class MachineMetrics:
    """A machine run's metrics over a path of ``duration_s`` [s]: one field per :class:`Metric` (per-branch ones as six
    values, a branch whose reference never reverses without a reversal error; the highest force peak a property),
    and a hybrid run's figures."""

    duration_s: float
    rms_tracking_error_mm: float
    max_tracking_error_mm: float
    branch_rms_error_mm: list[float]
    branch_reversal_error_mm: list[float | None]
    motor_torque_peak_nm: list[float]
    branch_force_peak_n: list[float]
    sync_error_rho: float
    loop_closure_residual_max_mm: float
    hybrid: HybridFigures | None = None

    @property
    def highest_branch_force_peak_n(self) -> float:
        """The highest of the six branch force peaks [N]."""
        return max(self.branch_force_peak_n)

    def value(self, metric: Metric) -> Any:
        """The value of ``metric``: a float, or six per-branch values."""
        return getattr(self, metric.value)

    def to_json(self, highest_force: bool = False) -> dict[str, Any]:
        """Plain data (what ``pusupu sim --json`` prints): the duration, each :class:`Metric` but the derived highest
        force (unless ``highest_force``: last, as the reports have it), and the hybrid figures of a hybrid run."""
        d: dict[str, Any] = {"duration_s": self.duration_s}
        d |= {m.value: self.value(m) for m in Metric if m is not Metric.HIGHEST_BRANCH_FORCE_PEAK_N}
        if self.hybrid is not None:
            d["hybrid"] = self.hybrid.to_json()
        if highest_force:
            d[Metric.HIGHEST_BRANCH_FORCE_PEAK_N.value] = self.highest_branch_force_peak_n
        return d

    @classmethod
    def from_json(cls, d: dict[str, Any]) -> MachineMetrics:
        """The record of :meth:`to_json`'s data (the derived highest force, if there, is left out)."""
        fields = {m.value: d[m.value] for m in Metric if m is not Metric.HIGHEST_BRANCH_FORCE_PEAK_N}
        hybrid = HybridFigures.from_json(d["hybrid"]) if "hybrid" in d else None
        return cls(duration_s=d["duration_s"], **fields, hybrid=hybrid)


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
