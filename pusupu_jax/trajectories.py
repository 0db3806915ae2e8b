"""Reference trajectories for the single-axis plant: slider positions [m] at the position-loop rate.

Every trajectory starts at rest at zero, where the simulated machine starts.
"""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

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


PLATFORM_TRAJECTORIES = ("arc", "p2p", "circle", "tilt", "excite")
SPEED, ACCELERATION = 0.05, 0.2  # m/s, m/s^2: the paths' peak speed and acceleration along the path, by default
CIRCLE_RADIUS = 0.1  # m, the ISO 230-4 circle's
TILT_AMPLITUDE = 0.1  # rad, the tilt sweep's
# rad/s and rad/s^2: tilting at these rates moves the spherical joints (320 mm from the platform centre on the
# default machine) about as fast as the translations' defaults, 0.05 m/s and 0.2 m/s^2
TILT_SPEED, TILT_ACCELERATION = 0.15, 0.6
# The excitation path's poses (offsets from home: x, y, z [m], a, b [rad]) and each move's peak acceleration along
# the path [m/s^2] (the tilts' 4 rad/s^2 per m/s^2); the speed caps, 0.3 m/s and 1.5 rad/s, are above what these
# short moves reach
EXCITATION_WAYPOINTS = (
    (0.0, 0.0, 0.0, 0.0, 0.0),
    (0.0, 0.0, 0.009, 0.0, 0.0),
    (0.017, 0.0, -0.009, 0.038, 0.0),
    (-0.017, 0.0, 0.0, -0.038, 0.0),
    (0.0, 0.017, 0.009, 0.0, -0.038),
    (0.0, -0.017, -0.009, 0.0, 0.038),
    (0.0136, 0.0136, 0.0, 0.038, 0.038),
    (0.0, 0.0, 0.0, 0.0, 0.0),
)
EXCITATION_ACCELERATION = (2.0, 1.7, 2.0, 1.7, 2.0, 1.7, 2.0)  # m/s^2
EXCITATION_SPEED, EXCITATION_TILT_SPEED = 0.3, 1.5  # m/s, rad/s


def _quintic_time(length: float, v_max: float, a_max: float) -> float:
    """The shortest duration [s] of a quintic move over ``length`` whose peak speed (1.875 L/T) and acceleration
    (5.77 L/T^2) stay within ``v_max`` and ``a_max`` (lengths in m with m/s and m/s^2, or in rad with rad/s and
    rad/s^2)."""
    by_acceleration: float = (5.7735 * length / a_max) ** 0.5
    return max(1.875 * length / v_max, by_acceleration)


def _quintic(dt: float, T: float) -> npt.NDArray[np.float64]:
    """Quintic time scaling ``10 u^3 - 15 u^4 + 6 u^5``, ``u = t / T``: 0 -> 1 over ``T`` [s] (at least one period
    ``dt``), sampled every ``dt``, at rest at both ends."""
    T = max(T, dt)
    n = max(2, int(np.ceil(T / dt)) + 1)
    tau: npt.NDArray[np.float64] = np.clip(np.arange(n) * dt / T, 0.0, 1.0)
    return 10 * tau**3 - 15 * tau**4 + 6 * tau**5


def _line(a: npt.ArrayLike, b: npt.ArrayLike, dt: float, T: float) -> npt.NDArray[np.float64]:
    """Points from ``a`` to ``b`` (offsets) in ``T`` [s] with :func:`_quintic` timing."""
    a, b = np.asarray(a, dtype=float), np.asarray(b, dtype=float)
    points: npt.NDArray[np.float64] = a + _quintic(dt, T)[:, None] * (b - a)
    return points


def _cruise(dt: float, length: float, v: float, a_max: float) -> npt.NDArray[np.float64]:
    """Distance [m] ``(n,)`` along a move sampled every ``dt``: the speed rises from rest to ``v`` [m/s] along
    :func:`_quintic`'s polynomial (peak acceleration ``a_max`` [m/s^2], over ``Ta = 1.875 v / a_max``), covers
    ``length`` [m] at ``v``, and falls back to rest the same way; each ramp adds ``v Ta / 2`` to ``length``."""
    ramp_time = 1.875 * v / a_max
    T = 2 * ramp_time + length / v

    # the distance from rest after ``time``: v Ta (2.5 u^4 - 3 u^5 + u^6) on the ramp, then at v
    def ramped(time: npt.NDArray[np.float64] | float) -> npt.NDArray[np.float64] | np.float64:
        u: npt.NDArray[np.float64] | np.float64 = np.clip(time / ramp_time, 0.0, 1.0)
        return v * ramp_time * (2.5 * u**4 - 3 * u**5 + u**6) + v * np.maximum(time - ramp_time, 0.0)

    t = np.minimum(np.arange(int(np.ceil(T / dt)) + 1) * dt, T)
    return np.where(t < T / 2, ramped(t), 2 * ramped(T / 2) - ramped(T - t))  # the second half mirrors the first


