"""Reverse-mode gradients through the whole cascade against central finite differences (float64), and the
forward/reverse gradient helper."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from pusupu_jax import AxisLoad, simulate, sim

N = 100  # 0.1 s at 1 kHz: 2000 current-loop ticks
T = np.arange(N) * 1e-3
REF = np.repeat((3.0 * (1 - np.cos(2 * np.pi * 5 * T)))[:, None], 6, axis=1)  # motor rad, smooth start
LOAD = AxisLoad.default()  # Coulomb friction included: tanh-smoothed, so differentiable


def objective(params, mode):
    """Mean squared tracking error [rad^2] plus a small current-effort term [A^2]."""
    trace = sim.rollout(params, LOAD, REF, outer=mode)
    return jnp.mean((trace.theta - trace.reference) ** 2) + 1e-3 * jnp.mean(trace.current**2)


_value = {m: jax.jit(lambda p, m=m: objective(p, m)) for m in ("imc", "pid")}
_grad = {m: jax.jit(jax.grad(lambda p, m=m: objective(p, m))) for m in ("imc", "pid")}
GROUPS = [
    ("imc", ["lambda1", "lambda2", "T0", "Kv", "Tv", "Ki", "Ti"]),
    ("pid", ["Kp_pid", "Ki_pid", "Kd_pid", "Tf_pid"]),
]


@pytest.mark.parametrize("mode,names", GROUPS)
def test_gradient_matches_central_differences(table1, mode, names):
    """Relative error <= 1e-5; the step h = 1e-5 |p| keeps truncation (~h^2) and rounding (~1e-16/h) below 1e-8."""
    grad = _grad[mode](table1)
    for axis in (0, 3):
        for name in names:
            v = np.asarray(getattr(table1, name))
            h = 1e-5 * abs(v[axis])
            e = np.zeros(6)
            e[axis] = h
            fd = (_value[mode](table1.replace(**{name: v + e})) - _value[mode](table1.replace(**{name: v - e}))) / (
                2 * h
            )
            ad = float(np.asarray(getattr(grad, name))[axis])
            assert abs(ad - fd) <= 1e-5 * abs(fd), f"{mode} {name} axis {axis}: grad {ad:.10g} vs fd {float(fd):.10g}"


def test_changing_gains_never_recompiles(table1):
    ref = np.zeros((20, 6))
    simulate(table1, ref)
    before = sim._rollout_jit._cache_size()
    for k in range(3):
        simulate(table1.replace(Kv=table1.Kv * (1.1 + k), lambda1=table1.lambda1 * (0.5 + k)), ref)
    assert sim._rollout_jit._cache_size() == before
    grads_before = _grad["imc"]._cache_size()
    _grad["imc"](table1.replace(lambda2=table1.lambda2 * 0.7))
    _grad["imc"](table1.replace(Ti=table1.Ti * 1.3))
    assert _grad["imc"]._cache_size() == grads_before == 1


def test_rematerialised_gradient_is_the_same(table1):
    """remat=True changes memory and time, not the numbers."""

    def loss(p, remat):
        trace = sim.rollout(p, LOAD, REF[:20], outer="imc", remat=remat)
        return jnp.mean((trace.theta - trace.reference) ** 2)

    plain = jax.grad(loss)(table1, False)
    remat = jax.grad(loss)(table1, True)
    for name in ("lambda1", "lambda2", "Kv", "Ti"):
        np.testing.assert_allclose(getattr(remat, name), getattr(plain, name), rtol=1e-12)


def test_forward_and_reverse_value_and_grad_agree_on_a_pytree():
    """pusupu_jax.gradients: both modes return (value, aux) and the gradient in the parameters' structure."""
    from pusupu_jax.gradients import value_and_grad

    def fun(x, scale):
        value = scale * (jnp.sum(jnp.sin(x["a"]) ** 2) + x["b"] ** 3)
        return value, {"doubled": 2 * value}

    x = {"a": jnp.array([0.3, -1.2, 2.0]), "b": jnp.array(0.7)}
    (v_r, aux_r), g_r = value_and_grad(fun, "reverse")(x, 1.5)
    (v_f, aux_f), g_f = jax.jit(value_and_grad(fun, "forward"))(x, 1.5)
    assert float(v_f) == pytest.approx(float(v_r), rel=1e-15) and float(aux_f["doubled"]) == pytest.approx(
        2 * float(v_r)
    )
    np.testing.assert_allclose(g_f["a"], 1.5 * np.sin(2 * np.asarray(x["a"])), rtol=1e-14)
    np.testing.assert_allclose(g_f["b"], 1.5 * 3 * 0.7**2, rtol=1e-14)
    for k in x:
        np.testing.assert_allclose(g_f[k], g_r[k], rtol=1e-14)
    with pytest.raises(ValueError, match="gradient mode: expected one of"):
        value_and_grad(fun, "sideways")
