"""The machine file: what the robot is (host-side).

A machine file describes one 6PUS-UPU robot, never its controller: the mechanism's geometry and
masses, each axis's drive (motor, inverter, ball screw, ratings) and drive-train friction, and the
payload.  The gain file says what the controller is told; no field lives in both.  Schema
``pusupu-machine`` version 1, every key required but ``uncertainty`` (``pusupu machine init`` writes the built-in
machine as a commented template; ``docs/machine.md`` documents each field)::

    format: pusupu-machine
    version: 1
    name: my-robot                 # a label for reports and gain files
    geometry: {rail_points: [[x, y, z] x 6], ...}   # every Geometry field, SI units
    drives: {R: 1.3, L: 0.0027, ...}                # every plant field of ServoParams: a number, or six
                                                    # (optional: encoder_counts, current_noise: the sensors)
    payload: {mass: 0.0, com: [0, 0, 0], inertia: [0, 0, 0]}
    uncertainty: {coulomb: 0.4, Kt: [...], ...,    # optional: standard errors of identified values,
                  correlation: {values: [coulomb[1], ...], matrix: [[1, ...], ...]}}   # and their correlations

:func:`load` reads and checks one: size, keys, shapes, signs, each drive value's range
(:func:`pusupu_jax.params.bounds`), the geometry's consistency, and that the home pose is
reachable, inside every stroke and well conditioned; one line names the first problem.
:func:`Machine.servo` puts the machine's drive values under a controller's gains, and
:func:`Machine.options` its payload into the MJX machine's options.  :func:`digest` identifies
the machine's content (not its comments or layout): a gain file records the digest of the
machine it was tuned on.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import os
from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, NamedTuple

import numpy as np
import numpy.typing as npt
import yaml

from . import inputs
from .params import N_AXES, AxisLoad, ParameterError, ServoParams, array_fields, bounds, validate
from .plant import kinematics
from .plant.geometry import FIELDS as GEOMETRY_FIELDS
from .plant.geometry import Geometry, GeometryError, validate_geometry

if TYPE_CHECKING:
    from .plant.model import ModelOptions

FORMAT, VERSION = "pusupu-machine", 1
KEYS = ("format", "version", "name", "geometry", "drives", "payload")
PAYLOAD_FIELDS = {
    "mass": ((), "kg", "the payload's mass (tool and workpiece)"),
    "com": ((3,), "m", "its centre of mass in the platform frame (origin at the platform centre)"),
    "inertia": (
        (3,),
        "kg*m^2",
        "its principal moments of inertia about its centre of mass, axes along the platform frame's",
    ),
}
COND_MAX = 30.0  # the Jacobian condition number a pose may reach (kinematics.check_poses)
# the optional ``uncertainty`` section: the standard error of each value ``pusupu identify`` fits (its --fit names,
# :class:`pusupu_jax.machine_fit.FitField`), what ``pusupu tune``'s ``draws`` draw machines from; its shape (a
# per-axis drive field: one number for all six axes or six), unit and meaning
UNCERTAINTY_FIELDS = {
    "coulomb": ((N_AXES,), "N", "Coulomb friction at the slider"),
    "viscous": ((N_AXES,), "N*s/m", "viscous friction at the slider"),
    "J": ((N_AXES,), "kg*m^2", "the motor's rotor inertia"),
    "Kt": ((N_AXES,), "N*m/A", "the motor's torque constant (Ke follows it in a draw)"),
    "payload_mass": ((), "kg", "the payload's mass"),
    "payload_com": ((3,), "m", "the payload's centre of mass"),
}
CORRELATION_TOLERANCE = 1e-9  # how far a correlation matrix may be from symmetric, unit-diagonal, semi-definite


def value_label(name: str, index: int) -> str:
    """One value of the ``uncertainty`` field ``name`` (index from 0): ``coulomb[3]`` (axis 3, from 1),
    ``payload_com.x``, ``payload_mass``: how a correlation names it."""
    shape = UNCERTAINTY_FIELDS[name][0]
    if shape == (N_AXES,):
        return f"{name}[{index + 1}]"
    return f"{name}.{'xyz'[index]}" if shape == (3,) else str(name)


@dataclass(frozen=True)
class Correlation:
    """The correlations between identified values, part of the ``uncertainty`` section: ``values``, their labels
    (:func:`value_label`), and ``matrix`` ``(n, n)``, the fit's covariance divided by the standard errors (symmetric,
    ones on its diagonal, positive semi-definite, each within :data:`CORRELATION_TOLERANCE`).  A value it leaves out
    is uncorrelated with the others."""

    values: tuple[str, ...]
    matrix: np.ndarray


class Sensor(NamedTuple):
    """An optional ``drives`` key that describes a drive's sensor, not its plant: left out, an ideal sensor (what the
    paper's machine is modelled with), and the file's digest is what it was before the key existed.  Only the
    simulated robot uses them; the MJX machine keeps ideal sensors."""

    kind: type[int] | type[float]
    low: float
    high: float
    unit: str
    doc: str
    range_doc: str
    example_doc: str  # the commented example of the template: what it is
    example: str  # and its value as written


SENSORS = {
    "encoder_counts": Sensor(
        int,
        256,
        2**32,
        "1",
        "encoder counts per motor revolution (optional; left out: an ideal encoder)",
        "an 8-bit encoder to a 32-bit one",
        "a 20-bit encoder",
        str(2**20),
    ),
    "current_noise": Sensor(
        float,
        0.0,
        100.0,
        "A",
        "the current sensor's noise, its standard deviation (optional; left out: none)",
        "0 to 100 A",
        "1 % of a 10 A rating",
        "0.1",
    ),
}


def _bounds(f: dataclasses.Field[Any]) -> tuple[float, float | str, str]:
    """A drive field's ``(low, high, why)`` (:func:`pusupu_jax.params.bounds`; every drive field is bounded)."""
    found = bounds(f)
    assert found is not None, f.name
    return found


