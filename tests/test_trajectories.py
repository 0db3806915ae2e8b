"""Named platform paths (the paper's, the ISO 230-4 circle, the tilt sweep, the excitation path): geometry, timing
limits, clear errors."""

import numpy as np
import pytest

import inspect

import jax.numpy as jnp

from pusupu_jax import LoopRates, ParameterError, ServoParams, machine_fit
from pusupu_jax.paths import check_path
from pusupu_jax.plant import kinematics
from pusupu_jax.plant.geometry import Geometry
from pusupu_jax.trajectories import TILT_SPEED, platform_path

HOME = Geometry.default().home
DT = LoopRates().dt_position


@pytest.mark.parametrize("kind", ["arc", "p2p", "circle"])
def test_paths_start_and_end_at_rest_within_the_limits(kind):
    v_max, a_max = 0.05, 0.2
    q = platform_path(kind, HOME, v_max=v_max, a_max=a_max)
    np.testing.assert_allclose(q[0], HOME, atol=1e-15)
    xy = q[:, :2]
    v = np.linalg.norm(np.diff(xy, axis=0), axis=1) / DT
    a = np.abs(np.diff(v)) / DT
    assert v.max() <= v_max * 1.001 and v.max() > 0.9 * v_max  # the limit is used, not exceeded
    assert a.max() <= a_max * 1.01
    assert v[:3].max() < 1e-3 and v[-3:].max() == 0.0  # starts and ends at rest
    np.testing.assert_array_equal(q[:, 2:], np.broadcast_to(HOME[2:], q[:, 2:].shape))  # level, constant height


def test_arc_is_a_major_arc_of_200_mm_about_home():
    q = platform_path("arc", HOME)
    xy = q[:, :2]
    on_arc = np.abs(np.linalg.norm(xy, axis=1) - 0.2) < 1e-12
    angles = np.unwrap(np.arctan2(xy[on_arc, 1], xy[on_arc, 0]))
    assert angles.max() - angles.min() == pytest.approx(1.5 * np.pi, abs=1e-9)


def test_p2p_visits_the_papers_points():
    xy = platform_path("p2p", HOME)[:, :2]
    for point in ([0, 0], [-0.1, -0.1], [0.1, 0.1]):
        assert np.min(np.linalg.norm(xy - point, axis=1)) < 1e-12


@pytest.mark.parametrize(
    "kwargs,message",
    [
        (dict(kind="square"), "expected one of"),
        (dict(kind="arc", v_max=0), "v_max: expected a positive"),
        (dict(kind="arc", a_max=np.nan), "a_max: expected a positive"),
        (dict(kind="p2p", hold=-1), "hold: expected a non-negative"),
    ],
)
def test_bad_path_settings(kwargs, message):
    with pytest.raises(ParameterError, match=message):
        platform_path(home=HOME, **kwargs)


def test_circle_is_the_iso_230_4_test_both_ways_at_the_feed():
    """From home out to 100 mm, a full 360 deg counterclockwise at 50 mm/s, the same clockwise, back to home."""
    q = platform_path("circle", HOME)
    xy = q[:, :2]
    assert np.linalg.norm(xy[0]) == 0 and np.linalg.norm(xy[-1]) == 0
    radius = np.linalg.norm(xy, axis=1)
    on = np.flatnonzero(np.abs(radius - 0.1) < 1e-12)
    assert np.all(np.diff(on) == 1)  # one stretch on the circle: out along a radius, around twice, back
    turn = np.unwrap(np.arctan2(xy[on, 1], xy[on, 0]))
    top = int(np.argmax(turn))
    assert np.all(np.diff(turn[: top + 1]) >= 0) and np.all(np.diff(turn[top:]) <= 0)  # counterclockwise, then back
    speed = np.linalg.norm(np.diff(xy[on], axis=0), axis=1) / DT
    for half in (slice(0, top), slice(top, None)):
        cruising = np.abs(speed[half] - 0.05) < 1e-9
        assert np.sum(cruising) * DT * 0.05 == pytest.approx(2 * np.pi * 0.1, abs=0.05 * DT)  # 360 deg at the feed
        assert np.all(np.diff(np.flatnonzero(cruising)) == 1)  # in one go, the ramps outside it
    assert turn[top] - turn[0] > 2 * np.pi


def test_tilt_sweep_tilts_a_then_b_then_both_at_the_angular_limit():
    q = platform_path("tilt", HOME)
    np.testing.assert_array_equal(q[:, :3], np.broadcast_to(HOME[:3], q[:, :3].shape))  # the centre stays at home
    a, b = q[:, 3], q[:, 4]
    first_b, first_both = int(np.argmax(b != 0)), int(np.argmax((a != 0) & (b != 0)))
    assert 0 < first_b < first_both
    assert np.all(b[:first_b] == 0) and np.all(a[first_b:first_both] == 0) and np.all(a[first_both:] == b[first_both:])
    for part in (a[:first_b], b[first_b:first_both], a[first_both:]):
        assert part.max() == pytest.approx(0.1) and part.min() == pytest.approx(-0.1)
    rate = np.linalg.norm(np.diff(q[:, 3:], axis=0), axis=1) / DT
    assert TILT_SPEED * 0.99 < rate.max() <= TILT_SPEED * 1.001
    assert np.all(q[-1] == HOME)


def test_the_excitation_path_reverses_every_slider_fast_and_tilts_both_ways_within_the_drives():
    """What identification needs from one log (``pusupu_jax.trajectories.excitation``): every slider reverses at
    least three times and reaches 0.1 m/s both ways (Coulomb against viscous friction), accelerates at 1.9 m/s^2 or
    more (the rotors' inertia), the platform moves up and down and tilts both ways about a and b (the payload's mass
    and its centre of mass's height), the drives' limits hold with a quarter of ``V_max/Ke`` to spare
    (``check_path``), and the motion ends inside the fit's default window."""
    servo = ServoParams.table1()
    q = platform_path("excite", HOME)
    report = check_path(q, servo, DT)  # raises where a limit is exceeded
    assert max(report["motor_speed_peak_rad_s"]) < 0.75 * servo.V_max[0] / servo.Ke[0]
    s = np.asarray(kinematics.inverse_kinematics(Geometry.default(), jnp.asarray(q)))
    v = np.gradient(s, DT, axis=0)
    a = np.gradient(v, DT, axis=0)
    for i in range(6):
        moving = v[:, i][np.abs(v[:, i]) > 1e-3]
        assert np.sum(np.diff(np.sign(moving)) != 0) >= 3, i
        assert v[:, i].max() > 0.1 and v[:, i].min() < -0.1, i
        assert np.abs(a[:, i]).max() > 1.9, i
    offsets = q - HOME
    for j in (2, 3, 4):  # z, a, b: both ways
        assert offsets[:, j].max() > 0.5 * np.abs(offsets[:, j]).max() and offsets[:, j].min() < 0
    last_move = np.flatnonzero(np.abs(np.diff(q, axis=0)).max(axis=1) > 0).max() + 1
    assert last_move * DT <= inspect.signature(machine_fit.fit).parameters["window_s"].default
    assert np.all(q[-1] == HOME)
