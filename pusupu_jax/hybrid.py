"""Force/position hybrid control with cross-coupling synchronous error compensation (paper eq. 10-14).

Branches 1-5 are position-controlled (2-DOF IMC); branch 6, the redundant one
(:data:`FORCE_AXIS`), is force-controlled: its drive's current reference is set from

    F_6 = F_q + F_rho                                   (eq. 13)
    F_rho = m6 rho'' + c6 rho' + g rho                  (eq. 14)

``F_q`` [N] is branch 6's share of the nominal inverse dynamics under the minimum-norm
distribution (:mod:`pusupu_jax.plant.dynamics`), precomputed along the reference path.
The branch errors are the paper's ``e_i = s_i - s'_i`` (reference minus actual slider
position [m], eq. 10), sampled at the position-loop rate.  Two forms of ``rho``:

* ``'rms'`` (the paper's): ``rho' = sqrt(mean_i xi_i^2)`` over the 10 pairwise differences
  ``xi = e_n - e_m`` of branches 1-5 (eq. 11).  Eq. 12 prints the square root over a
  plain sum, which would be imaginary for negative sums; it is read as this RMS.  This
  ``rho`` never decreases, so ``F_rho`` only ever pushes branch 6 one way (towards
  positive travel), whatever the sign of the errors.
* ``'signed'``: ``rho' = w . e_15`` with ``w = J_6 J_15^-1`` (:func:`~pusupu_jax.plant.dynamics.coupling_row`):
  the errors of branches 1-5 converted to the travel they imply for branch 6, positive
  when the platform lags so that branch 6 should push forward.  ``F_rho`` is then a PID
  force law on that coupling error, pushing either way.

In both forms ``rho`` is the time integral of ``rho'`` (rectangle rule) and ``rho''`` the
backward difference of ``rho'`` over one position period.  Eq. 14 names ``m6, c6, g`` a
mass, a Coriolis coefficient and a gravitational acceleration; dimensionally (``rho`` in
m s) they are three gains, tuned like any other: ``m6`` [N s/m] on ``rho''`` [m/s],
``c6`` [N/m] on ``rho'`` [m] and ``g`` [N/(m s)] on ``rho`` [m s].
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, Mapping, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from . import inputs
from .metrics import safe_sqrt
from .params import ParameterError

if TYPE_CHECKING:
    from jax.typing import ArrayLike

FORCE_AXIS = 5  # branch 6, zero-based
RHO_FORMS = ("rms", "signed")


# The force law has no single-axis loop whose poles could bound its gains: they are bounded by what the machine
# measured.  `pusupu experiment hybrid_grid` sweeps each gain alone (the others at their defaults) on the MJX machine
# in hybrid mode, p2p, seed 3 of the kinematic errors, at lambda2 = 0.15 s and at the smallest admissible lambda2
# (0.027 s): every run stayed within 1 mm and 93 N up to m6 = 1.4e5, c6 = 3e6 and g = 1e6; the first values that
# diverged (branch forces of kN, errors of mm) were m6 = 2.1e5, c6 = 5e6 and g = 1e7.  The bounds keep a factor of
# 2 to 3 below the largest stable value.
HYBRID_BOUNDS_WHY = (
    "the largest value kept at least a factor 2 below the smallest that diverged on the machine "
    "(pusupu experiment hybrid_grid, its gain sweep)"
)


def _gain(default: float, unit: str, doc: str, high: float) -> float:
    return field(default=default, metadata={"unit": unit, "doc": doc, "bounds": (0.0, high, HYBRID_BOUNDS_WHY)})


@jax.tree_util.register_dataclass
@dataclass(frozen=True)
class HybridGains:
    """Gains of eq. 14 (scalars, or arrays with a leading batch dimension) and the static form of ``rho``."""

    m6: Any = _gain(
        7.0e3,
        "N*s/m",
        "gain on rho'' (the paper's 'mass' of branch 6); in the signed form rho'' is "
        "branch 6's velocity error implied by branches 1-5, so m6 damps branch 6: default Kv Kt eta / r^2 "
        "of Table 1 (7.05e3), the proportional action of its own velocity loop (docs/hybrid.md)",
        7.0e4,
    )
    c6: Any = _gain(1.0e3, "N/m", "gain on rho' (the paper's 'Coriolis coefficient')", 1.0e6)
    g: Any = _gain(1.0e2, "N/(m*s)", "gain on rho (the paper's 'gravitational acceleration')", 3.0e5)
    form: str = field(default="signed", metadata=dict(static=True))

    @classmethod
    def from_mapping(cls, values: Mapping[str, Any], base: "HybridGains | None" = None) -> "HybridGains":
        """``base`` (default gains) with ``values`` replaced; validates (one number per gain, machine-wide)."""
        inputs.check_keys(values, "HybridGains", [f.name for f in dataclasses.fields(cls)], ParameterError)
        changes: dict[str, Any] = {
            k: v if k == "form" else inputs.number(v, f"HybridGains.{k}", ParameterError, finite=False)
            for k, v in values.items()
        }
        out = dataclasses.replace(base or cls(), **changes)
        validate_gains(out)
        return out

    def replace(self, **changes: Any) -> "HybridGains":
        return dataclasses.replace(self, **changes)


def gain_fields() -> list[dataclasses.Field[Any]]:
    """The numeric (traced) fields of :class:`HybridGains`."""
    return [f for f in dataclasses.fields(HybridGains) if not f.metadata.get("static")]


def validate_gains(h: HybridGains, bounded: bool = True) -> None:
    """Raise :class:`ParameterError` unless every gain lies within its bounds and the form is known.

    ``bounded=False``: finite and non-negative only, for a simulation that explores beyond what a gain file may hold
    (:func:`pusupu_jax.machine.simulate_scenarios`; the bounds are measured by such runs)."""
    if h.form not in RHO_FORMS:
        raise ParameterError(f"HybridGains.form: expected one of {RHO_FORMS}, got {h.form!r}")
    for f in gain_fields():
        try:
            v = np.asarray(getattr(h, f.name), dtype=float)
        except (TypeError, ValueError):
            raise ParameterError(
                f"HybridGains.{f.name}: expected a number [{f.metadata['unit']}], got {getattr(h, f.name)!r}"
            ) from None
        low, high, why = f.metadata["bounds"] if bounded else (0.0, np.inf, "finite and non-negative")
        bad = ~(np.isfinite(v) & (v >= low) & (v <= high))
        if bad.any():
            raise ParameterError(
                f"HybridGains.{f.name}: expected a number from {low:g} to {high:g} "
                f"[{f.metadata['unit']}] ({why}), got {v[bad].ravel()[0]:.6g}"
            )


@jax.tree_util.register_dataclass
@dataclass(frozen=True)
class HybridReference:
    """What the hybrid position period reads each sample: ``(N, ...)`` arrays scanned over time."""

    theta: Any  # (N, 6) motor-angle references, rad
    force_ff: Any  # (N,) F_q, the inverse-dynamics force of branch 6, N
    coupling: Any  # (N, 5) w = J_6 J_15^-1 at the reference pose, 1


def rms_rate(e: jax.Array) -> jax.Array:
    """``rho'`` of eq. 12 read as RMS: ``sqrt(mean xi^2)`` of the 10 pairwise differences of ``e[..., :5]`` [m]."""
    n, m = np.triu_indices(5, k=1)
    xi = e[..., n] - e[..., m]
    return safe_sqrt(jnp.mean(xi**2, axis=-1))  # every branch error equal: rho' = 0, derivative 0


