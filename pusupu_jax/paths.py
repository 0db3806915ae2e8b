"""The user's paths (host-side): a named path, a waypoint file or a time-stamped pose table, as platform poses at the
position-loop rate; and the check of a path against the machine before anything runs.

Wherever a path is asked for (``pusupu sim --plant mjx --trajectory``, ``pusupu gains check-ros
--trajectory``, ``pusupu bridge --trajectory``, the tuning configuration's ``trajectories:``, a batch
job's ``trajectory:``), a *path spec* gives it (:func:`platform_path_from`):

* a name of :data:`~pusupu_jax.trajectories.PLATFORM_TRAJECTORIES` (``arc``, ``p2p``, ``circle``,
  ``tilt``, ``excite``: :func:`~pusupu_jax.trajectories.platform_path`);
* a waypoint file, ``.yaml`` or ``.yml`` (:data:`FORMAT` version :data:`VERSION`): poses reached one
  after the other from home by straight segments in pose space with quintic timing, each under its
  own limits (:data:`DEFAULTS` where it gives none), with a dwell at its arrival;
* a pose table, ``.csv`` with the header ``t,x,y,z,a,b``: time-stamped poses at any rate, resampled
  at the position-loop rate by a monotone cubic (:meth:`_PoseTable.poses`).

Poses in both files are offsets from the machine's home: x, y, z [m] of the platform centre and the
tilts a, b [rad].  A file is read with :func:`pusupu_jax.inputs.read_text` (a regular UTF-8 file of at
most 1 MiB) and every fault is one line naming the file, the row or field, what was expected and
what was found.  Both formats field by field: ``docs/paths.md``.

:func:`check_path` checks a path against the machine (workspace, motor speeds, motor torques) before
anything runs; :func:`pusupu_jax.machine.machine_reference` calls it for every path it is given.
"""

from __future__ import annotations

import dataclasses
import hashlib
import os
from pathlib import Path
from typing import Any

import jax.numpy as jnp
import numpy as np
import numpy.typing as npt
from scipy.interpolate import PchipInterpolator

from . import inputs, trajectories, workload
from .params import LoopRates, ParameterError, ServoParams, command_limits
from .plant import dynamics, kinematics
from .plant.axis import screw_ratio
from .plant.friction import slider_friction
from .plant.geometry import Geometry, GeometryError
from .plant.model import ModelOptions
from .trajectories import PLATFORM_TRAJECTORIES
from .metrics import Metric

FORMAT, VERSION = "pusupu-path", 1
SUFFIXES = (".yaml", ".yml", ".csv")
COLUMNS = ("t", "x", "y", "z", "a", "b")  # s, then the pose offsets from home: m, m, m, rad, rad
UNITS = ("s", "m", "m", "m", "rad", "rad")
# What a waypoint file's segment gets for a limit it leaves out (and its ``defaults:`` does too): the named paths'
# peak speed and acceleration along the path, and the tilts' (:data:`~pusupu_jax.trajectories.TILT_SPEED`).
DEFAULTS = {
    "speed": trajectories.SPEED,
    "angular_speed": trajectories.TILT_SPEED,
    "acceleration": trajectories.ACCELERATION,
    "angular_acceleration": trajectories.TILT_ACCELERATION,
    "dwell": 0.0,
}
LIMIT_UNITS = {
    "speed": "m/s",
    "angular_speed": "rad/s",
    "acceleration": "m/s^2",
    "angular_acceleration": "rad/s^2",
    "dwell": "s",
}
# The largest offset a file may give, m for x, y, z and rad for the tilts: far beyond any machine of this kind (the
# workspace check refuses what this one cannot reach), it keeps the arithmetic of the timing finite; a tilt of a
# quarter turn is where the two-tilt orientation ends.
POSE_BOUNDS = (10.0, 10.0, 10.0, np.pi / 2, np.pi / 2)
HOME_TOLERANCE = 1e-6  # m or rad: how near home a pose table's first row must be


