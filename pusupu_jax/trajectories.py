"""Reference trajectories for the single-axis plant: slider positions [m] at the position-loop rate.

Every trajectory starts at rest at zero, where the simulated machine starts.
"""

from __future__ import annotations

import numpy as np

from . import workload
from .params import N_AXES, LoopRates, ParameterError

AXIS_TRAJECTORIES = ("step", "ramp", "sine")


def axis_reference(kind: str, rates: LoopRates = LoopRates(), duration: float | None = None) -> np.ndarray:
    """Slider reference of shape ``(N, 6)`` [m], ``N = duration / rates.dt_position``; a duration of more work than
    :func:`pusupu_jax.workload.check_run` allows is refused.

    * ``step``: 5 mm step at t = 0 (default 2 s);
    * ``ramp``: 50 mm/s from t = 0.1 s (default 1 s);
    * ``sine``: 10 mm amplitude, 1 Hz, ``10 mm * sin(2 pi t)`` (default 2 s).
    """
    if kind not in AXIS_TRAJECTORIES:
        raise ParameterError(f"trajectory: expected one of {AXIS_TRAJECTORIES}, got {kind!r}")
    duration = {"step": 2.0, "ramp": 1.0, "sine": 2.0}[kind] if duration is None else duration
    if not (np.isfinite(duration) and duration > 0):
        raise ParameterError(f"trajectory duration: expected a positive number of seconds, got {duration!r}")
    workload.check_run("trajectory duration", duration, rates)
    t = np.arange(max(1, int(round(duration / rates.dt_position)))) * rates.dt_position
    if kind == "step":
        x = np.full_like(t, 0.005)
    elif kind == "ramp":
        x = 0.05 * np.clip(t - 0.1, 0.0, None)
    else:
        x = 0.01 * np.sin(2 * np.pi * t)
    return np.repeat(x[:, None], N_AXES, axis=1)


PLATFORM_TRAJECTORIES = ("arc", "p2p")


def _quintic(dt, length, v_max, a_max):
    """Quintic time scaling 0 -> 1 whose peak speed (1.875 L/T) and acceleration (5.77 L/T^2) stay within limits."""
    T = max(1.875 * length / v_max, (5.7735 * length / a_max) ** 0.5, dt)
    n = max(2, int(np.ceil(T / dt)) + 1)
    tau = np.clip(np.arange(n) * dt / T, 0.0, 1.0)
    return 10 * tau**3 - 15 * tau**4 + 6 * tau**5


def _line(a, b, dt, v_max, a_max):
    """Points from ``a`` to ``b`` with quintic timing (peak speed ``v_max`` [m/s], acceleration ``a_max`` [m/s^2])."""
    a, b = np.asarray(a, dtype=float), np.asarray(b, dtype=float)
    return a + _quintic(dt, float(np.linalg.norm(b - a)), v_max, a_max)[:, None] * (b - a)


def _check_limits(v_max, a_max, hold):
    for name, v in (("v_max", v_max), ("a_max", a_max)):
        if not (np.isfinite(v) and v > 0):
            raise ParameterError(f"trajectory {name}: expected a positive number, got {v!r}")
    if not (np.isfinite(hold) and hold >= 0):
        raise ParameterError(f"trajectory hold: expected a non-negative number of seconds, got {hold!r}")


def _poses(home, offsets, dt, hold):
    """Level platform poses ``(N, 5)``: ``home`` plus position ``offsets`` ``(N, k <= 3)``, then ``hold`` [s] at rest."""
    offsets = np.concatenate([offsets, np.repeat(offsets[-1:], int(round(hold / dt)), axis=0)])
    q = np.repeat(np.asarray(home, dtype=float)[None], len(offsets), axis=0)
    q[:, :offsets.shape[1]] += offsets
    return q


def platform_path(kind: str, home, rates: LoopRates = LoopRates(), v_max: float = 0.05, a_max: float = 0.2,
                  hold: float = 0.5) -> np.ndarray:
    """Platform poses ``(N, 5)`` at the position-loop rate for the paper's paths, starting and ending at rest.

    * ``arc``: from home straight out to (200, 0, 0) mm, then a 270 deg major arc of 200 mm
      radius about home in the horizontal plane (Fig. 7);
    * ``p2p``: (0,0,0) -> (-100,-100,0) -> (100,100,0) mm (section 4).

    Offsets are from ``home`` (x, y, z [m], a, b [rad]); the platform stays level.  Each
    segment has quintic timing with peak speed ``v_max`` [m/s] and acceleration ``a_max``
    [m/s^2] along the path; ``hold`` [s] at rest is appended.
    """
    if kind not in PLATFORM_TRAJECTORIES:
        raise ParameterError(f"trajectory: expected one of {PLATFORM_TRAJECTORIES} for the mechanism, got {kind!r}")
    _check_limits(v_max, a_max, hold)
    dt = rates.dt_position
    if kind == "arc":
        phi = 1.5 * np.pi * _quintic(dt, 0.2 * 1.5 * np.pi, v_max, a_max)
        xy = [_line([0.0, 0.0], [0.2, 0.0], dt, v_max, a_max), np.stack([0.2 * np.cos(phi), 0.2 * np.sin(phi)], axis=1)]
        return _poses(home, np.concatenate(xy), dt, hold)
    return platform_waypoints(home, [[0.0, 0.0, 0.0], [-0.1, -0.1, 0.0], [0.1, 0.1, 0.0]], rates, v_max, a_max, hold)


def path_seconds(kind: str) -> float:
    """The duration [s] of :func:`platform_path` ``kind`` (its timing does not depend on the rate it is sampled at),
    known before a path is built at a rate that would make it too long to hold."""
    return len(platform_path(kind, np.zeros(5))) * LoopRates().dt_position


def platform_waypoints(home, waypoints, rates: LoopRates = LoopRates(), v_max=0.05, a_max: float = 0.2,
                       hold: float = 0.5) -> np.ndarray:
    """Level platform poses ``(N, 5)`` through position ``waypoints`` ``(K, 3)`` [m] from ``home``, straight
    segments with :func:`platform_path`'s quintic timing (at rest at every waypoint), then ``hold`` [s] at rest.

    ``v_max`` [m/s]: one peak speed, or one per segment (``K - 1``).  The machine starts at home,
    so the first waypoint should be ``(0, 0, 0)``.
    """
    points = np.asarray(waypoints, dtype=float)
    if points.ndim != 2 or points.shape[1] != 3 or len(points) < 2 or not np.isfinite(points).all():
        raise ParameterError(f"waypoints: expected at least two finite (x, y, z) offsets [m], got shape {points.shape}")
    speeds = np.broadcast_to(np.asarray(v_max, dtype=float), (len(points) - 1,))
    for v in speeds:
        _check_limits(v, a_max, hold)
    dt = rates.dt_position
    return _poses(home, np.concatenate([_line(a, b, dt, v, a_max) for a, b, v in zip(points[:-1], points[1:], speeds)]),
                  dt, hold)