def synchronous_error(branch_errors: jax.Array, dt: float) -> jax.Array:
    """Eq. 10-12: ``rho(t)`` [m s], shape ``(..., N)``, from branch errors ``(..., N, 6)`` [m] every ``dt`` [s]."""
    return jnp.cumsum(rms_rate(branch_errors), axis=-1) * dt


class ForceState(NamedTuple):
    """State of the force law."""

    rho: Any  # m s: the synchronous error, integral of rho'
    rate: Any  # m: the previous rho'
    force: Any  # N: the last F_6


def init(force: ArrayLike = 0.0) -> ForceState:
    """The force law at rest, its last ``F_6`` at ``force`` [N]."""
    return ForceState(jnp.zeros(()), jnp.zeros(()), jnp.zeros(()) + force)


def step(
    gains: HybridGains, state: ForceState, e: jax.Array, coupling: ArrayLike, force_ff: ArrayLike, dt: float
) -> tuple[ForceState, jax.Array]:
    """One position period (eq. 13-14): branch errors ``e`` (6,) [m] -> ``(state, F_6 [N])``.

    ``coupling`` (5,): the row ``w`` of the signed form [1]; ``force_ff``: ``F_q`` [N]; ``dt``: the period [s].
    """
    rate = rms_rate(e) if gains.form == "rms" else jnp.dot(coupling, e[..., :5])
    rho = state.rho + rate * dt
    force = force_ff + gains.m6 * (rate - state.rate) / dt + gains.c6 * rate + gains.g * rho
    return ForceState(rho, rate, force), force
