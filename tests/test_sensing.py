"""What the drives read of the machine: a drive that counts its encoder's counts for its speed
(``rollout(counted_speed=True)``, identify's replay of a machine with ``encoder_counts``)."""

import jax
import numpy as np

from pusupu_jax import LoopRates, cascade, loops, rollout


def test_a_drive_that_counts_its_speed_closes_its_velocity_loop_on_the_mean_of_the_last_period(
    table1_linear, linear_load
):
    """``counted_speed``: at each velocity tick the drives' speed is the motor angle's change over the last velocity
    period, over that period; a drive at rest has counted nothing at the first tick.  Velocity mode on the single-axis
    plant stepped at every current tick (five steps a velocity period), a speed step and then a rich input: each
    period's current reference is the velocity PI's answer, from the state the period started in, to that mean speed
    (to 1e-12 A); without counting, to the speed at the tick.  The two speeds differ by up to 0.06 rad/s while the
    motor accelerates, which moves the PI's answer by far more than the tolerance: the check tells them apart."""
    rates = LoopRates(n_mech=1)
    n = 200
    u = np.full(n, 10.0)  # rad/s
    u[0] = 0.0
    u[100:] += 3.0 * np.random.default_rng(1).standard_normal(n - 100)
    reference = np.repeat(u[:, None], 6, axis=1)
    drive = loops.discretize(table1_linear, rates)
    vmode = cascade.control_mode("velocity")
    tick = jax.jit(jax.vmap(lambda s, w, o: cascade.velocity_tick(drive, vmode, s, w, o)[1]))
    for counted in (True, False):
        trace = rollout(table1_linear, linear_load, reference, rates=rates, outer="velocity", counted_speed=counted)
        theta, omega = np.asarray(trace.theta), np.asarray(trace.omega)
        speed = np.diff(theta, axis=0, prepend=theta[:1]) / rates.dt_velocity if counted else omega
        i_ref = np.asarray(tick(trace.state, reference, speed))
        np.testing.assert_allclose(np.asarray(trace.current_reference)[:, 0], i_ref, rtol=0, atol=1e-12)
        if counted:  # the mean speed is not the speed at the tick: the check tells them apart
            assert np.abs(speed - omega).max() > 1e-3  # rad/s (0.06 measured): a billion times the check's tolerance
