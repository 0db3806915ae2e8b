"""Force/position hybrid control (eq. 10-14) and the minimum-norm inverse dynamics that feeds it F_q."""

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest

from pusupu_jax import AxisLoad, LoopRates, ParameterError, ServoParams, rollout
from pusupu_jax import hybrid as H
from pusupu_jax.plant import dynamics as D
from pusupu_jax.plant import model as M
from pusupu_jax.plant.axis import screw_ratio
from pusupu_jax.plant.geometry import Geometry
from pusupu_jax.trajectories import platform_path

G = Geometry.default()
SERVO = ServoParams.table1()
RATES = LoopRates()
P2P = platform_path("p2p", G.home, RATES)[:1600]  # the first 1.6 s of the paper's path, accelerating


@pytest.fixture(scope="module")
def p2p_forces():
    return D.inverse_dynamics_forces(SERVO, P2P, RATES.dt_position, G)


def test_minimum_norm_forces_drive_the_nominal_machine_along_the_path(p2p_forces):
    """Open loop: the forces alone, applied in C MuJoCo from the assembled start, reproduce the path.

    Nothing corrects drift here, so this checks the whole inverse-dynamics chain (pose to
    qpos map and its Jacobian, finite-difference rates, RNE, armature, projection).
    Observed 20 um after 1.5 s (the platform moves 20 mm); bound 50 um.  A force error of
    1 N on the machine (about 90 kg, plus 74 kg of reflected rotor per slider) would
    drift millimetres in that time.
    """
    F, _ = p2p_forces
    m = D.nominal_model(SERVO, G, M.ModelOptions())
    d = mujoco.MjData(m)
    d.qpos[:] = M.assembled_qpos(m, G, P2P[0])
    mujoco.mj_forward(m, d)
    dofs, platform = M.slide_dofs(m), m.body("platform").id
    n_sub = int(round(RATES.dt_position / m.opt.timestep))
    err = []
    for k in range(1500):
        for _ in range(n_sub):
            d.qfrc_applied[:] = 0
            d.qfrc_applied[dofs] = F[k]
            mujoco.mj_step(m, d)
        err.append(np.linalg.norm(d.xpos[platform] - P2P[k + 1, :3]))
    assert np.linalg.norm(P2P[1500, :3] - P2P[0, :3]) > 0.015
    assert max(err) < 5e-5, max(err)


def test_the_distribution_has_no_internal_force(p2p_forces):
    """Minimum norm: F has no component along the null space of J^T (the squeeze that does no work)."""
    F, J = p2p_forces
    for k in (0, 800, 1599):
        null = np.linalg.svd(J[k].T)[2][-1]  # J^T null = 0
        assert np.linalg.norm(J[k].T @ null) < 1e-12
        assert abs(null @ F[k]) < 1e-9 * np.linalg.norm(F[k])
    assert np.all(F[:, 5] > 10.0)  # branch 6 carries a real share of the weight


def test_coupling_row_maps_branch_motions_onto_branch_6(p2p_forces):
    _, J = p2p_forces
    w = D.coupling_row(J[:3])
    dq = np.random.default_rng(1).normal(size=(3, 5))
    ds = np.einsum("nij,nj->ni", J[:3], dq)
    np.testing.assert_allclose(np.einsum("ni,ni->n", w, ds[:, :5]), ds[:, 5], rtol=1e-10)


def test_rms_rate_is_eq_12_read_as_rms():
    e = np.random.default_rng(2).normal(size=(7, 6))
    xi = np.array([[row[n] - row[m] for n in range(4) for m in range(n + 1, 5)] for row in e])
    assert xi.shape == (7, 10)
    rms = np.sqrt(np.mean(xi**2, axis=1))
    np.testing.assert_allclose(H.rms_rate(jnp.asarray(e)), rms, rtol=1e-12)
    np.testing.assert_allclose(H.synchronous_error(jnp.asarray(e), 0.001), np.cumsum(rms) * 1e-3, rtol=1e-12)
    # equal errors on branches 1-5: no synchronous error, and a finite (zero) gradient there
    g = jax.grad(lambda x: H.rms_rate(x))(jnp.ones(6))
    assert np.all(np.isfinite(g)) and float(H.rms_rate(jnp.ones(6))) == 0.0


def test_force_law_is_eq_14_in_both_forms():
    e = jnp.array([1e-3, 2e-3, -1e-3, 0.0, 5e-4, 7.0])  # the sixth error is not used by either form
    w = jnp.array([0.2, -0.1, 0.3, 0.5, 0.1])
    dt = 0.001
    for form, rate in (("rms", float(H.rms_rate(e))), ("signed", float(w @ e[:5]))):
        gains = H.HybridGains(m6=2.0, c6=3e3, g=4e4, form=form)
        state = H.ForceState(jnp.asarray(0.01), jnp.asarray(1e-4), jnp.asarray(0.0))
        new, force = H.step(gains, state, e, w, 50.0, dt)
        rho = 0.01 + rate * dt
        expected = 50.0 + 2.0 * (rate - 1e-4) / dt + 3e3 * rate + 4e4 * rho
        assert float(force) == pytest.approx(expected, rel=1e-12)
        assert float(new.rho) == pytest.approx(rho, rel=1e-12) and float(new.force) == float(force)