def drive_fields() -> list[dataclasses.Field[Any]]:
    """The fields of :class:`~pusupu_jax.params.ServoParams` a machine file holds: its ``plant`` section."""
    return [f for f in array_fields(ServoParams) if f.metadata["section"] == "plant"]


@dataclass(frozen=True)
class Payload:
    """The payload on the platform: mass [kg], centre of mass [m] (platform frame), principal inertia [kg m^2]."""

    mass: float = 0.0
    com: tuple[float, float, float] = (0.0, 0.0, 0.0)
    inertia: tuple[float, float, float] = (0.0, 0.0, 0.0)


@dataclass(frozen=True)
class Machine:
    """One robot: ``geometry``, ``drives`` (``{field: (6,) array}`` of the plant fields of
    :class:`~pusupu_jax.params.ServoParams`), ``payload``, ``encoder_counts`` (counts per motor revolution,
    ``(6,)`` integers; None: ideal encoders) and ``current_noise`` (the current sensors' standard deviation [A],
    ``(6,)``; None: noise-free), ``uncertainty`` (the standard errors of identified values, ``{name: array}`` of
    :data:`UNCERTAINTY_FIELDS`, in their units; None: none given), ``correlation`` (the correlations between some of
    those values, :class:`Correlation`; None: none given, the values uncorrelated); ``name`` labels it."""

    name: str
    geometry: Geometry
    drives: dict[str, np.ndarray]
    payload: Payload = field(default_factory=Payload)
    encoder_counts: np.ndarray | None = None
    current_noise: np.ndarray | None = None
    uncertainty: dict[str, np.ndarray] | None = None
    correlation: Correlation | None = None

    @classmethod
    def default(cls) -> "Machine":
        """The built-in machine: the default geometry (``docs/geometry.md``), Table 1's drives with the documented
        choices (``docs/parameters.md``), no payload."""
        base = ServoParams.table1()
        return cls(
            "built-in",
            Geometry.default(),
            {f.name: np.asarray(getattr(base, f.name), dtype=float) for f in drive_fields()},
        )

    def servo(self, gains: ServoParams) -> ServoParams:
        """``gains`` (what the controller is told) on this machine's drives; checked, so a controller limit beyond
        the machine's rating (``I_max > I_peak``, ``V_max > V_dc``) is refused."""
        out = gains.replace(
            **{name: np.broadcast_to(v, np.shape(gains.lambda1)).copy() for name, v in self.drives.items()}
        )
        try:
            validate(out)
        except ParameterError as e:
            raise ParameterError(f"on machine {self.name!r}: {e}") from None
        return out

    def options(self, base: ModelOptions | None = None) -> ModelOptions:
        """``base`` (a :class:`~pusupu_jax.plant.model.ModelOptions`; default its defaults) with this machine's
        payload.  (MuJoCo is imported here, not with the module: a gain file is read on the robot side without it.)"""
        from .plant.model import ModelOptions

        return dataclasses.replace(
            ModelOptions() if base is None else base,
            payload=float(self.payload.mass),
            payload_com=tuple(self.payload.com),
            payload_inertia=tuple(self.payload.inertia),
        )

    def content(self) -> dict[str, Any]:
        """The machine as plain data (lists and floats), every field: what :func:`digest` hashes (the sensors, the
        uncertainty and its correlation only where given, so that a file without them keeps its digest)."""
        sensors = {
            k: _compact(getattr(self, k), spec.kind) for k, spec in SENSORS.items() if getattr(self, k) is not None
        }
        uncertainty = (
            {}
            if self.uncertainty is None
            else {
                "uncertainty": {
                    k: _compact(v) if UNCERTAINTY_FIELDS[k][0] == (N_AXES,) else np.asarray(v, float).tolist()
                    for k, v in self.uncertainty.items()
                }
                | (
                    {}
                    if self.correlation is None
                    else {
                        "correlation": {
                            "values": list(self.correlation.values),
                            "matrix": np.asarray(self.correlation.matrix, float).tolist(),
                        }
                    }
                )
            }
        )
        return {
            "format": FORMAT,
            "version": VERSION,
            "name": self.name,
            "geometry": {k: np.asarray(getattr(self.geometry, k), dtype=float).tolist() for k in GEOMETRY_FIELDS},
            "drives": {k: _compact(v) for k, v in self.drives.items()} | sensors,
            "payload": {
                "mass": float(self.payload.mass),
                "com": [float(x) for x in self.payload.com],
                "inertia": [float(x) for x in self.payload.inertia],
            },
        } | uncertainty