def is_path_file(spec: object) -> bool:
    """Whether ``spec`` names a path file (by its suffix, :data:`SUFFIXES`) rather than a named path."""
    return isinstance(spec, str) and spec not in PLATFORM_TRAJECTORIES and Path(spec).suffix.lower() in SUFFIXES


def check_spec(spec: object, where: str, error: type[Exception] = ParameterError) -> str:
    """``spec`` if it is a path spec (a name, or the name of a ``.yaml``, ``.yml`` or ``.csv`` file, not read here);
    ``error`` naming ``where`` otherwise."""
    if isinstance(spec, str) and (spec in PLATFORM_TRAJECTORIES or is_path_file(spec)):
        return spec
    raise error(
        f"{where}: expected one of {PLATFORM_TRAJECTORIES} or a path file ({', '.join(SUFFIXES)}), "
        f"got {inputs.shown(spec)}"
    )


def resolve(spec: str, folder: str | os.PathLike[str]) -> str:
    """``spec`` with a relative file name taken from ``folder`` (the folder of the file that names it)."""
    return str(Path(folder) / spec) if is_path_file(spec) and not Path(spec).is_absolute() else spec


def path_label(spec: str) -> str:
    """How scenarios and reports name the path ``spec``: its name, or its file's stem."""
    return Path(spec).stem if is_path_file(spec) else spec


def source_digest(spec: str) -> str:
    """What the path ``spec`` is made of, for digests: its name, or the SHA-256 of its file's bytes."""
    if not is_path_file(spec):
        return spec
    return hashlib.sha256(inputs.read_bytes(spec, "path file", ParameterError)).hexdigest()


def platform_path_from(spec: str, home: npt.ArrayLike, rates: LoopRates = LoopRates()) -> np.ndarray:
    """Platform poses ``(N, 5)`` (x, y, z [m], a, b [rad]) about ``home`` at the position-loop rate
    (``rates.dt_position``) for the path spec ``spec``: a name, a waypoint file or a pose table (module docstring).

    A file's duration is checked against :func:`pusupu_jax.workload.check_run` at ``rates`` before
    it is sampled.  Nothing here checks the path against the machine: :func:`check_path` does.
    """
    check_spec(spec, "trajectory")
    if not is_path_file(spec):
        return trajectories.platform_path(spec, home, rates)
    source = _read(spec)
    workload.check_run(spec, source.seconds, rates)
    return source.poses(np.asarray(home, dtype=float), rates)


def path_seconds(spec: str) -> float:
    """The duration [s] of the path ``spec`` (a waypoint file's to within a position period a segment), known before
    it is sampled at any rate: what the work checks count."""
    check_spec(spec, "trajectory")
    return _read(spec).seconds if is_path_file(spec) else trajectories.path_seconds(spec)


@dataclasses.dataclass(frozen=True)
class _Waypoints:
    """A waypoint file: ``points`` ``(K + 1, 5)`` offsets from home (the first zero, home itself), and the limits of
    the ``K`` segments (``{key of DEFAULTS: (K,)}``)."""

    points: np.ndarray
    limits: dict[str, np.ndarray]

    @property
    def seconds(self) -> float:
        lim = self.limits
        moves = trajectories.segment_seconds(
            self.points, lim["speed"], lim["acceleration"], lim["angular_speed"], lim["angular_acceleration"]
        )
        return float(np.sum(moves) + np.sum(lim["dwell"]))

    def poses(self, home: npt.NDArray[np.float64], rates: LoopRates) -> np.ndarray:
        lim = self.limits
        return trajectories.platform_waypoints(
            home,
            self.points,
            rates,
            lim["speed"],
            lim["acceleration"],
            hold=0.0,
            w_max=lim["angular_speed"],
            alpha_max=lim["angular_acceleration"],
            dwell=lim["dwell"],
        )


