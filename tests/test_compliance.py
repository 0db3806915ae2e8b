"""The admittance outer loop (pusupu_jax.compliance): its discretisation against python-control, and its checks (the
compliant rollout with nothing touching is checked in tests/test_contact_experiments.py, beside the peg run)."""

import control as ct
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from pusupu_jax import ServoParams
from pusupu_jax import compliance as C
from pusupu_jax.machine import Scenario, simulate_scenarios
from pusupu_jax.params import ParameterError
from pusupu_jax.plant.geometry import Geometry
from pusupu_jax.plant.model import ModelOptions

GAINS = C.AdmittanceGains(mass=np.full(3, 20.0), damping=np.full(3, 8000.0), stiffness=np.array([0.0, 0.0, 2e4]))


def _step_response(gains, force, dt, seconds):
    """The offsets [m] after each period under a constant contact force ``force`` [N] from rest, ``(N, 3)``."""

    def body(state, _):
        state = C.step(gains, state, jnp.asarray(force), jnp.zeros(3), dt)
        return state, state.offset

    return np.asarray(jax.lax.scan(body, C.init(), None, length=int(round(seconds / dt)))[1])


def test_the_admittance_converges_to_python_controls_mass_damper_spring():
    """A 10 N step on z (M 20 kg, D 8 kN s/m, K 20 kN/m): the offsets against python-control's continuous response of
    ``1 / (M s^2 + D s + K)`` over 1 s.  Semi-implicit Euler is first order: at 1 ms the largest error was 0.24 %
    of the final 0.5 mm, and halving the step halves it (ratios 2.003 and 2.002 observed down to 0.25 ms).
    Bounds: 1 % at 1 ms, ratio 1.8-2.2.
    """
    errors = []
    for dt in (1e-3, 5e-4):
        x = _step_response(GAINS, [0.0, 0.0, 10.0], dt, 1.0)[:, 2]
        t = np.arange(1, len(x) + 1) * dt
        _, y = ct.forced_response(
            ct.tf([1.0], [20.0, 8000.0, 2e4]), T=np.concatenate([[0.0], t]), U=np.full(len(t) + 1, 10.0)
        )
        errors.append(float(np.max(np.abs(x - np.asarray(y)[1:]))) / 5e-4)
    assert errors[0] < 0.01, errors
    assert 1.8 < errors[0] / errors[1] < 2.2, errors


def test_selection_and_clamp():
    """An axis out of the selection never moves; a force controller (K = 0) stops at the clamp without winding up."""
    gains = GAINS.replace(selection=np.array([0.0, 1.0, 1.0]), max_offset=0.001)
    x = _step_response(gains, [50.0, 50.0, 0.0], 1e-3, 2.0)
    assert np.all(x[:, 0] == 0.0)
    assert x[-1, 1] == pytest.approx(0.001)  # the y damper would run on forever: clamped at 1 mm
    back = C.step(
        gains, C.AdmittanceState(jnp.asarray(x[-1]), jnp.zeros(3)), jnp.asarray([0.0, -50.0, 0.0]), jnp.zeros(3), 1e-3
    )
    assert float(back.offset[1]) < 0.001  # and leaves it as soon as the force turns


@pytest.mark.parametrize(
    "change, message",
    [
        (dict(mass=np.array([20.0, -1.0, 20.0])), "mass > 0"),
        (dict(damping=np.full(3, np.nan)), "admittance.damping: expected one finite number or three"),
        (dict(max_offset=0.0), "admittance.max_offset: expected a positive offset"),
        (dict(mass=np.full(3, 1.0)), "dt D/M < 1"),
    ],
)
def test_bad_admittance_gains_are_named(change, message):
    with pytest.raises(ParameterError, match=message):
        C.validate_gains(GAINS.replace(**change), 1e-3)


@pytest.mark.parametrize(
    "change, message",
    [
        (dict(scene="wavy"), "ModelOptions.scene: expected one of"),
        (dict(cone="round"), "ModelOptions.cone: expected one of"),
        (dict(friction=-0.1), "ModelOptions.friction: expected a finite number >= 0"),
        (dict(hole_offset=(0.001,)), "ModelOptions.hole_offset: expected"),
    ],
)
def test_bad_contact_options_are_named(change, message):
    from pusupu_jax.plant.model import build_model

    with pytest.raises(ValueError, match=message):
        build_model(None, ModelOptions(contacts=True, **change))


def test_a_force_setpoint_of_the_wrong_shape_is_named():
    options = ModelOptions(contacts=True, solver_iterations=4, cone="elliptic")
    path = np.repeat(np.asarray(Geometry.default().home)[None], 10, axis=0)
    with pytest.raises(ValueError, match=r"force_setpoint: expected finite forces \[N\] of shape \(3,\) or \(10, 3\)"):
        simulate_scenarios(
            ServoParams.table1(),
            [Scenario(path, options)],
            mode="imc",
            compliance=GAINS,
            force_setpoint=np.zeros((5, 3)),
        )
