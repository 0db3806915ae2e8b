"""The coupled linear model: the six axes' cascades on one mechanism linearised at a pose (JAX, float64).

The single-axis model (:mod:`pusupu_jax.analysis`, :func:`pusupu_jax.margins.loop_gains`) sees each axis as a motor
driving a lumped mass.  The machine's six sliders drive one 5-DOF platform: a branch moves only as the others do,
through the mechanism's inertia and against their closed loops.  Here the mechanism linearised at a pose
(:func:`pusupu_jax.plant.dynamics.pose_inertia`: its inertia ``M_q`` in the platform's five coordinates and the
actuation Jacobian ``J = ds/dq``) takes the lumped masses' place.  With ``r = lead / 2 pi`` [m/rad] per axis, the motor
angles are ``theta = R^-1 J q`` (``R = diag(r)``) and the motor torques push the sliders with ``F = eta R^-1 tau``, the
rotors adding ``A = diag(eta J_rotor / r^2)`` [kg] and the drive train's viscous friction ``B = diag(viscous)``
[N s/m] on each slider::

    (M_q + J^T A J) q'' + J^T B J q' = J^T eta R^-1 Kt i

so the motor speeds answer the six currents through the 6 x 6 frequency response::

    w = G(s) i,   G(s) = R^-1 J (s (M_q + J^T A J) + J^T B J)^-1 J^T eta R^-1 Kt

For one axis on a lumped mass ``m`` (``J = 1``) this is ``Kt / ((J_rotor + m r^2 / eta) s + viscous r^2 / eta)``, the
single-axis model's motion block.  Left out, as there: gravity's stiffness (the change of the gravity load with the
pose), Coulomb friction, and the sampling of the loops.

Every axis runs the blocks of :func:`pusupu_jax.margins.axis_blocks`, continuous.  Axis ``k``'s loop is broken at its
controller's output, with every loop of the other five axes closed around zero references:

* ``current``: at the current controller's output, axis ``k``'s velocity loop open;
* ``velocity``: at the current reference, axis ``k``'s position loop open (the single-axis loop of ``pusupu
  analyze``);
* ``velocity_in_position``: the same with axis ``k``'s position loop closed, as the running machine is measured
  (``pusupu experiment loop_match``);
* ``position``: at the velocity reference.

With the blocks as diagonal matrices, a closed axis obeys ``Z i = -(Q K + E) w``: ``Z = L s + R + Ginv Gi Gcf`` (the
armature and its current loop), ``Q = Ginv Gi Gxi``, ``K = Gv (Gxv C / s + Gw)`` (the velocity and position loops
seen from the current reference), ``E`` the back-EMF.  The broken axis's row takes its own form and the injection
``x``: ``(D + P G) i = e_k b x``, solved per frequency as the 5 x 5 impedance of the platform's rates (the six
currents' system has the five coordinates' rank in its mechanical part), and ``L = -y / x`` from the controller's
output ``y``.  ``tests/test_coupled.py`` checks it against python-control's interconnection of the same blocks, and
against the single-axis model on a mechanism whose axes do not couple.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import numpy.typing as npt
from jax.typing import ArrayLike

from .margins import W_GRID, axis_blocks, margins
from .params import N_AXES, ServoParams, arrays
from .plant.axis import screw_ratio
from .plant.dynamics import pose_inertia
from .plant.geometry import Geometry
from .plant.model import ModelOptions

LOOPS = ("current", "velocity", "velocity_in_position", "position")


@dataclasses.dataclass(frozen=True)
class Mechanism:
    """The mechanism linearised at one pose: ``inertia`` ``M_q`` ``(5, 5)`` [kg, kg m, kg m^2] in the platform's
    five coordinates (rotors left out) and ``jacobian`` ``J = ds/dq`` ``(6, 5)``."""

    inertia: np.ndarray
    jacobian: np.ndarray

    @classmethod
    def at(cls, geom: Geometry, pose: npt.ArrayLike, options: ModelOptions = ModelOptions()) -> "Mechanism":
        """The nominal machine ``geom`` (payload of ``options``) at the platform pose ``pose`` ``(5,)``."""
        inertia, jacobian = pose_inertia(geom, np.asarray(pose, dtype=float)[None], options)
        return cls(inertia[0], jacobian[0])


def loop_gains(servo: ServoParams, mech: Mechanism, w: ArrayLike, mode: str = "imc") -> dict[str, jax.Array]:
    """``L(jw)`` of every loop (:data:`LOOPS`) of every axis, each broken in turn: ``(6, len(w))``, or, for ``w`` of
    shape ``(..., 6, n)``, axis ``k``'s loop at its own row ``w[..., k, :]`` of frequencies (as
    :func:`pusupu_jax.margins.margins` refines each axis's crossings)."""
    w = jnp.asarray(w, dtype=float)
    if w.ndim >= 2:
        flat = loop_gains(servo, mech, w.reshape(-1), mode)
        # (broken axis, ..., axis, n): the broken axis's own row
        return {
            k: jnp.moveaxis(jnp.diagonal(v.reshape((N_AXES,) + w.shape), 0, 0, w.ndim - 1), -1, -2)
            for k, v in flat.items()
        }
    p = {k: jnp.asarray(v) for k, v in arrays(servo).items()}
    r = jnp.asarray(screw_ratio(servo))
    J = jnp.asarray(mech.jacobian)
    push = p["eta"] * p["Kt"] / r  # N/A: slider force per motor current
    inertia = jnp.asarray(mech.inertia) + J.T @ (J * (p["eta"] * p["J"] / r**2)[:, None])
    damping = J.T @ (J * p["viscous"][:, None])
    s = 1j * w
    S = s[:, None]
    b = {k: v.T for k, v in axis_blocks(servo, s, mode).items()}  # (len(w), 6)
    k_velocity = b["Gv"] * b["Gw"]
    k_closed = b["Gv"] * (b["Gxv"] * b["C"] / S + b["Gw"])
    q = b["inverter"] * b["Gi"] * b["Gxi"]
    z = b["armature"] + b["inverter"] * b["Gi"] * b["Gcf"]
    p_closed = q * k_closed + b["emf"]
    own = jnp.eye(N_AXES, dtype=bool)[:, None, :]  # (broken axis, 1, axis)
    axes = jnp.arange(N_AXES)

    def response(d_own: jax.Array, p_own: jax.Array, source: jax.Array) -> tuple[jax.Array, jax.Array]:
        """The broken axis's current and speed per unit injection ``(6, len(w))``, from its own ``D``, ``P`` and
        ``b`` (each ``(len(w), 6)``: the value it takes when that axis is the broken one).

        Each axis's current ``i = (b x - P w) / D`` pushes its slider with ``push i``, so the platform's rates solve
        the 5 x 5 impedance ``(s M + J^T B J + J^T diag(push P / (r D)) J) q' = J^T push b x / D`` (the six
        currents' 6 x 6 system has the rank of the five coordinates in its mechanical part, and loses digits)."""
        d = jnp.where(own, d_own[None], z[None])
        feedback = jnp.where(own, p_own[None], p_closed[None]) * push / (r * d)
        impedance = S[None, :, :, None] * inertia + damping + jnp.einsum("ji,kwj,jl->kwil", J, feedback, J)
        force = jnp.where(own, (source * push / d_own)[None], 0.0)
        rates = jnp.linalg.solve(impedance, jnp.einsum("ji,kwj->kwi", J, force)[..., None])[..., 0]
        speed = jnp.einsum("ji,kwi->kwj", J, rates)[axes, :, axes] / r[:, None]
        return (source.T - p_own.T * speed) / d_own.T, speed

    i_current, _ = response(b["armature"], b["emf"], b["inverter"])
    _, w_velocity = response(z, b["emf"], q)
    _, w_position = response(z, q * k_velocity + b["emf"], q * b["Gv"] * b["Gxv"])
    return {
        "current": (b["Gi"] * b["Gcf"]).T * i_current,
        "velocity": k_velocity.T * w_velocity,
        "velocity_in_position": k_closed.T * w_velocity,
        "position": b["C"].T * w_position / S.T,
    }