@dataclasses.dataclass(frozen=True)
class _PoseTable:
    """A pose table: times ``t`` ``(M,)`` [s] from 0, strictly increasing, and ``offsets`` ``(M, 5)`` from home, the
    first at home."""

    t: np.ndarray
    offsets: np.ndarray

    @property
    def seconds(self) -> float:
        return float(self.t[-1])

    def poses(self, home: npt.NDArray[np.float64], rates: LoopRates) -> np.ndarray:
        """The table sampled every ``rates.dt_position`` from 0 to its last time (the last sample at that time) by
        piecewise cubic Hermite interpolation with monotone slopes (PCHIP, Fritsch-Carlson), each coordinate alone.

        Why PCHIP: it passes through every row, its first derivative is continuous (the drives get
        speeds without jumps), and between two rows it never leaves the range of their values, so it
        never overshoots (a rest of two equal rows stays a rest, a corner is not rounded outwards,
        and no pose between the rows lies beyond what the table asked for).  A cubic spline is
        smoother (continuous acceleration) but rings around corners and rests: it swings past the
        rows, and the machine with it.  PCHIP's acceleration may jump at a row; the torque check
        (:func:`check_path`) sees what that costs.
        """
        dt = rates.dt_position
        times = np.minimum(np.arange(int(np.ceil(self.seconds / dt - 1e-9)) + 1) * dt, self.seconds)
        # scipy ships no type stubs: the interpolant's values are Any
        return home + PchipInterpolator(self.t, self.offsets, axis=0)(times)  # type: ignore[no-any-return]


def _read(spec: str) -> _Waypoints | _PoseTable:
    """The waypoint file or pose table ``spec``, read and checked (one-line ParameterError naming the row or field)."""
    if Path(spec).suffix.lower() == ".csv":
        return _read_table(spec)
    return _read_waypoints(spec)


def _pose_value(value: object, where: str, j: int) -> float:
    bound = POSE_BOUNDS[j]
    return inputs.number(value, where, ParameterError, low=-bound, high=bound)


def _read_waypoints(spec: str) -> _Waypoints:
    data = inputs.read_yaml(spec, "path file", ParameterError)
    inputs.check_keys(
        data,
        spec,
        ("format", "version", "defaults", "waypoints"),
        ParameterError,
        required=("format", "version", "waypoints"),
    )
    if data["format"] != FORMAT:
        raise ParameterError(f"{spec}: format: expected {FORMAT!r}, got {inputs.shown(data['format'])}")
    if isinstance(data["version"], bool) or data["version"] != VERSION:
        raise ParameterError(f"{spec}: version: expected {VERSION}, got {inputs.shown(data['version'])}")
    defaults = dict(DEFAULTS)
    if data.get("defaults") is not None:
        given = inputs.check_keys(data["defaults"], f"{spec}: defaults", tuple(DEFAULTS), ParameterError)
        defaults |= {k: _limit(v, f"{spec}: defaults.{k}", k) for k, v in given.items()}
    waypoints = data["waypoints"]
    if not isinstance(waypoints, list) or not waypoints:
        raise ParameterError(
            f"{spec}: waypoints: expected a non-empty list of waypoints, got {inputs.shown(waypoints, 40)}"
        )
    points: list[np.ndarray | list[float]] = [np.zeros(5)]
    limits: dict[str, list[float]] = {k: [] for k in DEFAULTS}
    for i, entry in enumerate(waypoints):
        where = f"{spec}: waypoints[{i}]"
        inputs.check_keys(entry, where, ("pose",) + tuple(DEFAULTS), ParameterError, required=("pose",))
        pose = entry["pose"]
        if not isinstance(pose, list) or len(pose) != 5:
            raise ParameterError(
                f"{where}.pose: expected five numbers [x, y, z, a, b] (m, m, m, rad, rad, offsets "
                f"from home), got {inputs.shown(pose, 60)}"
            )
        points.append([_pose_value(v, f"{where}.pose[{j}] ({COLUMNS[j + 1]})", j) for j, v in enumerate(pose)])
        for k in DEFAULTS:
            limits[k].append(_limit(entry[k], f"{where}.{k}", k) if k in entry else defaults[k])
    return _Waypoints(np.array(points, dtype=float), {k: np.array(v) for k, v in limits.items()})


