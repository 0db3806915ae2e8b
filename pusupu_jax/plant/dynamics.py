"""Inverse dynamics of the nominal machine along a platform path, distributed over the six branches (host-side).

For a path of poses ``q(t)`` the whole mechanism moves consistently: ``qpos = Phi(q)``
(:func:`~pusupu_jax.plant.model.pose_to_qpos`), ``qvel = T q'`` with ``T = dPhi/dq``
(``nv x 5``).  MuJoCo's equation of motion ``M qacc + c = B F + Jc^T lambda`` (``B``
puts the slider forces ``F`` [N] on the slide joints, ``lambda`` are the spherical-joint
constraint forces) projected on the consistent motions, where ``Jc T = 0`` removes the
constraint forces, gives the five equations

    J^T F = Q,   Q = T^T (M qacc + c),   J = ds/dq (6 x 5, the rows of T at the slides).

Six forces for five equations: the redundancy.  The minimum-norm solution
``F = J (J^T J)^-1 Q`` is the distribution with the smallest sum of squared branch forces
(it has no component in the null space of ``J^T``, the internal force that only squeezes
the mechanism).  Its sixth component is the paper's ``F_q``, "the optimized inverse
redundant torque" of eq. 13, here a slider force [N].

``M qacc + c`` is MuJoCo's recursive Newton-Euler (``mj_rne``, gravity and Coriolis
included; it needs the bodies' positions, inertias and velocities, ``mj_kinematics``,
``mj_comPos`` and ``mj_comVel``, not the constraint solve of a whole ``mj_forward``) plus the rotor armature ``eta J /
r^2`` on the slides; ``qvel`` and ``qacc`` are
central differences of ``qpos`` along the sampled path (second-order accurate, the path
being smooth).  The nominal geometry is used: the controller does not know the seeded
kinematic errors of the real machine.
"""

from __future__ import annotations

import dataclasses
from typing import TYPE_CHECKING, Callable

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import numpy.typing as npt

from ..programs import Program, describe
from .axis import screw_ratio
from .geometry import Geometry
from .model import ModelOptions, build_model, pose_to_qpos, slide_dofs, slide_qpos

if TYPE_CHECKING:
    from ..params import ServoParams


# the compiled pose Jacobians of this process, by machine and precision (float64 on or off): see pose_jacobian
_POSE_JACOBIANS: dict[tuple[str, bool], Program] = {}
MIN_ROWS = 64  # the shortest padded length of pose_jacobian's program


def padded_rows(n: int) -> int:
    """The length that ``n`` poses are padded to for :func:`pose_jacobian`'s program: the next power of two, at
    least :data:`MIN_ROWS`, so that the paths of one octave of lengths share one compiled program (at most twice the
    rows computed)."""
    return max(MIN_ROWS, 1 << (n - 1).bit_length())


def pose_jacobian(
    geom: Geometry, options: ModelOptions = ModelOptions()
) -> Callable[[npt.ArrayLike], tuple[np.ndarray, np.ndarray]]:
    """``q (N, 5) -> (qpos (N, nq), T = dqpos/dq (N, nq, 5))`` of the nominal machine ``geom`` (seeded errors left
    out), as numpy arrays.

    Every command that builds a reference or reads a machine file asks it, for each path and for the linear model's
    load.  Its program is kept on disk (:class:`~pusupu_jax.programs.Program`), so that a later process loads it
    instead of tracing it, and in this process per machine and precision: the bridge reads its gain file (which asks
    this) before it turns float64 on, and a program of single precision must not serve it after that switch.  The
    poses are padded (the last one repeated) to :func:`padded_rows`: one program per octave of path lengths, not one
    per length."""
    options = dataclasses.replace(options, kin_error_seed=None)
    key = (describe((geom, options)), bool(jax.config.jax_enable_x64))  # type: ignore[attr-defined]  # JAX's flag
    program = _POSE_JACOBIANS.get(key)
    if program is None:
        phi = pose_to_qpos(build_model(geom, options), geom)
        program = _POSE_JACOBIANS[key] = Program(
            lambda q: (phi(q), jnp.vectorize(jax.jacfwd(phi), signature="(5)->(n,5)")(q)), key[0]
        )

    def run(q: npt.ArrayLike) -> tuple[np.ndarray, np.ndarray]:
        q = np.asarray(q)
        n = len(q)
        padded = np.concatenate([q, np.repeat(q[-1:], padded_rows(n) - n, axis=0)])
        qpos, T = program(jnp.asarray(padded))
        return np.asarray(qpos)[:n], np.asarray(T)[:n]

    return run


def nominal_model(servo: ServoParams, geom: Geometry, options: ModelOptions) -> mujoco.MjModel:
    """The model without kinematic errors, with the rotor armature of ``servo`` on the slides."""
    m = build_model(geom, dataclasses.replace(options, kin_error_seed=None))
    r = np.asarray(screw_ratio(servo))
    m.dof_armature[slide_dofs(m)] = np.asarray(servo.eta) * np.asarray(servo.J) / r**2
    return m


