"""The drive train's friction law, in numpy and JAX, and what it costs the drives of the MJX machine."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from pusupu_jax.machine import machine_reference
from pusupu_jax.params import stack
from pusupu_jax.plant import kinematics as K
from pusupu_jax.plant.friction import Friction, slider_friction
from pusupu_jax.sim import rollout
from tests.test_mjx_plant import G, PLANT, RATES, SERVO


def test_the_law_computes_in_numpy_on_numpy_and_in_jax_on_jax_arrays_alike():
    """One function for both: numpy parameters and speeds give a numpy array (the simulated robot's host-side step
    dispatches nothing to JAX), JAX arrays a JAX array, equal to rounding; it opposes the speed and is odd in it."""
    friction = jax.tree.map(lambda x: np.asarray(x, dtype=float), Friction.of(SERVO))
    v = np.array([-0.1, -1e-3, 0.0, 2e-4, 1e-3, 0.05])  # m/s
    host = slider_friction(friction, v)
    device = slider_friction(Friction.of(SERVO), jnp.asarray(v))
    assert type(host) is np.ndarray and isinstance(device, jax.Array)
    np.testing.assert_allclose(host, np.asarray(device), rtol=1e-15)
    np.testing.assert_allclose(host, 20.0 * np.tanh(v / 1e-3) + 50.0 * v, rtol=1e-15)  # Table 1's Fc, b, v_c
    assert np.all(host * v >= 0) and host[2] == 0.0
    np.testing.assert_array_equal(slider_friction(friction, -v), -host)


def test_at_constant_speed_the_drives_pay_the_friction_law_in_torque():
    """The MJX machine in PID + feedforward mode moves its platform at constant velocity (40 mm/s down, 20 mm/s along
    x, after a 0.1 s ramp: sliders at 36-45 mm/s), 0.8 s in all, vmapped over three drive trains: no friction, Table 1's
    and a different (coulomb, viscous) on each axis.  Over the last 0.1 s (the loops' transients from the ramp
    decayed), the motor forces at the sliders, ``eta tau / r`` [N], exceed the frictionless run's by the law at the
    slider speeds, ``coulomb tanh(v / v_coulomb) + viscous v``, as generalized forces on the platform's coordinates
    (``J^T F``, ``J = ds/dq``): six drives on five coordinates share the extra load with an internal force of their
    own (observed 0.6 N per branch with the varied friction), which ``J^T`` removes.  Bound 1 % of the largest
    component; observed 8e-4 (Table 1) and 7e-4 (varied).  The rest is inertia: the runs' sliders still differ by
    about 4e-4 m/s in speed, as their position errors (0.2 and 0.04 mm) decay.
    """
    n, ramp, speed = 800, 0.1, 0.04  # position periods (0.8 s), s, m/s down
    t = np.arange(n) * RATES.dt_position
    travel = np.where(t < ramp, speed * (t - ramp / np.pi * np.sin(np.pi * t / ramp)) / 2, speed * (t - ramp / 2))
    path = np.tile(np.asarray(G.home, dtype=float), (n, 1))
    path[:, 2] -= travel
    path[:, 0] += 0.5 * travel
    ref = machine_reference(SERVO, path, "pid_ff", rates=RATES)
    varied = SERVO.replace(
        coulomb=np.array([10.0, 15.0, 20.0, 25.0, 30.0, 35.0]),
        viscous=np.array([200.0, 0.0, 100.0, 50.0, 300.0, 150.0]),
    )
    servos = [SERVO.replace(coulomb=np.zeros(6), viscous=np.zeros(6)), SERVO, varied]
    run = jax.jit(jax.vmap(lambda servo: rollout(servo, None, ref, plant=PLANT, rates=RATES, outer="pid_ff")))
    trace = run(stack(servos))
    r, eta = np.asarray(SERVO.lead) / (2 * np.pi), np.asarray(SERVO.eta)
    force = np.asarray(trace.torque)[:, -100:] * eta / r  # N, at the sliders
    v = np.asarray(trace.velocity)[:, -100:]
    assert np.all((-0.046 < v) & (v < -0.035))
    J = np.asarray(jax.jit(jax.vmap(jax.jacfwd(lambda q: K.inverse_kinematics(G, q))))(jnp.asarray(path[-100:])))
    for k in (1, 2):
        law = np.einsum("nij,ni->j", J, np.asarray(slider_friction(Friction.of(servos[k]), v[k]))) / len(v[k])
        extra = np.einsum("nij,ni->j", J, force[k] - force[0]) / len(v[k])
        np.testing.assert_allclose(extra, law, atol=1e-2 * np.abs(law).max())


def test_the_reversal_error_is_the_largest_error_just_after_each_reversal_of_the_reference():
    """Branch 1's reference reverses once at sample 250 (a cosine through its turning point), branch 2's stops and goes
    back after a dwell, branch 3's never reverses: an error spike 20 ms after a reversal is the glitch, a larger one
    before the reversal or beyond the window is not, and branch 3 has none."""
    from pusupu_jax.machine import REVERSAL_WINDOW_S, reversal_error

    dt, n = 1e-3, 1000
    t = np.arange(n) * dt
    s_ref = np.zeros((n, 6))
    s_ref[:, 0] = np.cos(2 * np.pi * (t - 0.25) / 1.0)  # maximum at 0.25 s: the speed turns there
    s_ref[:, 1] = np.concatenate([np.linspace(0, 1, 400), np.ones(200), np.linspace(1, 0.5, 400)])
    s_ref[:, 2:] = t[:, None]
    e = np.full((n, 6), 1e-6)
    e[100, 0], e[270, 0], e[250 + int(REVERSAL_WINDOW_S / dt) + 5, 0] = 5e-3, 2e-3, 9e-3
    e[610, 1] = 3e-3  # 10 ms after branch 2 starts back
    out = reversal_error(e, s_ref, dt)
    assert out[0] == pytest.approx(2e-3) and out[1] == pytest.approx(3e-3)
    assert out[2:] == [None] * 4
