"""Gradients through the MJX machine against central differences: through contact, through the cascade
co-simulated with it, and of every objective term the tuner uses (apart from tests/test_mjx_plant.py so that
pytest-xdist can run these long compiles beside the rest of it)."""

import contextlib
import io

import jax
import jax.numpy as jnp
import numpy as np

from pusupu_jax.hybrid import HybridGains
from pusupu_jax.sim import rollout
from test_mjx_plant import CONTACT_PLANT, G, PLANT, RATES, SERVO, TORQUE, _above_the_surface, c_mujoco_run

with contextlib.redirect_stdout(io.StringIO()):  # MJX prints its optional GPU backends' import failures
    from mujoco import mjx


def test_gradient_through_contact_matches_central_differences():
    """d(mean platform height over the last 25 ms of 100 ms) / d(motor torque, the same on every axis) with the
    tool pressed on the surface (C MuJoCo: in contact at 75 ms and at 100 ms): reverse mode against
    central differences (h = 1e-5 N m), observed 4e-10 relative (7e-8 at h = 1e-4, 2e-7 at 1e-6: truncation
    and round-off of the differences).  Bound 1e-6.
    """
    aux = CONTACT_PLANT.prepare(SERVO, None, RATES.dt_mech)
    q0 = jnp.asarray(_above_the_surface(1e-3))
    platform = CONTACT_PLANT.mj_model.body("platform").id
    n, u, h = len(TORQUE), 0.02, 1e-5

    def height(tau):
        def body(d, _):
            d = CONTACT_PLANT.step(aux, d, jnp.full(6, tau))
            return d, d.xpos[platform, 2]

        d0 = mjx.forward(aux.model, CONTACT_PLANT.init(aux).replace(qpos=q0))
        return jnp.mean(jax.lax.scan(body, d0, None, length=n)[1][-n // 4:])

    value_and_grad = jax.jit(jax.value_and_grad(height))
    for steps in (3 * n // 4, n):
        assert c_mujoco_run(CONTACT_PLANT, aux, np.full((steps, 6), u), np.asarray(q0))[3].ncon == 1
    ad = float(value_and_grad(u)[1])
    fd = (float(value_and_grad(u + h)[0]) - float(value_and_grad(u - h)[0])) / (2 * h)
    assert fd > 0.0  # more holding torque, less weight on the surface: the platform sits higher
    assert abs(ad - fd) <= 1e-6 * abs(fd), (ad, fd)


def _tracking_and_torque_peak(params, reference):
    """IMC mode: mean squared motor-angle error [rad^2] + 0.01 x a smooth torque peak (log-sum-exp, sharpness
    20 /(N m))."""
    trace = rollout(params, None, reference, plant=PLANT, rates=RATES, outer="imc")
    peak = jax.nn.logsumexp(20.0 * jnp.abs(trace.torque), axis=0) / 20.0
    return jnp.mean((trace.theta - trace.reference) ** 2) + 1e-2 * jnp.mean(peak)


def _short_path(n=50):
    """Platform poses of a 5 mm cosine move along x in ``n`` position periods (50 ms)."""
    x = 0.005 * (1 - np.cos(np.pi * np.arange(n) / (n - 1)))
    return np.stack([x, 0 * x, np.full(n, float(G.home[2])), 0 * x, 0 * x], axis=1)


def _short_move(outer):
    """The rollout reference of :func:`_short_path` for ``outer``."""
    from pusupu_jax.machine import machine_reference

    return machine_reference(SERVO, _short_path(), outer, rates=RATES)


# Hybrid mode is left to test_every_objective_term_has_the_gradient_of_central_differences below (lambda1, lambda2,
# T0, m6, c6, g, every term, both gradient modes, the default signed form); the rms form differs from it only in rho',
# whose gradient tests/test_hybrid.py checks in the force law itself.  A hybrid case here cost a compile (100 s).
def test_gradient_through_the_cosimulation_matches_central_differences():
    """Reverse mode through cascade + MJX in IMC mode (50 ms: 200 MJX steps, 1000 current ticks), servo gains
    perturbed on axis 0: relative error <= 1e-3.  Observed: 1.4e-6 (lambda1), 3.8e-7 (lambda2), 6.8e-10 (Kv),
    1.8e-6 (Tv)."""
    ref = _short_move("imc")
    objective = jax.jit(_tracking_and_torque_peak)
    grad = jax.jit(jax.grad(_tracking_and_torque_peak))(SERVO, ref)
    for name in ("lambda1", "lambda2", "Kv", "Tv"):
        v = np.asarray(getattr(SERVO, name))
        e = np.zeros(6)
        e[0] = 1e-4 * abs(v[0])
        plus, minus = SERVO.replace(**{name: v + e}), SERVO.replace(**{name: v - e})
        fd = (objective(plus, ref) - objective(minus, ref)) / (2 * e[0])
        ad = float(np.asarray(getattr(grad, name))[0])
        assert fd != 0.0, name
        assert abs(ad - fd) <= 1e-3 * abs(fd), (name, ad, float(fd))


def test_every_objective_term_has_the_gradient_of_central_differences():
    """Each term of pusupu_jax.objectives through hybrid mode on the machine (50 ms), d/d(log gain) for the
    tuner's default fields (shared lambda1, lambda2, T0 and m6, c6, g), in reverse and in forward mode: relative
    error <= 1e-3, or within 1e-7 of the term's size.  Observed: 1e-7 to 2e-5 where the gradient is
    substantial (lambda2, c6 on every term); up to 1e-2 only on gradients 1e-6 of the term or smaller (g and
    m6 on a 50 ms run, lambda1 on force_peak).  The two modes agree to 1e-9 of the term's size: they differ
    by rounding only.
    """
    from pusupu_jax import objectives
    from tune.space import Space

    ref = _short_move("hybrid")
    path = _short_path()
    space = Space.create(("imc", "hybrid"), SERVO, HybridGains())

    def terms(z):
        servo, hybrid = space.apply(z)
        trace = rollout(servo, None, ref, plant=PLANT, rates=RATES, outer="hybrid", hybrid=hybrid)
        return objectives.terms(trace, servo, jnp.asarray(path), RATES.dt_position, sharpness_force=1.0)

    z0 = space.z0()
    jac = jax.jit(jax.jacrev(terms))(z0)
    # forward mode as one tangent at a time, and the terms' values from the same compiled program (its primal
    # output): one compile serves the forward-mode check and the central differences
    jvp = jax.jit(lambda z, dz: jax.jvp(terms, (z,), (dz,)))
    zero = {k: jnp.zeros_like(v) for k, v in z0.items()}

    def value(z):
        return jvp(z, zero)[0]

    h = 1e-3
    at_start = value(z0)
    report = []
    for field in z0:
        plus, minus = value(z0 | {field: z0[field] + h}), value(z0 | {field: z0[field] - h})
        forward = jvp(z0, zero | {field: jnp.ones_like(z0[field])})[1]
        for name in objectives.TERMS:
            fd = (float(plus[name]) - float(minus[name])) / (2 * h)
            ad = float(jac[name][field])
            report.append((field, name, ad, fd))
            assert abs(float(forward[name]) - ad) <= 1e-9 * abs(float(at_start[name])), (field, name)
            # 1e-3 relative, or 1e-7 of the term's own size for gradients too small to matter to the tuner
            # (where central differences see the rollout's round-off: force_peak vs lambda1 is 1e-6 relative)
            assert abs(ad - fd) <= 1e-3 * abs(fd) + 1e-7 * abs(float(at_start[name])), (field, name, ad, fd)
    assert sum(abs(fd) > 1e-3 * abs(float(at_start[name])) for _, name, _, fd in report) >= 5  # real gradients