def inverse_dynamics_forces(
    servo: ServoParams,
    path: npt.ArrayLike,
    dt: float,
    geom: Geometry | None = None,
    options: ModelOptions = ModelOptions(),
) -> tuple[np.ndarray, np.ndarray]:
    """Minimum-norm slider forces along ``path`` and the actuation Jacobians.

    ``path``: poses ``(N, 5)`` sampled every ``dt`` [s] (at least 3 samples).  Returns
    ``(F, J)``: forces ``(N, 6)`` [N] with ``J^T F = Q`` at every sample, and ``J = ds/dq``
    ``(N, 6, 5)`` of the nominal geometry.
    """
    geom = Geometry.default() if geom is None else geom
    path = np.asarray(path, dtype=float)
    if path.ndim != 2 or path.shape[1] != 5 or len(path) < 3:
        raise ValueError(f"path: expected poses of shape (N >= 3, 5), got {path.shape}")
    m = nominal_model(servo, geom, options)
    qpos, T = pose_jacobian(geom, options)(path)
    qvel = np.gradient(qpos, dt, axis=0)
    qacc = np.gradient(qvel, dt, axis=0)
    d = mujoco.MjData(m)
    tau = np.zeros((len(path), m.nv))
    for k in range(len(path)):
        d.qpos[:], d.qvel[:] = qpos[k], qvel[k]
        mujoco.mj_kinematics(m, d)
        mujoco.mj_comPos(m, d)
        mujoco.mj_comVel(m, d)
        d.qacc[:] = qacc[k]
        mujoco.mj_rne(m, d, 1, tau[k])
    tau += m.dof_armature * qacc
    Q = np.einsum("nij,ni->nj", T, tau)
    J = T[:, slide_qpos(m), :]
    F = np.einsum("nij,nj->ni", J, np.linalg.solve(np.einsum("nki,nkj->nij", J, J), Q[..., None])[..., 0])
    return F, J


def coupling_row(J: npt.ArrayLike) -> np.ndarray:
    """``w = J_6 J_15^-1``, shape ``(..., 5)``: when branches 1-5 move by ``ds_15``, branch 6 moves by ``w . ds_15``."""
    J = np.asarray(J)
    return np.linalg.solve(np.swapaxes(J[..., :5, :], -1, -2), J[..., 5, :][..., None])[..., 0]


def pose_inertia(
    geom: Geometry, poses: npt.ArrayLike, options: ModelOptions = ModelOptions()
) -> tuple[np.ndarray, np.ndarray]:
    """The mechanism linearised at each of ``poses`` ``(N, 5)``: its inertia in the platform's five coordinates,
    ``M_q = T^T M T`` ``(N, 5, 5)`` [kg, kg m, kg m^2], and the actuation Jacobian ``J = ds/dq`` ``(N, 6, 5)``.

    ``M`` is MuJoCo's joint-space inertia of the whole mechanism (rotors left out; the payload of ``options`` in,
    seeded errors not) and ``T = dPhi/dq`` maps the platform's rates to every joint's (the consistent motions), so
    ``q'^T M_q q' / 2`` is the mechanism's kinetic energy.
    """
    poses = np.atleast_2d(np.asarray(poses, dtype=float))
    options = dataclasses.replace(options, kin_error_seed=None)
    m = build_model(geom, options)
    qpos, T = pose_jacobian(geom, options)(poses)
    d = mujoco.MjData(m)
    M = np.zeros((m.nv, m.nv))
    inertia = np.zeros((len(poses), 5, 5))
    for k in range(len(poses)):
        d.qpos[:] = qpos[k]
        mujoco.mj_forward(m, d)
        mujoco.mj_fullM(m, d, M)
        inertia[k] = T[k].T @ M @ T[k]
    return inertia, T[:, slide_qpos(m), :]


def reflected_mass(geom: Geometry, poses: npt.ArrayLike, options: ModelOptions = ModelOptions()) -> np.ndarray:
    """The mechanism's mass [kg] each slider carries at each of ``poses`` ``(N, 5)``: the diagonal of the
    actuator-space inertia ``J+^T M_q J+``, ``(N, 6)``.

    ``M_q`` and ``J`` are :func:`pose_inertia`'s, and ``J+`` the pseudo-inverse of ``J``: the slider forces of
    the minimum-norm distribution (as :func:`inverse_dynamics_forces`) that accelerate the platform as
    slider accelerations ``s''`` ask are ``J+^T M_q J+ s''``, so its diagonal is the mass one axis's loop sees
    when the others hold their share.  The payload of ``options`` is included; seeded errors are not.
    """
    inertia, J = pose_inertia(geom, poses, options)
    pinv = np.linalg.pinv(J)  # (N, 5, 6)
    out: np.ndarray = np.einsum("nii->ni", np.swapaxes(pinv, -1, -2) @ inertia @ pinv)
    return out