def digest(machine: Machine) -> str:
    """sha256 of the machine's content (canonical JSON of :meth:`Machine.content`, float64 values): equal for the
    same robot whatever the file's comments, order or number formatting."""
    return hashlib.sha256(json.dumps(machine.content(), sort_keys=True).encode()).hexdigest()


def is_builtin(machine: Machine) -> bool:
    """Whether ``machine`` is the built-in one (the same digest): the machine Table 1's gains are for."""
    return digest(machine) == digest(Machine.default())


def carried_mass(machine: Machine) -> np.ndarray:
    """The mass [kg] each slider carries at the machine's home pose, ``(6,)``: the diagonal of the mechanism's
    actuator-space inertia (:func:`pusupu_jax.plant.dynamics.reflected_mass`, payload included, rotors not)."""
    from .plant.dynamics import reflected_mass

    key = digest(machine)
    if key not in _CARRIED:
        # to the gram: the axes of a symmetric machine read the same, not values apart by rounding
        _CARRIED[key] = np.round(reflected_mass(machine.geometry, machine.geometry.home, machine.options())[0], 3)
    return _CARRIED[key].copy()


_CARRIED: dict[str, np.ndarray] = {}  # digest -> carried_mass: a machine's model is built once per process


PATH_SAMPLES = 64  # poses of a path at which the carried mass is taken (evenly spaced, its ends included)