def segment_seconds(
    waypoints: npt.ArrayLike,
    v_max: npt.ArrayLike,
    a_max: npt.ArrayLike,
    w_max: npt.ArrayLike = TILT_SPEED,
    alpha_max: npt.ArrayLike = TILT_ACCELERATION,
) -> np.ndarray:
    """The durations [s] ``(K - 1,)`` of the straight segments through ``waypoints`` ``(K, 3)`` or ``(K, 5)`` (x, y,
    z [m], then a, b [rad]) with quintic timing: each the longest of what its translation needs under ``v_max``
    [m/s] and ``a_max`` [m/s^2] and what its tilts need under ``w_max`` [rad/s] and ``alpha_max`` [rad/s^2] (each
    one value or one per segment)."""
    steps = np.diff(np.asarray(waypoints, dtype=float), axis=0)
    limits = np.broadcast_arrays(
        *(np.asarray(v, dtype=float) for v in (v_max, a_max, w_max, alpha_max)), np.zeros(len(steps))
    )[:4]
    return np.array(
        [
            max(
                _quintic_time(float(np.linalg.norm(d[:3])), v, a), _quintic_time(float(np.linalg.norm(d[3:])), w, alpha)
            )
            for d, v, a, w, alpha in zip(steps, *limits)
        ]
    )


def _check_limits(positive: dict[str, float], nonnegative: dict[str, float]) -> None:
    for name, v in positive.items():
        if not (np.isfinite(v) and v > 0):
            raise ParameterError(f"trajectory {name}: expected a positive number, got {v!r}")
    for name, v in nonnegative.items():
        if not (np.isfinite(v) and v >= 0):
            raise ParameterError(f"trajectory {name}: expected a non-negative number of seconds, got {v!r}")


def _poses(home: npt.ArrayLike, offsets: npt.NDArray[np.float64], dt: float, hold: float) -> npt.NDArray[np.float64]:
    """Platform poses ``(N, 5)``: ``home`` plus ``offsets`` ``(N, k)`` (the first ``k`` of x, y, z [m], a, b
    [rad]; the others stay at home), then ``hold`` [s] at rest."""
    offsets = np.concatenate([offsets, np.repeat(offsets[-1:], int(round(hold / dt)), axis=0)])
    q = np.repeat(np.asarray(home, dtype=float)[None], len(offsets), axis=0)
    q[:, : offsets.shape[1]] += offsets
    return q


def platform_path(
    kind: str,
    home: npt.ArrayLike,
    rates: LoopRates = LoopRates(),
    v_max: float = SPEED,
    a_max: float = ACCELERATION,
    hold: float = 0.5,
) -> np.ndarray:
    """Platform poses ``(N, 5)`` at the position-loop rate for the named paths, starting and ending at rest.

    * ``arc``: from home straight out to (200, 0, 0) mm, then a 270 deg major arc of 200 mm
      radius about home in the horizontal plane (Fig. 7);
    * ``p2p``: (0,0,0) -> (-100,-100,0) -> (100,100,0) mm (section 4);
    * ``circle``: the circular test of ISO 230-4 (:func:`iso_circle`): a circle of
      :data:`CIRCLE_RADIUS` about home in the horizontal plane at the feed ``v_max``, counterclockwise
      then clockwise, approached from the centre;
    * ``tilt``: a tilt sweep (:func:`tilt_sweep`) of :data:`TILT_AMPLITUDE` about a, then b, then both,
      at :data:`TILT_SPEED` and :data:`TILT_ACCELERATION`;
    * ``excite``: the excitation path for identification (:func:`excitation`), its own limits.

    Offsets are from ``home`` (x, y, z [m], a, b [rad]); the platform stays level but in ``tilt`` and ``excite``.
    Straight segments have quintic timing with peak speed ``v_max`` [m/s] and acceleration
    ``a_max`` [m/s^2] along the path; ``hold`` [s] at rest is appended.
    """
    if kind not in PLATFORM_TRAJECTORIES:
        raise ParameterError(f"trajectory: expected one of {PLATFORM_TRAJECTORIES} for the mechanism, got {kind!r}")
    _check_limits({"v_max": v_max, "a_max": a_max}, {"hold": hold})
    dt = rates.dt_position
    if kind == "arc":
        phi = 1.5 * np.pi * _quintic(dt, _quintic_time(0.2 * 1.5 * np.pi, v_max, a_max))
        xy = [
            _line([0.0, 0.0], [0.2, 0.0], dt, segment_seconds([[0.0, 0.0], [0.2, 0.0]], v_max, a_max)[0]),
            np.stack([0.2 * np.cos(phi), 0.2 * np.sin(phi)], axis=1),
        ]
        return _poses(home, np.concatenate(xy), dt, hold)
    if kind == "circle":
        return iso_circle(home, rates, CIRCLE_RADIUS, v_max, a_max, hold)
    if kind == "tilt":
        return tilt_sweep(home, rates, TILT_AMPLITUDE, hold=hold)
    if kind == "excite":
        return excitation(home, rates, hold)
    return platform_waypoints(home, [[0.0, 0.0, 0.0], [-0.1, -0.1, 0.0], [0.1, 0.1, 0.0]], rates, v_max, a_max, hold)


