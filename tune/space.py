"""What the tuner moves: parameter groups, the log parametrisation and the box bounds.

A group names fields of :class:`~pusupu_jax.params.ServoParams` or
:class:`~pusupu_jax.hybrid.HybridGains`.  Each tuned field is a log-value ``z``: one per
axis, or one shared by every axis when ``shared`` (servo fields only; the hybrid gains are
machine-wide scalars anyway).  ``exp(z)`` keeps every gain positive; after each optimiser
step ``z`` is projected onto the box ``[log lo, log hi]``.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import jax.numpy as jnp
import numpy as np

from pusupu_jax.hybrid import HybridGains
from pusupu_jax.params import ParameterError, ServoParams, arrays
from pusupu_jax.params import bounds as bounds_of

GROUPS = {
    "imc": ("lambda1", "lambda2", "T0"),
    "velocity": ("Kv", "Tv"),
    "current": ("Ki", "Ti"),
    "pid": ("Kp_pid", "Ki_pid", "Kd_pid", "Tf_pid"),
    "feedforward": ("Kff_pid",),
    "hybrid": ("m6", "c6", "g"),
}
HYBRID_FIELDS = GROUPS["hybrid"]


def field_bounds(name: str) -> tuple[float, float, str]:
    """``(low, high, why)`` of a tuned field: its documented range (:func:`pusupu_jax.params.bounds`)."""
    cls = HybridGains if name in HYBRID_FIELDS else ServoParams
    return bounds_of(next(f for f in dataclasses.fields(cls) if f.name == name))


@dataclass(frozen=True)
class Space:
    """The tuned fields around a start point: ``z`` is a dict of log-values (the optimiser's pytree)."""

    fields: tuple[str, ...]
    shared: bool
    servo0: ServoParams
    hybrid0: HybridGains
    lower: dict  # name -> lower bound (same shape as the value)
    upper: dict

    @classmethod
    def create(
        cls,
        groups,
        servo0: ServoParams,
        hybrid0: HybridGains,
        shared: bool = True,
        bounds: dict | None = None,
        span: float = 10.0,
    ) -> "Space":
        """Fields of ``groups``; default bounds ``start / span`` to ``start * span`` within the field's own
        (:func:`field_bounds`), overridden by ``bounds``, which must lie within the field's own too."""
        unknown = [g for g in groups if g not in GROUPS]
        if unknown or not groups:
            raise ParameterError(f"tune groups: expected some of {sorted(GROUPS)}, got {list(groups)}")
        fields = tuple(f for g in groups for f in GROUPS[g])
        space = cls(fields, shared, servo0, hybrid0, {}, {})
        start = space.values(space.z0())
        bounds = bounds or {}
        extra = sorted(set(bounds) - set(fields))
        if extra:
            raise ParameterError(f"tune bounds: {extra[0]!r} is not a tuned field; tuned: {list(fields)}")
        for f in fields:
            lo, hi = bounds.get(f, (None, None))
            v = np.asarray(start[f])
            low, high, why = field_bounds(f)
            if (lo is not None and lo < low) or (hi is not None and hi > high):
                raise ParameterError(
                    f"tune bounds.{f}: expected within the field's range {low:g} to {high:g} ({why}), got [{lo}, {hi}]"
                )
            space.lower[f] = np.full_like(v, np.maximum(v / span, low) if lo is None else lo, dtype=float)
            space.upper[f] = np.full_like(v, np.minimum(v * span, high) if hi is None else hi, dtype=float)
            if not ((0 < space.lower[f]) & (space.lower[f] <= v) & (v <= space.upper[f])).all():
                raise ParameterError(
                    f"tune bounds.{f}: expected 0 < lower <= start ({v.ravel()[0]:.6g}) <= upper, "
                    f"got [{space.lower[f].ravel()[0]:.6g}, {space.upper[f].ravel()[0]:.6g}]"
                )
        return space

    def _start(self, name):
        if name in HYBRID_FIELDS:
            return np.asarray(getattr(self.hybrid0, name), dtype=float)
        v = np.asarray(getattr(self.servo0, name), dtype=float)
        if self.shared:
            if not np.allclose(v, v[0]):
                raise ParameterError(f"tune: {name} differs between axes at the start; set shared: false")
            return np.asarray(v[0])
        return v

    def z0(self) -> dict:
        return {f: jnp.log(jnp.asarray(self._start(f))) for f in self.fields}

    def values(self, z) -> dict:
        return {f: jnp.exp(v) for f, v in z.items()}

    def json_values(self, z) -> dict:
        """:meth:`values` as JSON types (lists of floats): a report's ``start`` and ``result``."""
        return {f: np.asarray(v).tolist() for f, v in self.values(z).items()}

    def project(self, z) -> dict:
        return {f: jnp.clip(v, np.log(self.lower[f]), np.log(self.upper[f])) for f, v in z.items()}

    @property
    def start(self) -> tuple[ServoParams, HybridGains]:
        """The start point ``(servo0, hybrid0)``: every field the tuner leaves alone takes its value from it."""
        return self.servo0, self.hybrid0

    def apply(self, z, start: tuple[ServoParams, HybridGains] | None = None) -> tuple[ServoParams, HybridGains]:
        """The full parameter sets at ``z`` (traceable), the other fields from ``start`` (default :attr:`start`; the
        tuner's gradient takes it as an argument, so that one program serves every start point and machine)."""
        servo0, hybrid0 = self.start if start is None else start
        vals = self.values(z)
        servo = {f: jnp.broadcast_to(v, (6,)) for f, v in vals.items() if f not in HYBRID_FIELDS}
        hybrid = {f: v for f, v in vals.items() if f in HYBRID_FIELDS}
        return servo0.replace(**servo), hybrid0.replace(**hybrid)

    def host_values(self, z) -> tuple[ServoParams, HybridGains]:
        """:meth:`apply` as host values: numpy arrays in the servo parameters, floats in the hybrid gains."""
        servo, hybrid = self.apply(z)
        return (
            servo.replace(**{k: np.asarray(v) for k, v in arrays(servo).items()}),
            hybrid.replace(**{f: float(getattr(hybrid, f)) for f in HYBRID_FIELDS}),
        )
