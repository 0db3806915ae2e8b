"""Platform paths of the paper: geometry, timing limits, and clear errors."""

import numpy as np
import pytest

from pusupu_jax import LoopRates, ParameterError
from pusupu_jax.plant.geometry import Geometry
from pusupu_jax.trajectories import platform_path

HOME = Geometry.default().home
DT = LoopRates().dt_position


@pytest.mark.parametrize("kind", ["arc", "p2p"])
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


@pytest.mark.parametrize("kwargs,message", [(dict(kind="circle"), "expected one of"),
                                            (dict(kind="arc", v_max=0), "v_max: expected a positive"),
                                            (dict(kind="arc", a_max=np.nan), "a_max: expected a positive"),
                                            (dict(kind="p2p", hold=-1), "hold: expected a non-negative")])
def test_bad_path_settings(kwargs, message):
    with pytest.raises(ParameterError, match=message):
        platform_path(home=HOME, **kwargs)