def iso_circle(
    home: npt.ArrayLike,
    rates: LoopRates = LoopRates(),
    radius: float = CIRCLE_RADIUS,
    feed: float = SPEED,
    a_max: float = ACCELERATION,
    hold: float = 0.5,
) -> np.ndarray:
    """The circular test of ISO 230-4 as platform poses ``(N, 5)``: a circle of ``radius`` [m] about home in the
    horizontal plane, contoured at ``feed`` [m/s] in both directions, the platform level.

    ISO 230-4 contours the circle counterclockwise and clockwise (its bidirectional circular
    deviation compares the two), each direction over the full 360 deg at the programmed feed,
    with arcs of overshoot where the feed builds up and dies down outside the 360 deg.  Here: from
    home straight out to (``radius``, 0, 0) (quintic, ``feed`` and ``a_max`` [m/s^2]); a
    counterclockwise pass whose feed rises from rest along the quintic smoothstep (peak
    acceleration ``a_max`` along the path), holds ``feed`` over a full 360 deg, and falls back to
    rest (the ramps' arcs, ``1.875 feed^2 / (2 a_max)`` long each, 6.7 deg at the defaults, lie
    before and after it); the same pass clockwise back to (``radius``, 0, 0); straight back to home;
    ``hold`` [s] at rest.  The standard's evaluation of the measured circle (its circular and
    radial deviations) is not computed: the machine's metrics are the tracking errors.
    """
    _check_limits({"radius": radius, "v_max": feed, "a_max": a_max}, {"hold": hold})
    dt = rates.dt_position
    phi = _cruise(dt, 2 * np.pi * radius, feed, a_max) / radius
    ccw = np.stack([radius * np.cos(phi), radius * np.sin(phi)], axis=1)
    out = _line([0.0, 0.0], [radius, 0.0], dt, segment_seconds([[0.0, 0.0], [radius, 0.0]], feed, a_max)[0])
    offsets = [out, ccw, ccw[::-1], out[::-1]]  # clockwise and back to home: the same moves, time reversed
    return _poses(home, np.concatenate(offsets), dt, hold)


def tilt_sweep(
    home: npt.ArrayLike,
    rates: LoopRates = LoopRates(),
    amplitude: float = TILT_AMPLITUDE,
    w_max: float = TILT_SPEED,
    alpha_max: float = TILT_ACCELERATION,
    hold: float = 0.5,
) -> np.ndarray:
    """A tilt sweep as platform poses ``(N, 5)``, the platform centre at home: tilt ``a`` to ``+amplitude``, to
    ``-amplitude`` and back to level [rad], then ``b`` the same way, then both together (``a = b``); each move
    straight with quintic timing under ``w_max`` [rad/s] and ``alpha_max`` [rad/s^2], at rest between moves, then
    ``hold`` [s] at rest."""
    _check_limits({"amplitude": amplitude}, {})
    tilts = amplitude * np.array([[0, 0], [1, 0], [-1, 0], [0, 0], [0, 1], [0, -1], [0, 0], [1, 1], [-1, -1], [0, 0]])
    points = np.concatenate([np.zeros((len(tilts), 3)), tilts], axis=1)
    return platform_waypoints(home, points, rates, hold=hold, w_max=w_max, alpha_max=alpha_max)