def carried_mass_range(
    machine: Machine, poses: npt.ArrayLike, options: ModelOptions | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """The lightest and the heaviest mass [kg] each slider carries over ``poses`` ``(N, 5)`` and home, ``((6,),
    (6,))``: :func:`carried_mass`'s diagonal at :data:`PATH_SAMPLES` poses evenly spaced along the path (the
    reflected mass changes slowly with the pose: the built-in machine's varies by 8 % over 0.14 m of travel), with
    the payload of ``options`` (default the machine's own, :meth:`Machine.options`)."""
    from .plant.dynamics import reflected_mass

    poses = np.asarray(poses, dtype=float)
    pick = np.unique(np.linspace(0, len(poses) - 1, min(PATH_SAMPLES, len(poses))).round().astype(int))
    home = np.asarray(machine.geometry.home, dtype=float)[None]
    options = machine.options() if options is None else options
    mass = np.round(reflected_mass(machine.geometry, np.vstack([home, poses[pick]]), options), 3)
    return mass.min(axis=0), mass.max(axis=0)


class PathRun(NamedTuple):
    """A path on a machine: platform ``poses`` ``(N, 5)``, the model ``options`` it runs with (their payload; None:
    the machine's own) and the nominal ``geometry`` (None: the machine's)."""

    poses: npt.ArrayLike
    options: ModelOptions | None = None
    geometry: Geometry | None = None


MARGIN_LOADS = ("home", "lightest", "heaviest")
"""The names of :func:`margin_loads`' loads, as a gain file's ``provenance.margin_loads_kg`` records them."""


def margin_loads(machine: Machine, runs: Iterable[PathRun] = ()) -> dict[str, AxisLoad]:
    """The single-axis loads the linear model's margins are taken with on ``machine``: ``home``
    (:func:`axis_load`), and with ``runs`` the ``lightest`` and the ``heaviest`` mass each slider carries over all
    of them (:func:`carried_mass_range` of each, on its geometry with its payload).  The gain check, the tuner's
    margin constraints and ``pusupu analyze --trajectory`` take every one."""
    home = axis_load(machine)
    ranges = [
        carried_mass_range(machine if g is None else dataclasses.replace(machine, geometry=g), poses, options)
        for poses, options, g in runs
    ]
    if not ranges:
        return {"home": home}
    lightest = home.replace(mass=np.min([low for low, _ in ranges], axis=0))
    heaviest = home.replace(mass=np.max([high for _, high in ranges], axis=0))
    return dict(zip(MARGIN_LOADS, (home, lightest, heaviest)))


def axis_load(machine: Machine) -> AxisLoad:
    """The single-axis load of the linear model on ``machine`` (``pusupu analyze``, the gain check's margins, the
    tuner's margin constraints): the mass each slider carries at home (:func:`carried_mass`), level rails.

    Measured against the MJX machine's own loop gains (``pusupu experiment loop_match``, ``docs/machine.md``), it
    puts the velocity loop's crossover within 5 % (a lumped 20 kg, 33-38 % too high), and the phase margins it
    reports are below the machine's: on the safe side (the coupled model, :mod:`pusupu_jax.coupled`, matches
    them)."""
    return AxisLoad.default().replace(mass=carried_mass(machine))


def reference(machine: Machine) -> dict[str, str]:
    """What a gain file records of the machine it was tuned on: ``{name, digest}``."""
    return {"name": machine.name, "digest": digest(machine)}


def _compact(values: npt.ArrayLike, kind: type[float] | type[int] = float) -> float | list[Any]:
    arr = np.asarray(values, dtype=kind)
    return kind(arr.flat[0]) if np.all(arr == arr.flat[0]) else arr.tolist()


def load(path: str | os.PathLike[str]) -> Machine:
    """Read and check a machine file (see the module docstring); raises ParameterError in one line."""
    path = Path(path)
    doc = inputs.read_yaml(path, "machine file", ParameterError)
    try:
        return parse(doc)
    except ParameterError as e:
        raise ParameterError(f"{path}: {e}") from None


def parse(doc: Any) -> Machine:
    """:func:`load` on a parsed document."""
    inputs.check_keys(doc, "machine file", [*KEYS, "uncertainty"], ParameterError, required=KEYS)
    if doc["format"] != FORMAT:
        raise ParameterError(f"format: expected {FORMAT!r}, got {inputs.shown(doc['format'])}")
    if doc["version"] != VERSION or isinstance(doc["version"], bool):
        raise ParameterError(f"version: expected {VERSION}, got {inputs.shown(doc['version'])}")
    name = doc["name"]
    if not isinstance(name, str) or not name.strip() or len(name) > 100 or not name.isprintable():
        raise ParameterError(f"name: expected a printable label of 1 to 100 characters, got {inputs.shown(name)}")
    geometry = _geometry(doc["geometry"])
    drives = _drives(doc["drives"])
    payload = _payload(doc["payload"])
    sensors = {k: _sensor(k, doc["drives"][k]) for k in SENSORS if k in doc["drives"]}
    uncertainty, correlation = _uncertainty(doc["uncertainty"]) if "uncertainty" in doc else (None, None)
    machine = Machine(name, geometry, drives, payload, **sensors, uncertainty=uncertainty, correlation=correlation)
    check(machine)
    return machine


def _array(value: object, where: str, shape: tuple[int, ...]) -> np.ndarray:
    return inputs.array(value, where, shape, ParameterError)


def _geometry(values: Any) -> Geometry:
    names = list(GEOMETRY_FIELDS)
    inputs.check_keys(values, "geometry", names, ParameterError, required=names, what="field")
    g = Geometry(**{k: _array(values[k], f"geometry.{k}", GEOMETRY_FIELDS[k][0]) for k in names})
    try:
        validate_geometry(g)
    except GeometryError as e:
        raise ParameterError(str(e)) from None
    return g


def _drives(values: Any) -> dict[str, np.ndarray]:
    names = [f.name for f in drive_fields()]
    inputs.check_keys(values, "drives", [*names, *SENSORS], ParameterError, required=names, what="field")
    out: dict[str, np.ndarray] = {}
    for f in drive_fields():
        v, where = values[f.name], f"drives.{f.name}"
        if isinstance(v, list):
            if len(v) != N_AXES:
                raise ParameterError(
                    f"{where}: expected a number or a list of {N_AXES} (one per axis), got a list of {len(v)}"
                )
            arr = np.array([inputs.number(x, f"{where}[{k}]", ParameterError) for k, x in enumerate(v)])
        else:
            arr = np.full(N_AXES, inputs.number(v, where, ParameterError))
        low, high, why = _bounds(f)
        top = np.asarray(values[high], dtype=float) if isinstance(high, str) else high
        bad = (arr < low) | (arr > top)
        if bad.any():
            k = int(np.argmax(bad))
            raise ParameterError(
                f"{where}: expected {low:g} to {high if isinstance(high, str) else f'{high:g}'} "
                f"[{f.metadata['unit']}] ({why}), got {arr[k]:.6g} on axis {k}"
            )
        out[f.name] = arr
    return out


def _sensor(name: str, value: Any) -> np.ndarray:
    """The optional ``drives`` key ``name`` (:data:`SENSORS`): one value for all six axes or six, each in range."""
    spec, where = SENSORS[name], f"drives.{name}"
    values = value if isinstance(value, list) else [value] * N_AXES
    one = "an integer" if spec.kind is int else "a number"
    if len(values) != N_AXES:
        raise ParameterError(
            f"{where}: expected {one} or a list of {N_AXES} (one per axis), got a list of {len(values)}"
        )

    def read(v: Any, at: str) -> float:
        if spec.kind is int:
            return inputs.integer(v, at, ParameterError, low=int(spec.low), high=int(spec.high))
        return inputs.number(v, at, ParameterError, low=spec.low, high=spec.high)

    return np.array(
        [read(v, where if not isinstance(value, list) else f"{where}[{k}]") for k, v in enumerate(values)],
        dtype=np.int64 if spec.kind is int else float,
    )


def _uncertainty(values: Any) -> tuple[dict[str, np.ndarray], Correlation | None]:
    """The optional ``uncertainty`` section: standard errors, each finite and non-negative, in
    :data:`UNCERTAINTY_FIELDS`'s shapes (a per-axis one as one number for all six axes, or six), and their optional
    ``correlation`` (:func:`check_correlation`)."""
    names = list(UNCERTAINTY_FIELDS)
    inputs.check_keys(values, "uncertainty", [*names, "correlation"], ParameterError, what="field")
    out = {}
    for k, v in values.items():
        if k == "correlation":
            continue
        shape, where = UNCERTAINTY_FIELDS[k][0], f"uncertainty.{k}"
        if shape == (N_AXES,) and not isinstance(v, list):
            v = [v] * N_AXES
        arr = _array(v, where, shape)
        if (arr < 0).any():
            raise ParameterError(f"{where}: expected standard errors >= 0, got {arr.tolist()}")
        out[k] = arr
    if "correlation" not in values:
        return out, None
    doc, where = values["correlation"], "uncertainty.correlation"
    inputs.check_keys(doc, where, ["values", "matrix"], ParameterError, required=["values", "matrix"], what="key")
    labels = doc["values"]
    if not isinstance(labels, list) or len(labels) < 2 or not all(isinstance(x, str) for x in labels):
        raise ParameterError(f"{where}.values: expected a list of two or more value labels, got {inputs.shown(labels)}")
    correlation = Correlation(tuple(labels), _array(doc["matrix"], f"{where}.matrix", (len(labels), len(labels))))
    check_correlation(correlation, out)
    return out, correlation


def check_correlation(correlation: Correlation, uncertainty: dict[str, np.ndarray]) -> None:
    """ParameterError, one line, unless ``correlation`` names distinct values (:func:`value_label`) that each have a
    standard error above 0 in ``uncertainty``, and its matrix is a correlation matrix: symmetric, ones on its
    diagonal, entries within [-1, 1] and no eigenvalue below 0 (each within :data:`CORRELATION_TOLERANCE`)."""
    where = "uncertainty.correlation"
    errors = {
        value_label(k, i): float(e)
        for k, v in uncertainty.items()
        for i, e in enumerate(np.broadcast_to(v, UNCERTAINTY_FIELDS[k][0]).reshape(-1))
    }
    for label in correlation.values:
        if label not in errors:
            raise ParameterError(
                f"{where}.values: expected labels of values this section gives a standard error "
                f"({', '.join(errors) or 'none'}), got {label!r}"
            )
        if errors[label] == 0:
            raise ParameterError(f"{where}.values: expected values with a standard error above 0, got {label!r} at 0")
    if len(set(correlation.values)) != len(correlation.values):
        raise ParameterError(f"{where}.values: expected each value once, got {list(correlation.values)}")
    C, tol = np.asarray(correlation.matrix, float), CORRELATION_TOLERANCE
    asymmetry = float(np.max(np.abs(C - C.T), initial=0.0))
    diagonal = float(np.max(np.abs(np.diag(C) - 1), initial=0.0))
    smallest = float(np.min(np.linalg.eigvalsh((C + C.T) / 2), initial=0.0))
    if asymmetry > tol or diagonal > tol or np.any(np.abs(C) > 1 + tol) or smallest < -tol:
        raise ParameterError(
            f"{where}.matrix: expected a correlation matrix (symmetric, ones on its diagonal, entries within [-1, 1], "
            f"no eigenvalue below 0), got asymmetry {asymmetry:.3g}, diagonal off 1 by {diagonal:.3g}, largest "
            f"entry {float(np.max(np.abs(C), initial=0.0)):.6g}, smallest eigenvalue {smallest:.3g}"
        )


def encoder_quanta(machine: Machine, dt_velocity: float) -> dict[str, list[float]] | None:
    """What ``machine``'s encoders resolve, per axis (None for ideal encoders): one count at the slider [m] and the
    speed step [rad/s] of a speed measured from counts over one velocity period ``dt_velocity`` [s]."""
    if machine.encoder_counts is None:
        return None
    count = 2 * np.pi / machine.encoder_counts  # rad at the motor
    return {
        "counts_per_rev": machine.encoder_counts.tolist(),
        "slider_count_m": (count * machine.drives["lead"] / (2 * np.pi)).tolist(),
        "speed_step_rad_s": (count / dt_velocity).tolist(),
    }


def _payload(values: Any) -> Payload:
    names = list(PAYLOAD_FIELDS)
    inputs.check_keys(values, "payload", names, ParameterError, required=names, what="field")
    mass = inputs.number(values["mass"], "payload.mass", ParameterError, low=0.0, high=10000.0)
    com = _array(values["com"], "payload.com", (3,))
    inertia = _array(values["inertia"], "payload.inertia", (3,))
    if (np.abs(com) > 10.0).any():
        raise ParameterError(f"payload.com: expected within 10 m of the platform centre, got {com.tolist()}")
    if (inertia < 0).any():
        raise ParameterError(f"payload.inertia: expected non-negative principal moments, got {inertia.tolist()}")
    a, b, c = inertia
    if a + b < c or b + c < a or a + c < b:
        raise ParameterError(
            f"payload.inertia: expected principal moments obeying the triangle inequality (a body's "
            f"can), got {inertia.tolist()}"
        )
    return Payload(mass, tuple(com.tolist()), tuple(inertia.tolist()))


def check(machine: Machine, paths: Iterable[tuple[str, npt.ArrayLike]] = ()) -> dict[str, dict[str, Any]]:
    """Check that the machine is whole and its home pose (and each of ``paths``, ``(N, 5)`` poses) lies in its
    workspace: every branch reachable, every slider inside its stroke, the UPU leg within its limits, the Jacobian's
    condition number at most :data:`COND_MAX`.  Returns the extremes found (``kinematics.check_poses``) per path,
    ``home`` first."""
    geometry = machine.geometry
    home = np.asarray(geometry.home, dtype=float)[None]
    out: dict[str, dict[str, Any]] = {}
    for name, poses in (("home", home), *paths):
        try:
            out[name] = kinematics.check_poses(geometry, poses, cond_max=COND_MAX)
        except GeometryError as e:
            raise ParameterError(f"{'geometry.home' if name == 'home' else f'path {name}'}: {e}") from None
    return out


def template(machine: Machine | None = None) -> str:
    """The machine file of ``machine`` (default: the built-in one) as YAML, each field commented with its unit and
    meaning: what ``pusupu machine init`` writes."""
    machine = Machine.default() if machine is None else machine
    content = machine.content()
    units = {f.name: (f.metadata["unit"], f.metadata["doc"]) for f in drive_fields()}
    lines = [
        f"# {FORMAT} version {VERSION}: what the robot is (docs/machine.md). SI units throughout.",
        "# A per-axis drive value is one number for all six axes, or a list of six.",
        f"format: {FORMAT}",
        f"version: {VERSION}",
        f"name: {json.dumps(machine.name)}",
        "geometry:",
    ]
    for k, (_, unit, doc) in GEOMETRY_FIELDS.items():
        lines.append(f"  # {doc} [{unit}]")
        lines.append(f"  {k}: {_flow(content['geometry'][k])}")
    lines.append("drives:  # each axis: motor, inverter, ball screw, ratings and drive-train friction")
    for k, v in content["drives"].items():
        unit, doc = units[k] if k not in SENSORS else (SENSORS[k].unit, SENSORS[k].doc)
        lines.append(f"  # {doc} [{unit}]")
        lines.append(f"  {k}: {_flow(v)}")
    for k, spec in SENSORS.items():
        if k not in content["drives"]:
            lines.append(f"  # {spec.doc} [{spec.unit}]; {spec.example_doc}: {spec.example}")
            lines.append(f"  # {k}: {spec.example}")
    lines.append("payload:")
    for k, (_, unit, doc) in PAYLOAD_FIELDS.items():
        lines.append(f"  # {doc} [{unit}]")
        lines.append(f"  {k}: {_flow(content['payload'][k])}")
    if "uncertainty" in content:
        lines.append("uncertainty:  # standard errors of identified values: pusupu tune's draws (docs/tuning.md)")
        for k, v in content["uncertainty"].items():
            if k == "correlation":
                lines.append(
                    "  # the correlations between these values (the fit's covariance over their standard errors)"
                )
                lines.append("  correlation:")
                lines.append(f"    values: {_flow(v['values'])}")
                lines.append("    matrix:")
                lines.extend(f"    - {_flow(row)}" for row in v["matrix"])
                continue
            lines.append(f"  # {UNCERTAINTY_FIELDS[k][2]} [{UNCERTAINTY_FIELDS[k][1]}]")
            lines.append(f"  {k}: {_flow(v)}")
    return "\n".join(lines) + "\n"


def _flow(value: Any) -> str:
    text: str = yaml.safe_dump(value, default_flow_style=True, width=1000).strip().removesuffix("\n...")
    return text


def json_schema() -> dict[str, Any]:
    """The JSON Schema of a machine file (for editors), generated from the field metadata."""

    def number() -> dict[str, Any]:
        return {"type": "number"}

    def shaped(shape: tuple[int, ...]) -> dict[str, Any]:
        schema = number()
        for n in reversed(shape):
            schema = {"type": "array", "items": schema, "minItems": n, "maxItems": n}
        return schema

    drives = {}
    for f in drive_fields():
        low, high, why = _bounds(f)
        one = {"type": "number", "minimum": low} | ({} if isinstance(high, str) else {"maximum": high})
        drives[f.name] = {
            "description": f"{f.metadata['doc']} [{f.metadata['unit']}]; range: {why}",
            "oneOf": [one, {"type": "array", "items": one, "minItems": N_AXES, "maxItems": N_AXES}],
        }
    sensors = {}
    for k, spec in SENSORS.items():
        one = {"type": "integer" if spec.kind is int else "number", "minimum": spec.low, "maximum": spec.high}
        sensors[k] = {
            "description": f"{spec.doc} [{spec.unit}]; range: {spec.range_doc}",
            "oneOf": [one, {"type": "array", "items": one, "minItems": N_AXES, "maxItems": N_AXES}],
        }
    uncertainty = {}
    for k, (shape, unit, doc) in UNCERTAINTY_FIELDS.items():
        one = {"type": "number", "minimum": 0}
        many = {"type": "array", "items": one, "minItems": shape[0], "maxItems": shape[0]} if shape else None
        uncertainty[k] = {"description": f"standard error of {doc} [{unit}]"} | (
            {"oneOf": [one, many]} if shape == (N_AXES,) else many or one
        )
    uncertainty["correlation"] = {
        "description": "the correlations between some of these values (the fit's covariance over their standard "
        "errors): their labels, such as coulomb[1] or payload_com.x, and the matrix, symmetric with ones on its "
        "diagonal",
        "type": "object",
        "additionalProperties": False,
        "required": ["values", "matrix"],
        "properties": {
            "values": {"type": "array", "items": {"type": "string"}, "minItems": 2, "uniqueItems": True},
            "matrix": {
                "type": "array",
                "items": {"type": "array", "items": {"type": "number", "minimum": -1, "maximum": 1}},
            },
        },
    }
    return {
        "$schema": "https://json-schema.org/draft/2020-12/schema",
        "title": f"{FORMAT} version {VERSION}",
        "type": "object",
        "additionalProperties": False,
        "required": list(KEYS),
        "properties": {
            "format": {"const": FORMAT},
            "version": {"const": VERSION},
            "name": {"type": "string", "minLength": 1, "maxLength": 100},
            "geometry": {
                "type": "object",
                "additionalProperties": False,
                "required": list(GEOMETRY_FIELDS),
                "properties": {
                    k: shaped(s) | {"description": f"{doc} [{unit}]"} for k, (s, unit, doc) in GEOMETRY_FIELDS.items()
                },
            },
            "drives": {
                "type": "object",
                "additionalProperties": False,
                "required": list(drives),
                "properties": drives | sensors,
            },
            "payload": {
                "type": "object",
                "additionalProperties": False,
                "required": list(PAYLOAD_FIELDS),
                "properties": {
                    k: shaped(s) | {"description": f"{doc} [{unit}]"} for k, (s, unit, doc) in PAYLOAD_FIELDS.items()
                },
            },
            "uncertainty": {
                "description": "optional: standard errors of identified values (pusupu identify writes them)",
                "type": "object",
                "additionalProperties": False,
                "properties": uncertainty,
            },
        },
    }


def schema_text() -> str:
    """:func:`json_schema` as the text of ``pusupu_jax/schemas/pusupu-machine.schema.json``."""
    return json.dumps(json_schema(), indent=2) + "\n"
