"""Kinematics of the 6PUS-UPU manipulator in JAX: the 5-DOF pose, inverse and forward kinematics, Jacobians.

Pose ``q = (x, y, z, a, b)``: the platform centre ``p = (x, y, z)`` [m] (the UPU
branch's top universal joint) and the platform normal ``n = Rx(a) Ry(b) e_z`` (two
tilts [rad]).  The passive UPU branch fixes the rest of the orientation: its base
universal joint turns the leg by ``Rx(phi1) Ry(phi2)`` so that the leg points at ``p``
(``phi1 = atan2(-y, z)``, ``phi2 = asin(x / |p|)``) and its top universal joint adds
``Ry(alpha) Rx(beta)``, so that

    R = Rx(phi1) Ry(gamma) Rx(beta),   gamma = phi2 + alpha.

Given ``n``, ``m = Rx(-phi1) n = (cos(beta) sin(gamma), -sin(beta), cos(beta) cos(gamma))``
gives ``beta = -asin(m_y)``, ``gamma = atan2(m_x, m_z)`` in closed form.  With ``a = b = 0``
the platform is level and unturned (``R = I``).  The leg must stay above the base
(``z > 0``) and away from ``|m_y| = 1``.

Inverse kinematics (closed form): the spherical joint ``P_i = p + R c_i`` and the slider
``b_i + s_i u_i`` are a rod length apart, ``|b_i + s_i u_i - P_i| = l_i``, so
``s_i = u_i.d_i - sqrt((u_i.d_i)^2 - |d_i|^2 + l_i^2)`` with ``d_i = P_i - b_i`` (the
slider below the joint it carries, as in the default geometry).

Forward kinematics: Gauss-Newton on the six branch equations for the five pose
coordinates, a fixed number of iterations (a ``lax.scan``, so it is differentiable).
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any, Callable, cast

import jax
import jax.numpy as jnp
import numpy as np
import numpy.typing as npt

from .geometry import Geometry, GeometryError

if TYPE_CHECKING:
    from jax.typing import ArrayLike


def rot_x(t: ArrayLike) -> jax.Array:
    c, s = jnp.cos(t), jnp.sin(t)
    z, o = jnp.zeros_like(t), jnp.ones_like(t)
    return jnp.stack([jnp.stack([o, z, z], -1), jnp.stack([z, c, -s], -1), jnp.stack([z, s, c], -1)], -2)


def rot_y(t: ArrayLike) -> jax.Array:
    c, s = jnp.cos(t), jnp.sin(t)
    z, o = jnp.zeros_like(t), jnp.ones_like(t)
    return jnp.stack([jnp.stack([c, z, s], -1), jnp.stack([z, o, z], -1), jnp.stack([-s, z, c], -1)], -2)


def xy_hinge_angles(direction: ArrayLike) -> tuple[jax.Array, jax.Array]:
    """Angles of a hinge about x then a hinge about y that turn the z axis onto ``direction`` (any length)."""
    direction = jnp.asarray(direction)
    length = jnp.linalg.norm(direction, axis=-1)
    return jnp.arctan2(-direction[..., 1], direction[..., 2]), jnp.arcsin(direction[..., 0] / length)


def upu_angles(
    q: jax.Array | npt.NDArray[np.float64],
) -> tuple[jax.Array, jax.Array, jax.Array, jax.Array, jax.Array]:
    """Joint coordinates of the UPU branch for pose ``q``: (phi1, phi2, leg length [m], alpha, beta)."""
    p = q[..., :3]
    length = jnp.linalg.norm(p, axis=-1)
    phi1, phi2 = xy_hinge_angles(p)
    n = jnp.einsum("...ij,...j->...i", rot_x(q[..., 3]) @ rot_y(q[..., 4]), jnp.array([0.0, 0.0, 1.0]))
    m = jnp.einsum("...ij,...j->...i", rot_x(-phi1), n)
    beta = -jnp.arcsin(m[..., 1])
    gamma = jnp.arctan2(m[..., 0], m[..., 2])
    return phi1, phi2, length, gamma - phi2, beta


def platform_rotation(q: jax.Array | npt.NDArray[np.float64]) -> jax.Array:
    """Platform orientation ``R`` (3x3) imposed by the UPU branch for pose ``q``."""
    phi1, phi2, _, alpha, beta = upu_angles(q)
    return rot_x(phi1) @ rot_y(phi2 + alpha) @ rot_x(beta)


def joint_points(geom: Geometry, q: jax.Array | npt.NDArray[np.float64]) -> jax.Array:
    """Spherical-joint centres ``P_i`` in the base frame, shape ``(..., 6, 3)`` [m]."""
    R = platform_rotation(q)
    # a JAX array: with a numpy ``q``, numpy's ``+`` defers to the JAX array (numpy's stubs say ndarray)
    return cast(jax.Array, q[..., None, :3] + jnp.einsum("...ij,kj->...ki", R, jnp.asarray(geom.platform_points)))


# The functions that host-side code calls on whole paths (the path checks, the references) are jitted: run op by
# op, each of their operations compiled alone on a cold cache (227 compiles: the default tune's problem build took
# 15.5 s, now 10.4 s).  Inside a traced function a jit is inlined.
@jax.jit
def _branch_terms(geom: Geometry, q: jax.Array) -> tuple[jax.Array, jax.Array]:
    d = joint_points(geom, q) - jnp.asarray(geom.rail_points)
    ud = jnp.sum(d * jnp.asarray(geom.rail_dirs), axis=-1)
    disc = ud**2 - jnp.sum(d**2, axis=-1) + jnp.asarray(geom.rod_lengths) ** 2
    return ud, disc


@jax.jit
def inverse_kinematics(geom: Geometry, q: jax.Array) -> jax.Array:
    """Slider positions ``s`` (``(..., 6)`` [m]) for poses ``q`` (``(..., 5)``); NaN where unreachable."""
    ud, disc = _branch_terms(geom, q)
    return cast(jax.Array, ud - jnp.sqrt(disc))  # jax.jit's wrapper returns Any


@jax.jit
def jacobian(geom: Geometry, q: jax.Array) -> jax.Array:
    """``ds/dq``, shape ``(..., 6, 5)`` (forward-mode derivative of the closed-form IK)."""
    jac = jnp.vectorize(jax.jacfwd(lambda qq: inverse_kinematics(geom, qq)), signature="(5)->(6,5)")
    return cast(jax.Array, jac(q))  # jnp.vectorize returns an untyped callable


def forward_kinematics(
    geom: Geometry, s: jax.Array, q0: ArrayLike | None = None, iterations: int = 12
) -> tuple[jax.Array, jax.Array]:
    """Pose ``q`` whose IK is ``s`` (Gauss-Newton from ``q0``, default home); returns ``(q, residual [m])``.

    ``residual`` is the max |IK(q) - s| after the last iteration: near zero when ``s``
    is consistent with the mechanism (six sliders over-determine five coordinates).
    """
    q0 = jnp.asarray(geom.home if q0 is None else q0, dtype=s.dtype)

    def solve(s1: jax.Array, q1: jax.Array) -> tuple[jax.Array, jax.Array]:
        def step(q: jax.Array, _: None) -> tuple[jax.Array, None]:
            r = inverse_kinematics(geom, q) - s1
            J = jax.jacfwd(lambda qq: inverse_kinematics(geom, qq))(q)
            return q - jnp.linalg.solve(J.T @ J, J.T @ r), None

        q, _ = jax.lax.scan(step, q1, None, length=iterations)
        return q, jnp.max(jnp.abs(inverse_kinematics(geom, q) - s1))

    return cast(tuple[jax.Array, jax.Array], jnp.vectorize(solve, signature="(6),(5)->(5),()")(s, q0))


@jax.jit
def condition_number(geom: Geometry, q: jax.Array) -> jax.Array:
    """Condition number of the Jacobian at poses ``q``, its tilt columns scaled by the platform's radius.

    A tilt [rad] times the characteristic length (mean distance of the spherical joints
    from the platform centre) is a length, so every column is in metres.
    """
    length = jnp.mean(jnp.linalg.norm(jnp.asarray(geom.platform_points), axis=-1))
    J = jacobian(geom, q) * jnp.array([1.0, 1.0, 1.0, 1.0, 1.0]).at[3:].set(length)
    sv = jnp.linalg.svd(J, compute_uv=False)
    return sv[..., 0] / sv[..., -1]


def check_poses(
    geom: Geometry, q: npt.ArrayLike, cond_max: float = 30.0, margin: float = 0.0, dt: float | None = None
) -> dict[str, Any]:
    """Check poses ``q`` (``(N, 5)``) host-side before any simulation; raise :class:`GeometryError` if bad.

    Every branch must be reachable, every slider within its stroke (shrunk by ``margin``
    [m] at both ends), the UPU leg within its limits, the leg above the base, and
    :func:`condition_number` at most ``cond_max`` (the default geometry stays below 15.2
    on the paper's paths).  The error names the first pose that fails (its index, and its time
    when ``dt``, the poses' period [s], is given), the branch (1 to 6, as the paper numbers them),
    the value and the limit.  Returns the extremes found.
    """
    q = np.atleast_2d(np.asarray(q, dtype=float))
    if q.ndim != 2 or q.shape[1] != 5 or not np.isfinite(q).all():
        raise GeometryError(f"poses: expected finite (N, 5) poses (x, y, z, a, b), got shape {q.shape}")
    ud, disc = (np.asarray(a) for a in _branch_terms(geom, jnp.asarray(q)))
    s = ud - np.sqrt(np.maximum(disc, 0.0))  # inverse_kinematics, from the terms already at hand (where reachable)
    lo, hi = np.asarray(geom.stroke_min) + margin, np.asarray(geom.stroke_max) - margin
    leg = np.linalg.norm(q[:, :3], axis=1)
    cond = np.nan_to_num(np.asarray(condition_number(geom, jnp.asarray(q))), nan=np.inf)
    out = (s < lo) | (s > hi)

    def at(k: int) -> str:
        return f"pose {k}" + ("" if dt is None else f" (t = {k * dt:.6g} s)") + f" {_fmt(q[k])}"

    def unreachable(k: int) -> str:
        return f"{at(k)}: branch {int(np.argmax(disc[k] < 0)) + 1} unreachable (its rod is too short for the joint)"

    def out_of_stroke(k: int) -> str:
        i = int(np.argmax(out[k]))
        return (
            f"{at(k)}: slider {i + 1} out of stroke, s = {s[k, i] * 1e3:.1f} mm, expected {lo[i] * 1e3:.1f} to "
            f"{hi[i] * 1e3:.1f} mm"
        )

    # (which poses fail, the message for pose k); of two failing at one pose, the first listed is said
    checks: list[tuple[np.bool_ | npt.NDArray[np.bool_], Callable[[int], str]]] = [
        (q[:, 2] <= 0, lambda k: f"{at(k)}: expected the platform above the base (z > 0), got z = {q[k, 2]:.4g} m"),
        ((disc < 0).any(axis=1), unreachable),
        (out.any(axis=1), out_of_stroke),
        (
            (leg < float(geom.upu_min)) | (leg > float(geom.upu_max)),
            lambda k: (
                f"{at(k)}: UPU leg {leg[k] * 1e3:.1f} mm outside {float(geom.upu_min) * 1e3:.0f} to "
                f"{float(geom.upu_max) * 1e3:.0f} mm"
            ),
        ),
        (cond > cond_max, lambda k: f"{at(k)}: near-singular, Jacobian condition number {cond[k]:.3g} > {cond_max:g}"),
    ]
    failing = [(int(np.argmax(bad)), n) for n, (bad, _) in enumerate(checks) if bad.any()]
    if failing:
        k, n = min(failing)
        raise GeometryError(checks[n][1](k))
    return {
        "slider_min_m": s.min(axis=0).tolist(),
        "slider_max_m": s.max(axis=0).tolist(),
        "cond_max": float(cond.max()),
        "upu_leg_m": [float(leg.min()), float(leg.max())],
    }


def _fmt(q: npt.NDArray[np.float64]) -> str:
    return f"(x={q[0] * 1e3:.1f} mm, y={q[1] * 1e3:.1f} mm, z={q[2] * 1e3:.1f} mm, a={q[3]:.3g}, b={q[4]:.3g})"
