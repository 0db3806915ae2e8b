"""Compliance in contact: an admittance outer loop on the platform, driven by the measured contact force.

Not in the paper (its Fig. 9 shows peg-in-hole and surface tracking as photographs, without
the law).  The law designed here sits outside every branch's cascade, at the position-loop
rate: the contact force ``F`` [N] that a wrist sensor measures on the tool (world axes)
moves an offset ``x_c`` [m] of the platform's position reference through a mass-damper-spring,
per world axis ``k`` selected by ``S_k = 1``::

    M_k x_c'' + D_k x_c' + K_k x_c = S_k (F_k - F_d,k)

``F_d`` is the contact force to hold, a profile along the path (the force on the tool, so
``+z`` presses the tool down onto a surface below it).  ``K_k = 0`` makes axis ``k`` a force
controller: it moves until ``F_k = F_d,k``.  ``S_k = 0`` keeps axis ``k`` in position control
(the selection of classic hybrid position/force control).  The references of the branches are
the nominal inverse kinematics of the path's pose plus ``x_c`` (orientation unchanged),
recomputed every position period.

Discretisation: semi-implicit (symplectic) Euler at the position period ``dt``, velocity
first; for the undamped part it is stable while ``dt sqrt(K/M) < 2``, and the damping term
needs ``dt D / M < 2`` (:func:`validate_gains` checks both, with margin).

The gains' sizes are physical: the contact is a stiff spring (MuJoCo's default soft contact on
this machine: about 6e5 N/m), so the force loop's time constant ``D / k_contact`` must stay
slower than the IMC's reference filter (Table 1: lambda1 = 18 ms), which puts ``D`` in the
1e4-1e5 N s/m range where the contact itself closes the loop (``docs/compliance.md`` has the
lateral axes of the peg, an exception).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from .params import ParameterError


@jax.tree_util.register_dataclass
@dataclass(frozen=True)
class AdmittanceGains:
    """The admittance of the platform's position, per world axis x, y, z (each ``(3,)``)."""

    mass: Any  # kg, M
    damping: Any  # N s/m, D
    stiffness: Any  # N/m, K (0: force control on that axis)
    selection: Any = (1.0, 1.0, 1.0)  # 1: the axis yields to the contact force; 0: it stays in position control
    max_offset: Any = 0.02  # m, |x_c| is clamped to this on every axis

    def replace(self, **changes: Any) -> "AdmittanceGains":
        return dataclasses.replace(self, **changes)


@jax.tree_util.register_dataclass
@dataclass(frozen=True)
class ComplianceReference:
    """What a compliant position period reads each sample: ``(N, ...)`` arrays scanned over time."""

    pose: Any  # (N, 5) platform poses of the path (x, y, z [m], a, b [rad])
    force_setpoint: Any  # (N, 3) N, F_d: the contact force on the tool to hold (world axes)
    inner: Any  # the cascade's own reference (motor angles, or a HybridReference); its angles are recomputed


class AdmittanceState(NamedTuple):
    offset: Any  # (3,) m, x_c
    rate: Any  # (3,) m/s, x_c'


def validate_gains(gains: AdmittanceGains, dt: float) -> None:
    """One-line ParameterError unless the gains are finite, M and D positive, K non-negative, and the
    discretisation at ``dt`` [s] stable with a factor-2 margin."""
    for name in ("mass", "damping", "stiffness", "selection", "max_offset"):
        v = np.asarray(getattr(gains, name), dtype=float)
        if v.shape not in ((), (3,)) or not np.isfinite(v).all():
            raise ParameterError(f"admittance.{name}: expected one finite number or three (x, y, z), got {v.tolist()}")
    if (np.asarray(gains.max_offset) <= 0).any():
        raise ParameterError(f"admittance.max_offset: expected a positive offset [m], got {gains.max_offset!r}")
    m, d, k = (
        np.broadcast_to(np.asarray(getattr(gains, n), dtype=float), (3,)) for n in ("mass", "damping", "stiffness")
    )
    if (m <= 0).any() or (d <= 0).any() or (k < 0).any():
        raise ParameterError(
            f"admittance: expected mass > 0, damping > 0 and stiffness >= 0 [kg, N s/m, N/m], "
            f"got {m.tolist()}, {d.tolist()}, {k.tolist()}"
        )
    if (dt * np.sqrt(k / m) >= 1.0).any() or (dt * d / m >= 1.0).any():
        raise ParameterError(
            f"admittance: the discretisation at dt = {dt} s needs dt sqrt(K/M) < 1 and dt D/M < 1 "
            f"(a factor 2 inside stability); got {np.round(dt * np.sqrt(k / m), 3).tolist()} and "
            f"{np.round(dt * d / m, 3).tolist()}"
        )


def init() -> AdmittanceState:
    """The admittance at rest: no offset [m], no rate [m/s]."""
    return AdmittanceState(jnp.zeros(3), jnp.zeros(3))


def step(
    gains: AdmittanceGains, state: AdmittanceState, force: jax.Array, force_setpoint: jax.Array, dt: float
) -> AdmittanceState:
    """One position period of the admittance (semi-implicit Euler) for the measured contact force ``force`` and
    the setpoint ``force_setpoint`` [N] (world axes): the new offset [m] and its rate [m/s]."""
    acceleration = (
        jnp.asarray(gains.selection) * (force - force_setpoint)
        - gains.damping * state.rate
        - gains.stiffness * state.offset
    ) / gains.mass
    rate = state.rate + dt * acceleration
    offset = jnp.clip(state.offset + dt * rate, -gains.max_offset, gains.max_offset)
    rate = jnp.where(jnp.abs(offset) >= gains.max_offset, 0.0, rate)  # no wind-up against the clamp
    return AdmittanceState(offset, rate)