def _limit(value: object, where: str, key: str) -> float:
    """A segment's limit: a positive number (a dwell: non-negative) in :data:`LIMIT_UNITS` ``[key]``."""
    return inputs.number(value, f"{where} [{LIMIT_UNITS[key]}]", ParameterError, low=0.0, low_open=key != "dwell")


def _read_table(spec: str) -> _PoseTable:
    text = inputs.read_text(spec, "pose table", ParameterError).lstrip("\ufeff")  # a spreadsheet's byte order mark
    rows = [(n, line) for n, line in enumerate(text.splitlines(), 1) if line.strip()]
    header = ",".join(COLUMNS)
    if not rows:
        raise ParameterError(f"{spec}: expected a header {header}, got an empty file")
    n, line = rows[0]
    names = [c.strip() for c in line.split(",")]
    if sorted(names) != sorted(COLUMNS):
        raise ParameterError(
            f"{spec}: row {n}: expected the header {header} (the six columns in any order), got "
            f"{inputs.shown(line, 80)}"
        )
    order = [names.index(c) for c in COLUMNS]
    values, numbers = [], []
    for n, line in rows[1:]:
        cells = line.split(",")
        if len(cells) != len(COLUMNS):
            raise ParameterError(f"{spec}: row {n}: expected {len(COLUMNS)} values ({header}), got {len(cells)}")
        row = []
        for j in order:
            name, cell = names[j], cells[j].strip()
            try:
                v = float(cell)
            except ValueError:
                raise ParameterError(
                    f"{spec}: row {n}, {name}: expected a number, got {inputs.shown(cell, 40)}"
                ) from None
            where = f"{spec}: row {n}, {name} [{UNITS[COLUMNS.index(name)]}]"
            row.append(
                inputs.number(v, where, ParameterError)
                if name == "t"
                else _pose_value(v, where, COLUMNS.index(name) - 1)
            )
        values.append(row)
        numbers.append(n)
    if len(values) < 2:
        raise ParameterError(f"{spec}: expected at least two rows of poses under the header, got {len(values)}")
    table = np.array(values)
    t = table[:, 0]
    back = np.flatnonzero(np.diff(t) <= 0)
    if back.size:
        k = int(back[0]) + 1
        raise ParameterError(
            f"{spec}: row {numbers[k]}, t: expected a time after the row before's {t[k - 1]:.9g} s "
            f"(times strictly increasing), got {t[k]:.9g} s"
        )
    away = np.flatnonzero(np.abs(table[0, 1:]) > HOME_TOLERANCE)
    if away.size:
        j = int(away[0]) + 1
        raise ParameterError(
            f"{spec}: row {numbers[0]}, {COLUMNS[j]}: expected 0 (the path starts at home, where "
            f"the machine starts: every offset within {HOME_TOLERANCE:g}), got "
            f"{table[0, j]:.6g} {UNITS[j]}"
        )
    return _PoseTable(t - t[0], table[:, 1:])


