"""The checked derivations of the design notes, held by the code (python-control as the oracle)."""

import math

import control as ct
import jax.numpy as jnp
import numpy as np
import pytest

from pusupu_jax import AxisLoad, loops
from pusupu_jax import analysis as an


def _freq(lti_block, w):
    """Frequency response of a continuous JAX LTI block (axis 0) at rad/s ``w``."""
    A, B, C, D = (np.asarray(m)[0] for m in (lti_block.A, lti_block.B, lti_block.C, lti_block.D))
    return np.array([(C @ np.linalg.solve(1j * x * np.eye(A.shape[0]) - A, B) + D).item() for x in w])


W = np.logspace(-2, 5, 200)


def test_c2_is_the_imc_controller_of_the_nominal_position_plant(table1):
    """C2 = Q/(1 - P Q) with P = 1/(s(T0 s+1)), Q = P^-1 f, f = (3 l2 s+1)/(l2 s+1)^3."""
    l2, T0 = float(table1.lambda2[0]), float(table1.T0[0])
    s = ct.tf("s")
    P = 1 / (s * (T0 * s + 1))
    f = (3 * l2 * s + 1) / (l2 * s + 1) ** 3
    Q = (s * (T0 * s + 1)) * f
    imc = Q(1j * W) / (1 - P(1j * W) * Q(1j * W))  # pointwise: no numerical pole-zero cancellation
    jax_c2 = _freq(loops.imc_c2(table1.lambda2, table1.T0), W)
    np.testing.assert_allclose(jax_c2, imc, rtol=1e-8)


@pytest.mark.parametrize("lambda1,lambda2", [(0.018, 0.15), (0.05, 0.03), (0.1, 0.1)])
@pytest.mark.parametrize("source", ["jax", "analysis"])
def test_2dof_imc_responses_with_a_perfect_model(table1, lambda1, lambda2, source):
    """With the plant C2 was designed on, P = 1/(s (T0 s+1)), interconnected in python-control (float64):

    * the loop's own (disturbance) response is f_d = (3 l2 s+1)/(l2 s+1)^3: the complementary
      sensitivity C2 P/(1 + C2 P) = f_d, so an output disturbance reaches theta as 1 - f_d;
    * the full form's reference response C1 C2 P/(1 + C2 P) is f_r = (3 l1 s+1)/(l1 s+1)^3
      (lambda1 alone sets tracking);
    * the printed form's is (3 l1 s+1)/(l2 s+1)^3 (lambda2 sets tracking too; a ramp lags 3 (l2 - l1)).

    Tolerance 1e-9 relative over 1e-2..1e5 rad/s: only rounding separates the two sides.
    """
    T0 = float(table1.T0[0])
    s = ct.tf("s")
    f_r = (3 * lambda1 * s + 1) / (lambda1 * s + 1) ** 3
    f_d = (3 * lambda2 * s + 1) / (lambda2 * s + 1) ** 3
    P = ct.ss(1 / (s * (T0 * s + 1)))
    if source == "jax":  # the discretiser's continuous blocks, brought into python-control

        def c1(form):
            blk = loops.imc_c1(jnp.full(6, lambda1), jnp.full(6, lambda2), form)
            return ct.ss(*(np.asarray(m)[0] for m in (blk.A, blk.B, blk.C, blk.D)))

        blk = loops.imc_c2(jnp.full(6, lambda2), jnp.full(6, T0))
        c2 = ct.ss(*(np.asarray(m)[0] for m in (blk.A, blk.B, blk.C, blk.D)))
    else:

        def c1(form):
            return an.imc_c1(lambda1, lambda2, form)

        c2 = an.blocks(table1.replace(lambda2=np.full(6, lambda2)), AxisLoad.default())["C2"]
        c2 = ct.ss(*ct.ssdata(c2))
    loop = ct.feedback(c2 * P, 1)  # theta / r1: the loop's complementary sensitivity
    jw = 1j * W
    np.testing.assert_allclose(loop(jw), f_d(jw), rtol=1e-9)
    np.testing.assert_allclose(ct.feedback(1, c2 * P)(jw), 1 - f_d(jw), rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose((c1("full") * loop)(jw), f_r(jw), rtol=1e-9)
    printed = (3 * lambda1 * s + 1) / (lambda2 * s + 1) ** 3
    np.testing.assert_allclose((c1("printed") * loop)(jw), printed(jw), rtol=1e-9)


@pytest.mark.parametrize("name", ["Gxi", "Gcf", "Gi", "Gxv", "Gw", "Gv", "C1", "C1 printed", "C2", "PID"])
def test_jax_blocks_match_the_analysis_blocks(table1, name):
    p = table1.replace(imc_form="printed") if name == "C1 printed" else table1
    name = name.split()[0]
    jax_block = {
        "Gxi": loops.first_order(jnp.ones(6), p.Tcf),
        "Gcf": loops.first_order(p.Kcf, p.Tcf),
        "Gi": loops.pi_controller(p.Ki, p.Ti),
        "Gxv": loops.first_order(jnp.ones(6), p.Tw),
        "Gw": loops.first_order(p.Kw, p.Tw),
        "Gv": loops.pi_controller(p.Kv, p.Tv),
        "C1": loops.imc_c1(p.lambda1, p.lambda2, p.imc_form),
        "C2": loops.imc_c2(p.lambda2, p.T0),
        "PID": loops.pid_controller(p.Kp_pid, p.Ki_pid, p.Kd_pid, p.Tf_pid),
    }[name]
    ref = an.blocks(p, AxisLoad.default())[name]
    np.testing.assert_allclose(_freq(jax_block, W), ref(1j * W), rtol=1e-8)


def test_current_loop_of_the_paper_crosses_near_250_hz_with_67_degrees(table1):
    m = an.margins(an.current_open_loop_locked(table1))
    assert m["crossover_hz"] == pytest.approx(250.0, rel=0.01)
    assert m["phase_margin_deg"] == pytest.approx(67.0, abs=0.5)
    # Ti = L/R: the PI zero cancels the armature pole (to Table 1's rounding)
    assert float(table1.Ti[0]) == pytest.approx(float(table1.L[0] / table1.R[0]), rel=2e-3)


def test_nominal_position_loop_has_53_degrees_at_6_67_rad_s(table1):
    gm, pm, _, _, wgc, _ = ct.stability_margins(an.nominal_position_open_loop(table1))
    assert wgc == pytest.approx(6.667, rel=1e-3)
    assert pm == pytest.approx(53.13, abs=0.05)


def test_default_torque_constant_reproduces_T0(table1):
    """Kt (= Ke) was chosen so that the identified velocity loop has T0 = 0.01475 s with the default load."""
    load = AxisLoad.default()
    assert an.identify_T0(table1, load) == pytest.approx(0.01475, rel=5e-4)
    assert an.kt_for_T0(table1, load) == pytest.approx(float(table1.Kt[0]), rel=1e-3)


def test_real_loops_keep_margins_with_defaults(table1):
    """With the default drive train and load every real loop (with back-EMF and filters) is stable with margin."""
    result = an.loop_metrics(table1, AxisLoad.default())
    for name in an.LOOPS:
        m = result["axes"][0][name]
        assert m["phase_margin_deg"] > 45 and m["gain_margin_db"] > 6, (name, m)
    # the real position loop stays close to the nominal design (53.1 deg at 1.061 Hz)
    pos = result["axes"][0]["position"]
    assert pos["phase_margin_deg"] == pytest.approx(53.1, abs=2.0)
    assert pos["crossover_hz"] == pytest.approx(6.667 / (2 * math.pi), rel=0.02)