def excitation(home: npt.ArrayLike, rates: LoopRates = LoopRates(), hold: float = 0.5) -> np.ndarray:
    """The excitation path for identification (``pusupu identify``) as platform poses ``(N, 5)``: 2 s of moves that
    excite the drive trains' friction, the rotors' inertia and torque constants, and the payload's mass and centre of
    mass, then ``hold`` [s] at rest.

    Seven straight moves through :data:`EXCITATION_WAYPOINTS`, each mixing a translation of 9-37 mm with a tilt of
    up to 0.076 rad, at rest at every waypoint (quintic timing, peak accelerations
    :data:`EXCITATION_ACCELERATION`, alternately 2 and 1.7 m/s^2, and 4 rad/s^2 per m/s^2 in tilt). On the built-in
    machine:

    * every slider reverses at least three times, at peak speeds of 0.1-0.27 m/s (2-5 times the task paths'), and
      each quintic move sweeps its speed from rest to its peak, so Coulomb (the sign of the speed) and viscous
      friction (the speed) part;
    * the sliders accelerate at 2-2.5 m/s^2, so the rotors' inertia (74 kg at the slider with the built-in rotor)
      is the largest load in the moves, against gravity's at rest;
    * the moves up and down accelerate the payload vertically (its mass), and the tilts of both signs about a
      and b swing its centre of mass sideways (the centre's height: a level path barely moves it);
    * the motion takes 1.99 s, inside ``pusupu identify``'s default window of 2 s;
    * the motors reach 167 rad/s, 0.74 of ``V_max/Ke`` (227 rad/s, the velocity loop's clamp), so a machine with a
      torque constant 10 % above the built-in one still follows it.

    On another machine the path is checked like every path (:func:`pusupu_jax.paths.check_path`).
    """
    accel = np.asarray(EXCITATION_ACCELERATION)
    return platform_waypoints(
        home,
        EXCITATION_WAYPOINTS,
        rates,
        EXCITATION_SPEED,
        accel,
        hold,
        w_max=EXCITATION_TILT_SPEED,
        alpha_max=4.0 * accel,
    )


def path_seconds(kind: str) -> float:
    """The duration [s] of :func:`platform_path` ``kind`` (its timing does not depend on the rate it is sampled at),
    known before a path is built at a rate that would make it too long to hold."""
    return len(platform_path(kind, np.zeros(5))) * LoopRates().dt_position


def platform_waypoints(
    home: npt.ArrayLike,
    waypoints: npt.ArrayLike,
    rates: LoopRates = LoopRates(),
    v_max: npt.ArrayLike = SPEED,
    a_max: npt.ArrayLike = ACCELERATION,
    hold: float = 0.5,
    *,
    w_max: npt.ArrayLike = TILT_SPEED,
    alpha_max: npt.ArrayLike = TILT_ACCELERATION,
    dwell: npt.ArrayLike = 0.0,
) -> np.ndarray:
    """Platform poses ``(N, 5)`` through ``waypoints``, offsets from ``home``: ``(K, 3)`` (x, y, z [m], the platform
    level) or ``(K, 5)`` (x, y, z [m], a, b [rad]).  Straight segments in pose space with quintic timing, at rest
    at every waypoint (:func:`segment_seconds`), each followed by ``dwell`` [s] at rest, then ``hold`` [s] at rest.

    ``v_max`` [m/s], ``a_max`` [m/s^2], ``w_max`` [rad/s], ``alpha_max`` [rad/s^2] and ``dwell`` [s]:
    one value, or one per segment (``K - 1``).  The machine starts at home, so the first waypoint
    should be zero.
    """
    points = np.asarray(waypoints, dtype=float)
    if points.ndim != 2 or points.shape[1] not in (3, 5) or len(points) < 2 or not np.isfinite(points).all():
        raise ParameterError(
            "waypoints: expected at least two finite (x, y, z) offsets [m] or (x, y, z, a, b) "
            f"offsets [m, rad], got shape {points.shape}"
        )
    limits = np.broadcast_arrays(
        *(np.asarray(v, dtype=float) for v in (v_max, a_max, w_max, alpha_max, dwell)), np.zeros(len(points) - 1)
    )[:5]
    for v, a, w, alpha, d in zip(*limits):
        _check_limits({"v_max": v, "a_max": a, "w_max": w, "alpha_max": alpha}, {"dwell": d, "hold": hold})
    dt = rates.dt_position
    moves = []
    for a, b, T, d in zip(points[:-1], points[1:], segment_seconds(points, *limits[:4]), limits[4]):
        moves += [_line(a, b, dt, T), np.repeat(b[None], int(round(d / dt)), axis=0)]
    return _poses(home, np.concatenate(moves), dt, hold)