def check_path(
    path: npt.ArrayLike,
    servo: ServoParams,
    dt: float,
    geom: Geometry | None = None,
    options: ModelOptions = ModelOptions(),
    where: str = "path",
) -> dict[str, Any]:
    """Check platform poses ``path`` ``(N, 5)`` (one every ``dt`` [s]) against the machine before anything runs.

    1. The workspace (:func:`pusupu_jax.plant.kinematics.check_poses`): every branch reachable,
       every slider within its stroke, the passive UPU leg within its lengths, the Jacobian well
       conditioned.
    2. The motors' speed: slider speed ``v`` [m/s] over the screw ratio ``r = lead / 2 pi``
       [m/rad], at most ``servo.speed_max`` [rad/s] and at most ``V_max / Ke`` [rad/s], where the
       back-EMF takes the whole voltage (the velocity loop's clamp: the cascade commands no more).
    3. The motors' torque: ``(F + F_f(v)) r / eta`` [N m], at most ``Kt I_max``: ``F`` the
       minimum-norm slider forces [N] that move the nominal machine (``geom``, ``options``'
       payload) along the path (:func:`pusupu_jax.plant.dynamics.inverse_dynamics_forces`; its
       model carries the rotor inertia as the slides' armature ``eta J / r^2``, so ``F r / eta``
       already holds the rotor's ``J theta''``), ``F_f`` the drive train's friction
       (:func:`pusupu_jax.plant.friction.slider_friction`).

    Speeds and accelerations are central differences along the path with the machine at rest
    before it (at its first pose) and after it (held at its last): a path that starts or stops
    moving at once is seen doing so.  ``servo`` is one parameter set (its fields ``(6,)``).

    Raises :class:`GeometryError`, one line: ``where``, the first pose that fails (index and time
    ``index dt``), the branch (1 to 6), the value and the limit; the workspace is checked first
    (the drives' loads need it).  Returns the extremes: :func:`check_poses`' and per branch
    ``motor_speed_peak_rad_s`` and ``motor_torque_peak_nm``.
    """
    geom = Geometry.default() if geom is None else geom
    path = np.asarray(path, dtype=float)
    try:
        report = kinematics.check_poses(geom, path, dt=dt)
    except GeometryError as e:
        raise GeometryError(f"{where} leaves the workspace: {e}") from None
    still = np.concatenate([path[:1], path, path[-1:]])
    force, _ = dynamics.inverse_dynamics_forces(servo, still, dt, geom, options)
    s = np.asarray(kinematics.inverse_kinematics(geom, jnp.asarray(path)))  # the program machine_reference runs
    v = np.gradient(np.concatenate([s[:1], s, s[-1:]]), dt, axis=0)
    r, eta = np.asarray(screw_ratio(servo), dtype=float), np.asarray(servo.eta, dtype=float)
    speed = np.abs(v) / r
    torque = np.abs(force + np.asarray(slider_friction(servo, v))) * r / eta
    rated = np.asarray(servo.speed_max, dtype=float)
    emf, torque_max = command_limits(servo)
    speed_max = np.minimum(rated, emf)
    failing = [
        (int(np.argmax(bad.any(axis=1))), n)
        for n, bad in enumerate((speed > speed_max, torque > torque_max))
        if bad.any()
    ]
    if failing:
        j, n = min(failing)
        k = min(max(j - 1, 0), len(path) - 1)  # the pose of row j of ``still``
        at = f"{where} exceeds the drives: pose {k} (t = {k * dt:.6g} s)"
        if n == 0:
            i = int(np.argmax(speed[j] > speed_max))
            name = "speed_max" if rated[i] <= emf[i] else "V_max/Ke"
            raise GeometryError(
                f"{at}: branch {i + 1} motor speed {speed[j, i]:.4g} rad/s (slider {abs(v[j, i]):.3g} "
                f"m/s), expected at most {name} = {speed_max[i]:.4g} rad/s"
            )
        i = int(np.argmax(torque[j] > torque_max))
        raise GeometryError(
            f"{at}: branch {i + 1} motor torque {torque[j, i]:.4g} N m (slider force "
            f"{force[j, i]:.4g} N), expected at most Kt I_max = {torque_max[i]:.4g} N m"
        )
    return report | {
        "motor_speed_peak_rad_s": speed.max(axis=0).tolist(),
        Metric.MOTOR_TORQUE_PEAK_NM: torque.max(axis=0).tolist(),
    }
