"""Geometry and kinematics of the 6PUS-UPU mechanism (float64)."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from pusupu_jax.plant import kinematics as K
from pusupu_jax.plant.geometry import Geometry, GeometryError, dump_geometry, load_geometry, validate_geometry

G = Geometry.default()
Z0 = float(G.home[2])


def paper_paths(n=361):
    """The 200 mm-radius arc in the horizontal plane and (0,0,0) -> (-100,-100,0) -> (100,100,0) mm, about home."""
    phi = np.linspace(0, 2 * np.pi, n)
    arc = np.stack([0.2 * np.cos(phi), 0.2 * np.sin(phi), np.full(n, Z0), 0 * phi, 0 * phi], axis=1)
    t = np.linspace(0, 1, 101)[:, None]
    corner = np.array([-0.1, -0.1, 0, 0, 0])
    p2p = np.concatenate([t * corner, corner + t * np.array([0.2, 0.2, 0, 0, 0])]) + np.array([0, 0, Z0, 0, 0])
    return arc, p2p


def workspace_sample(n=300, seed=0):
    """Poses spread over the working volume: |x|, |y| <= 220 mm, z within +-80 mm of home, tilts within 0.12 rad."""
    rng = np.random.default_rng(seed)
    lo, hi = np.array([-0.22, -0.22, Z0 - 0.08, -0.12, -0.12]), np.array([0.22, 0.22, Z0 + 0.08, 0.12, 0.12])
    return lo + (hi - lo) * rng.random((n, 5))


def test_default_geometry_holds_the_paper_paths_with_margin():
    """Every slider at least 100 mm inside its stroke and the Jacobian condition number <= 15.2 along both paths."""
    validate_geometry(G)
    for path in paper_paths():
        report = K.check_poses(G, path, cond_max=15.2, margin=0.1)
        assert report["cond_max"] < 15.2


def test_inverse_and_forward_kinematics_round_trip_across_the_workspace():
    q = workspace_sample()
    K.check_poses(G, q)  # the sample is reachable and well conditioned
    s = K.inverse_kinematics(G, jnp.asarray(q))
    q_fk, residual = K.forward_kinematics(G, s)
    err_xyz = np.max(np.abs(np.asarray(q_fk)[:, :3] - q[:, :3]))
    err_tilt = np.max(np.abs(np.asarray(q_fk)[:, 3:] - q[:, 3:]))
    assert err_xyz <= 1e-9 and err_tilt <= 1e-9, (err_xyz, err_tilt)
    assert float(np.max(residual)) <= 1e-12


def test_jacobian_matches_central_differences():
    q = workspace_sample(20, seed=1)
    J = np.asarray(K.jacobian(G, jnp.asarray(q)))
    h = 1e-6
    for k in range(5):
        e = np.zeros(5)
        e[k] = h
        fd = (
            np.asarray(K.inverse_kinematics(G, jnp.asarray(q + e)))
            - np.asarray(K.inverse_kinematics(G, jnp.asarray(q - e)))
        ) / (2 * h)
        np.testing.assert_allclose(J[:, :, k], fd, rtol=1e-6, atol=1e-9)


def test_upu_branch_imposes_the_orientation():
    """R is a rotation, its normal is the commanded tilt, and it is the UPU chain Rx(phi1) Ry(phi2) Ry(alpha)
    Rx(beta)."""
    q = jnp.asarray(workspace_sample(50, seed=2))
    R = np.asarray(K.platform_rotation(q))
    np.testing.assert_allclose(R @ np.swapaxes(R, -1, -2), np.broadcast_to(np.eye(3), R.shape), atol=1e-14)
    n = np.asarray(jnp.einsum("...ij,j->...i", K.rot_x(q[:, 3]) @ K.rot_y(q[:, 4]), jnp.array([0.0, 0.0, 1.0])))
    np.testing.assert_allclose(R[:, :, 2], n, atol=1e-14)
    phi1, phi2, length, alpha, beta = K.upu_angles(q)
    leg = np.asarray(jnp.einsum("...ij,j->...i", K.rot_x(phi1) @ K.rot_y(phi2), jnp.array([0.0, 0.0, 1.0])))
    np.testing.assert_allclose(leg * np.asarray(length)[:, None], np.asarray(q[:, :3]), atol=1e-14)
    chain = K.rot_x(phi1) @ K.rot_y(phi2) @ K.rot_y(alpha) @ K.rot_x(beta)
    np.testing.assert_allclose(np.asarray(chain), R, atol=1e-14)
    # a level pose is level and unturned wherever the platform is
    arc, _ = paper_paths(37)
    np.testing.assert_allclose(
        np.asarray(K.platform_rotation(jnp.asarray(arc))), np.broadcast_to(np.eye(3), (37, 3, 3)), atol=1e-14
    )


def test_forward_kinematics_is_differentiable():
    s0 = K.inverse_kinematics(G, jnp.asarray(G.home))
    dq = jax.jacfwd(lambda s: K.forward_kinematics(G, s)[0])(s0)
    J = np.asarray(K.jacobian(G, jnp.asarray(G.home)))
    np.testing.assert_allclose(np.asarray(dq) @ J, np.eye(5), atol=1e-9)  # FK is a left inverse of IK


@pytest.mark.parametrize(
    "pose,message",
    [
        ([1.0, 0.0, Z0, 0, 0], "branch . unreachable"),
        ([0.0, 0.0, Z0 + 0.45, 0, 0], "slider . out of stroke"),
        ([0.0, 0.0, -0.1, 0, 0], "above the base"),
        ([0.0, 0.0, 0.5, 0, 0], "UPU leg"),
    ],
)
def test_bad_poses_are_named(pose, message):
    g = G.replace(stroke_min=np.full(6, -1.0)) if "UPU" in message else G
    with pytest.raises(GeometryError, match=message):
        K.check_poses(g, np.array([G.home, pose]))


def test_near_singular_poses_are_caught():
    with pytest.raises(GeometryError, match="near-singular, Jacobian condition number"):
        K.check_poses(G, G.home[None], cond_max=5.0)


def test_inconsistent_geometry_and_files(tmp_path):
    cases = [
        (dict(rail_points=np.zeros((5, 3))), r"rail_points: expected shape \(6, 3\)"),
        (dict(rail_dirs=np.tile([0, 0, 2.0], (6, 1))), "expected unit vectors"),
        (dict(rod_lengths=np.full(6, -0.9)), "rod_lengths: expected positive"),
        (dict(stroke_min=np.full(6, 0.5)), "expected < stroke_max"),
        (dict(home=np.array([0, 0, np.nan, 0, 0])), "home: expected finite"),
    ]
    for change, message in cases:
        with pytest.raises(GeometryError, match=message):
            validate_geometry(G.replace(**change))
    path = tmp_path / "g.yaml"
    path.write_text(dump_geometry(G))
    g2 = load_geometry(path)
    for name in ("rail_points", "platform_points", "rod_lengths", "home"):
        np.testing.assert_array_equal(np.asarray(getattr(g2, name)), np.asarray(getattr(G, name)))
    path.write_text("rod_length: 0.9\n")
    with pytest.raises(GeometryError, match="unknown geometry field 'rod_length'"):
        load_geometry(path)


def test_the_pose_jacobian_of_a_padded_program_is_each_poses_own():
    """pusupu_jax.plant.dynamics.pose_jacobian pads the poses to a power of two (one program per octave of path
    lengths): each pose's ``qpos`` and ``dqpos/dq`` come out as they do alone, and equal ``jax.jacfwd`` of the pose map
    (1e-12: XLA vectorises a batch differently from one pose, last bits only), for lengths below, at and above a
    padded size, and the shorter paths of one octave share a program."""
    from pusupu_jax.plant import dynamics
    from pusupu_jax.plant.model import ModelOptions, build_model, pose_to_qpos
    from pusupu_jax.programs import describe

    assert [dynamics.padded_rows(n) for n in (1, 64, 65, 128, 129, 43347)] == [64, 64, 128, 128, 256, 65536]
    poses = workspace_sample(129, seed=1)
    phi = pose_to_qpos(build_model(G, ModelOptions()), G)
    want_qpos, want_T = phi(jnp.asarray(poses)), jax.vmap(jax.jacfwd(phi))(jnp.asarray(poses))
    jacobian = dynamics.pose_jacobian(G)
    for n in (3, 64, 100, 129):
        qpos, T = jacobian(poses[:n])
        assert qpos.shape == (n, want_qpos.shape[1]) and T.shape == (n, want_qpos.shape[1], 5)
        np.testing.assert_allclose(qpos, want_qpos[:n], rtol=0, atol=1e-12)
        np.testing.assert_allclose(T, want_T[:n], rtol=0, atol=1e-12)
    # the process's one program for G holds one executable per padded size (64, 128, 256 here), none per length
    program = dynamics._POSE_JACOBIANS[(describe((G, ModelOptions())), True)]
    rows = {int(avals[0].split("[")[1].split(",")[0]) for _, avals in program._calls}
    assert {64, 128, 256} <= rows and all(dynamics.padded_rows(r) == r for r in rows), rows