@pytest.mark.parametrize("form", H.RHO_FORMS)
def test_force_law_gradient_is_that_of_central_differences(form):
    """d F_6 / d (branch errors, m6, c6, g, the carried rho and rate) in both forms against central differences:
    within 1e-6 relative, or 1e-6 absolute for derivatives below 1 (m6, c6, g).  Observed 6e-8 or less, the
    round-off of the differences: F_6 is linear in all but the errors, and smooth in those away from equal errors.
    With this, the gradient through the machine is checked in the default (signed) form only
    (tests/test_mjx_plant.py), since the forms differ in nothing but ``rho'``."""
    x0 = np.array([1e-3, 2e-3, -1e-3, 0.0, 7e-4, 7.0, 2.0, 3e3, 4e4, 0.01, 1e-4])
    w = jnp.array([0.2, -0.1, 0.3, 0.5, 0.1])

    def force(x):
        gains = H.HybridGains(m6=x[6], c6=x[7], g=x[8], form=form)
        return H.step(gains, H.ForceState(x[9], x[10], jnp.asarray(0.0)), x[:6], w, 50.0, 0.001)[1]

    ad = np.asarray(jax.grad(force)(jnp.asarray(x0)))
    for k in range(len(x0)):
        h = 1e-6 * max(abs(x0[k]), 1e-3)
        e = np.zeros_like(x0)
        e[k] = h
        fd = (float(force(jnp.asarray(x0 + e))) - float(force(jnp.asarray(x0 - e)))) / (2 * h)
        assert abs(ad[k] - fd) <= 1e-6 * max(abs(fd), 1.0), (form, k, ad[k], fd)
    assert ad[5] == 0.0 and np.all(np.abs(ad[:5]) > 100.0)  # the sixth error is not used; the five are


def test_bad_hybrid_gains_are_rejected():
    with pytest.raises(ParameterError, match=r"HybridGains.c6: expected a number from 0 to 1e\+06"):
        H.HybridGains.from_mapping({"c6": -1.0})
    with pytest.raises(ParameterError, match=r"HybridGains.g: expected a number, got nan"):
        H.HybridGains.from_mapping({"g": float("nan")})
    with pytest.raises(ParameterError, match=r"form: expected one of \('rms', 'signed'\)"):
        H.HybridGains.from_mapping({"form": "abs"})
    with pytest.raises(ParameterError, match="unknown key 'k6'"):
        H.HybridGains.from_mapping({"k6": 1.0})


def test_hybrid_rollout_force_controls_axis_6_and_leaves_1_to_5_alone():
    """On six independent single-axis plants: axes 1-5 run as in IMC mode, to float64 rounding; axis 6's
    current settles at F r / (eta Kt) for a constant force command (zero coupling gains).  The two modes are two
    compiled programs: they agree to the bit at XLA's optimisation levels 0, 1 and 3 (an earlier tree's differed by
    1 ulp at level 0, 4e-16 rad of 0.14 rad); any coupling of the force law into axes 1-5 would show at 1e-6 of
    their motion.
    """
    n = 300
    theta = jnp.asarray(np.full((n, 6), 2.0))  # rad
    force = 30.0  # N: beats the 20 N Coulomb friction; the slider speeds up slowly, far from voltage limits
    ref = H.HybridReference(theta, jnp.full((n,), force), jnp.zeros((n, 5)))
    load = AxisLoad.default()
    run = jax.jit(rollout, static_argnames=("outer",))
    hybrid = run(SERVO, load, ref, outer="hybrid", hybrid=H.HybridGains(m6=0.0, c6=0.0, g=0.0))
    imc = run(SERVO, load, theta, outer="imc")
    np.testing.assert_allclose(np.asarray(hybrid.theta)[:, :5], np.asarray(imc.theta)[:, :5], rtol=1e-12, atol=1e-15)
    i_cmd = force * float(screw_ratio(SERVO)[5]) / (float(SERVO.eta[5]) * float(SERVO.Kt[5]))
    assert float(hybrid.current[-1, 5]) == pytest.approx(i_cmd, rel=1e-3)
    assert float(hybrid.velocity[-1, 5]) > 0.001  # pushed, not position-held


def test_rollout_wants_hybrid_gains_exactly_in_hybrid_mode():
    with pytest.raises(ValueError, match="hybrid gains are needed exactly when outer='hybrid'"):
        rollout(SERVO, AxisLoad.default(), jnp.zeros((3, 6)), outer="imc", hybrid=H.HybridGains())