def loop_margins(servo: ServoParams, mech: Mechanism, mode: str = "imc") -> dict[str, dict[str, jax.Array]]:
    """:func:`pusupu_jax.margins.margins` of every loop of every axis of the coupled model: ``{loop:
    {phase_margin_deg, gain_margin_db, crossover_rad_s}}``, each ``(6,)``.

    The phase margin is read within (-180, 180] deg: the single-axis margins anchor the phase at the grid's lowest
    frequency where a loop's integrators put it, but a coupled loop need not start there (the other axes' position
    loops hold the platform, so at low frequency the broken axis pushes against a spring).  The anchor's error is a
    whole turn common to every crossing of a loop, so the smallest margin is still found at the right crossing; a
    margin below -180 deg would read as its value plus 360 deg (stability is read from poles, not from margins)."""

    # w: the grid (n,), or points per loop (4, 6, k): every loop from one evaluation of loop_gains
    def stack(w: ArrayLike) -> jax.Array:
        gains = loop_gains(servo, mech, w, mode)
        return jnp.stack([gains[name] if jnp.ndim(w) == 1 else gains[name][i] for i, name in enumerate(LOOPS)])

    stacked = margins(stack, W_GRID)
    pm = stacked["phase_margin_deg"]
    stacked["phase_margin_deg"] = jnp.where(jnp.isfinite(pm), 180.0 - jnp.mod(180.0 - pm, 360.0), pm)
    return {name: {k: v[i] for k, v in stacked.items()} for i, name in enumerate(LOOPS)}
