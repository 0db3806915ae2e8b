"""Gain files: the tuned servo gains for people as well as programs, validated on load (host-side).

Schema ``pusupu-gains`` version 4, every key required, in this order (``docs/gains.md`` shows a
whole file; ``pusupu_jax/schemas/pusupu-gains.schema.json`` is its JSON Schema, :mod:`pusupu_jax.gain_schema`; a
table of it for people is :mod:`pusupu_jax.gain_view`'s)::

    schema: pusupu-gains
    version: 4
    mode: hybrid                       # the control mode the gains are for: imc | pid | pid_ff | hybrid
    machine: {name: my-robot, digest: <sha256>}   # the machine file the gains were tuned on
    controller:                        # what the controller is told: gains, limits it enforces
      position: {imc_form: full, lambda1: {value: 0.0105, unit: s, tuned: true}, ...}
      velocity: {Kv: {value: .., unit: A/(rad/s), tuned: true}, ...}
      current: {...}, limits: {...}, pid: {...}
      hybrid: {form: signed, m6: {value: .., unit: N*s/m, tuned: true}, ...}
    rates: {f_current: 20000.0, n_velocity: 5, n_position: 4, n_mech: 5, method: tustin}
    discrete:                          # each controller block at its rate: x+ = A x + B u, y = C x + D u
      current_pi: {sample_period_s: 5.0e-05, input: .., output: .., clamp: .., A: .., B: .., C: .., D: ..}
    margins: {current: {phase_margin_deg: .., gain_margin_db: ..}, velocity: .., position: ..}
    stability: {current: {spectral_radius: ..}, velocity: .., position: ..}
    provenance: {package, package_version, jax_version, mujoco_version, git_commit, created_utc, ...}
    checksum: <sha256 of everything above>

A value shared by the six axes is written once; otherwise as a list of six.  A field the
tuner moved carries ``tuned: true``.  The plant (motor, inverter, screw, friction: the ``plant`` fields
of :class:`~pusupu_jax.params.ServoParams`) is not in the file: it is the machine file's
(:mod:`pusupu_jax.machine_file`), and ``machine`` names the one the gains were tuned on by its digest.
Every check runs on the machine the caller gives (default: the built-in one).  Version 3 files
have no ``machine`` key: they were tuned on the built-in machine.  Version 2 files carried the plant
in a ``plant`` section; they are read only when that section equals the built-in plant (:func:`builtin_plant`).
:func:`migrate` rewrites either as version 4.

:func:`load` checks everything and raises :class:`~pusupu_jax.params.ParameterError` with one
line naming the problem: the schema and version, unknown and missing keys, units, kinds and
bounds of every value, that the discrete blocks are the discretisation of the gains at the
stated rates, that every loop is stable by its discrete poles and keeps at least
:data:`~pusupu_jax.stability.FLOORS` of margin (:func:`pusupu_jax.stability.check`; or the
caller's explicit floors, never thresholds read from the file) with the machine's load at home
and with every load the file records it was tuned with (:func:`tuned_loads`), and last the checksum.  The
checksum detects accidents (a truncated or edited file), not attacks: anyone can compute it.
:func:`sign` recomputes the derived blocks and the checksum of a deliberately edited file once
its gains pass the same checks.
"""

from __future__ import annotations

import dataclasses
import datetime
import hashlib
import os
import subprocess
from collections.abc import Callable, Collection, Sequence
from pathlib import Path
from typing import Any

import jax
import numpy as np
import numpy.typing as npt
import yaml

from . import __version__, inputs, loops, stability
from .files import write_atomic
from .params_file import rates_from_mapping
from . import machine_file
from .cascade import GAIN_FILE_MODES
from .gain_view import show
from .hybrid import HybridGains, gain_fields
from .lti import LTI
from .machine_file import Machine
from .params import AxisLoad, LoopRates, ParameterError, ServoParams, array_fields, static_fields
from .stability import FLOORS

SCHEMA, VERSION = "pusupu-gains", 4
KEYS = (
    "schema",
    "version",
    "mode",
    "machine",
    "controller",
    "rates",
    "discrete",
    "margins",
    "stability",
    "provenance",
    "checksum",
)
KEYS_V3 = tuple(k for k in KEYS if k != "machine")
KEYS_V2 = ("schema", "version", "mode", "controller", "plant", "rates", "discrete", "margins", "provenance", "checksum")
MODES = GAIN_FILE_MODES
CONTROLLER_SECTIONS = ("position", "velocity", "current", "limits", "pid", "hybrid")
PLANT_V2 = ("Kn", "Tn", "R", "L", "J", "Kt", "Ke", "lead", "eta")  # a version 2 file's plant section
LIMITS_SINCE_V3 = ("following_error", "following_error_time")  # limits a version 2 file lacks: the defaults

# each discrete block: where it sits in loops.Drive, its sample period (a LoopRates property), what flows
# in and out, and what clamps it
BLOCKS: dict[str, tuple[Callable[[loops.Drive], LTI], str, str, str, str]] = {
    "current_ref_filter": (
        lambda d: d.current.ref_filter,
        "dt_current",
        "current reference [A]",
        "filtered current reference [A]",
        "none",
    ),
    "current_fb_filter": (
        lambda d: d.current.fb_filter,
        "dt_current",
        "measured current [A]",
        "filtered current [A]",
        "none",
    ),
    "current_pi": (
        lambda d: d.current.pi,
        "dt_current",
        "current error [A] (filtered reference - filtered current)",
        "inverter command [V], the back-EMF feedforward emf_ff*Ke*w/Kn added",
        "sum clamped to +-V_max/Kn; integration held while the clamp and the error push the same way",
    ),
    "velocity_ref_filter": (
        lambda d: d.velocity.ref_filter,
        "dt_velocity",
        "speed reference [rad/s]",
        "filtered speed reference [rad/s]",
        "none",
    ),
    "velocity_fb_filter": (
        lambda d: d.velocity.fb_filter,
        "dt_velocity",
        "measured motor speed [rad/s]",
        "filtered speed [rad/s]",
        "none",
    ),
    "velocity_pi": (
        lambda d: d.velocity.pi,
        "dt_velocity",
        "speed error [rad/s] (filtered reference - filtered speed)",
        "current reference [A]",
        "clamped to +-I_max; integration held as for the current PI",
    ),
    "imc_c1": (lambda d: d.imc.c1, "dt_position", "motor-angle reference [rad]", "prefiltered reference [rad]", "none"),
    "imc_c2": (
        lambda d: d.imc.c2,
        "dt_position",
        "angle error [rad] (prefiltered reference - measured angle)",
        "speed reference [rad/s]",
        "none",
    ),
    "pid": (
        lambda d: d.pid,
        "dt_position",
        "angle error [rad]",
        "speed reference [rad/s] (pid_ff: plus Kff_pid times the reference's change over one period / period)",
        "none",
    ),
}


@dataclasses.dataclass(frozen=True)
class GainFile:
    """A loaded gain file: the parameter sets it describes and its document."""

    servo: ServoParams
    hybrid: HybridGains
    rates: LoopRates
    mode: str
    document: dict[str, Any]
    machine: dict[str, str]  # {name, digest} of the machine the gains were tuned on

    def tuned_on(self, machine: Machine) -> bool:
        """Whether the gains were tuned on ``machine`` (same digest)."""
        return self.machine["digest"] == machine_file.digest(machine)

    def __repr__(self) -> str:
        """The table of ``pusupu gains show`` (:func:`show`), not the document's nested dicts."""
        return "GainFile: " + show(self.document)


def margins_report(
    servo: ServoParams, mode: str = "imc", machine: Machine | None = None
) -> dict[str, dict[str, list[float]]]:
    """Phase [deg] and gain [dB] margins of every loop of every axis as lists (:func:`pusupu_jax.stability.margins`,
    single-axis model with ``machine``'s load, :func:`pusupu_jax.machine_file.axis_load`; default the built-in
    machine)."""
    m, _ = stability.margins(servo, mode, machine_file.axis_load(Machine.default() if machine is None else machine))
    return {loop: {k: v[k].tolist() for k in ("phase_margin_deg", "gain_margin_db")} for loop, v in m.items()}


def builtin_plant() -> dict[str, np.ndarray]:
    """``{field: (6,) array}`` of the plant a gain file's gains run on: the ``plant`` fields of Table 1's
    :class:`~pusupu_jax.params.ServoParams`."""
    base = ServoParams.table1()
    return {
        f.name: np.asarray(getattr(base, f.name)) for f in array_fields(ServoParams) if f.metadata["section"] == "plant"
    }


def _plain(value: Any) -> Any:
    """``value`` as YAML's safe dumper takes it: enum members (a :class:`~pusupu_jax.metrics.Metric` key, a mode) as
    their names, tuples as lists, in mappings and lists at any depth."""
    if isinstance(value, dict):
        return {_plain(k): _plain(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_plain(v) for v in value]
    if isinstance(value, str):
        return str(value)
    return value


def _compact(values: npt.ArrayLike) -> float | list[Any]:
    """A per-axis value written once when the six are equal, else as a list of six (plain floats)."""
    arr = np.asarray(values, dtype=float)
    return float(arr.flat[0]) if np.all(arr == arr.flat[0]) else arr.tolist()


# one compiled program rather than some forty operations dispatched one by one (each looked up in the compilation
# cache): seconds of every command that reads or writes a gain file
_discretize = jax.jit(loops.discretize, static_argnums=1)


def _discrete(servo: ServoParams, rates: LoopRates) -> dict[str, dict[str, Any]]:
    with jax.enable_x64(True):  # the file holds float64 coefficients, whatever the caller's JAX precision
        drive = jax.tree.map(np.asarray, _discretize(servo, rates))
    out: dict[str, dict[str, Any]] = {}
    for name, (get, period, signal_in, signal_out, clamp) in BLOCKS.items():
        block = get(drive)
        mats = {k: np.asarray(getattr(block, k)) for k in ("A", "B", "C", "D")}
        same = all(np.array_equal(m, np.broadcast_to(m[:1], m.shape)) for m in mats.values())
        coefficients = (
            {k: m[0].tolist() for k, m in mats.items()}
            if same
            else {"per_axis": [{k: m[a].tolist() for k, m in mats.items()} for a in range(6)]}
        )
        out[name] = {
            "sample_period_s": getattr(rates, period),
            "input": signal_in,
            "output": signal_out,
            "clamp": clamp,
            **coefficients,
        }
    return out


def _git_commit() -> str | None:
    try:
        r = subprocess.run(
            ["git", "rev-parse", "HEAD"], cwd=Path(__file__).parent, capture_output=True, text=True, timeout=10
        )
        dirty = subprocess.run(
            ["git", "status", "--porcelain", "--untracked-files=no"],
            cwd=Path(__file__).parent,
            capture_output=True,
            text=True,
            timeout=10,
        ).stdout.strip()
    except (OSError, subprocess.SubprocessError):
        return None
    return (r.stdout.strip() + ("-dirty" if dirty else "")) if r.returncode == 0 else None


def _versions() -> dict[str, str | None]:
    import importlib.metadata as md

    def version(name: str) -> str | None:
        try:
            return md.version(name)
        except md.PackageNotFoundError:
            return None

    return {
        "package": "pusupu_jax",
        "package_version": __version__,
        "jax_version": version("jax"),
        "mujoco_version": version("mujoco"),
        "git_commit": _git_commit(),
    }


def _checksum(text: str) -> str:
    return hashlib.sha256(text.encode()).hexdigest()


def _field(value: npt.ArrayLike, unit: str, tuned: bool) -> dict[str, Any]:
    return {"value": _compact(value), "unit": unit} | ({"tuned": True} if tuned else {})


def document(
    servo: ServoParams,
    hybrid: HybridGains,
    rates: LoopRates,
    *,
    mode: str,
    tuned: Collection[str] = (),
    provenance: dict[str, Any] | None = None,
    floors: Sequence[float] = FLOORS,
    machine: Machine | None = None,
) -> str:
    """The YAML text of a gain file for gains tuned on ``machine`` (default: the built-in one); checked first:
    raises ParameterError rather than describe gains that :func:`pusupu_jax.stability.check` refuses (with each of
    :func:`tuned_loads`: the machine's load at home, and those ``provenance`` records as ``margin_loads_kg``), or
    ``servo`` whose plant fields are not the machine's drives."""
    if mode not in MODES:
        raise ParameterError(f"gains mode: expected one of {tuple(map(str, MODES))}, got {mode!r}")
    machine = Machine.default() if machine is None else machine
    _check_plant({name: getattr(servo, name) for name in machine.drives}, "servo", machine)
    provenance = _plain(provenance or {})
    loads = tuned_loads(provenance, machine, machine_file.reference(machine))
    found = stability.check_loads(servo, hybrid, rates, mode, floors, loads, along="the paths it was tuned on")
    controller: dict[str, dict[str, Any]] = {name: {} for name in CONTROLLER_SECTIONS}
    for f in static_fields(ServoParams):
        controller[f.metadata["section"]][f.name] = getattr(servo, f.name)
    for f in array_fields(ServoParams):
        if f.metadata["section"] != "plant":
            controller[f.metadata["section"]][f.name] = _field(
                getattr(servo, f.name), f.metadata["unit"], f.name in tuned
            )
    controller["hybrid"] = {
        "form": hybrid.form,
        **{f.name: _field(float(getattr(hybrid, f.name)), f.metadata["unit"], f.name in tuned) for f in gain_fields()},
    }
    doc = {
        "schema": SCHEMA,
        "version": VERSION,
        "mode": str(mode),  # a Mode, written as its name
        "machine": machine_file.reference(machine),
        "controller": controller,
        "rates": dataclasses.asdict(rates),
        "discrete": _discrete(servo, rates),
        "margins": {loop: {k: _compact(v) for k, v in m.items()} for loop, m in found.margins().items()},
        "stability": {loop: {"spectral_radius": _compact(r)} for loop, r in found.radii().items()},
        "provenance": {
            **_versions(),
            "created_utc": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
            "tuned_fields": sorted(tuned),
            **provenance,
        },
    }
    # innermost mappings on one line
    body: str = yaml.safe_dump(doc, sort_keys=False, default_flow_style=None, width=110)
    checksum: str = yaml.safe_dump({"checksum": _checksum(body)})
    return body + checksum


def write(path: str | os.PathLike[str], servo: ServoParams, hybrid: HybridGains, rates: LoopRates, **kw: Any) -> Path:
    """:func:`document` written atomically (a crash leaves the old file)."""
    return write_atomic(path, document(servo, hybrid, rates, **kw))


def load(
    path: str | os.PathLike[str],
    floors: Sequence[float] = FLOORS,
    check_stability: bool = True,
    machine: Machine | None = None,
) -> GainFile:
    """Read and check a gain file (see the module docstring) on ``machine`` (default: the built-in one); stability
    is checked against ``floors``.

    ``check_stability=False`` leaves out :func:`pusupu_jax.stability.check`'s poles and margins (every value's bounds
    are still checked): for a diagnosis of a refused file, never to run or export its gains."""
    path = Path(path)
    text = inputs.read_text(path, "gain file", ParameterError)
    try:
        return parse(text, floors=floors, check_stability=check_stability, machine=machine)
    except ParameterError as e:
        raise ParameterError(f"{path}: {e}") from None


def parse(
    text: str,
    floors: Sequence[float] = FLOORS,
    checksum: bool = True,
    check_stability: bool = True,
    machine: Machine | None = None,
) -> GainFile:
    """:func:`load` on text; ``checksum=False`` skips the checksum and the derived blocks (for :func:`sign`)."""
    machine = Machine.default() if machine is None else machine
    doc = inputs.parse_yaml(text, "gain file", ParameterError)
    if not isinstance(doc, dict):
        raise ParameterError(f"expected a {SCHEMA} mapping, got {type(doc).__name__}")
    if doc.get("schema") != SCHEMA:
        raise ParameterError(f"schema: expected {SCHEMA!r}, got {inputs.shown(doc.get('schema'))}")
    version = doc.get("version")
    if version not in (2, 3, VERSION) or isinstance(version, bool):
        extra = (
            ": version 1 files predate the choice of IMC prefilter (they meant eq. 9 as printed); re-run pusupu tune"
            if version == 1
            else " (this pusupu_jax reads 4, and 3 and 2, tuned on the built-in machine)"
        )
        raise ParameterError(f"version: expected {VERSION}, got {inputs.shown(version)}{extra}")
    keys = {VERSION: KEYS, 3: KEYS_V3, 2: KEYS_V2}[version]
    inputs.check_keys(doc, "gain file", keys, ParameterError, required=keys)
    mode = inputs.choice(doc["mode"], "mode", MODES, ParameterError)
    tuned_on = _machine_reference(doc["machine"]) if version == VERSION else machine_file.reference(Machine.default())
    servo, hybrid = _parameters(doc, version, machine)
    names = [f.name for f in dataclasses.fields(LoopRates)]
    rates = rates_from_mapping(inputs.check_keys(doc["rates"], "rates", names, ParameterError, required=names))
    if not isinstance(doc["provenance"], dict):
        raise ParameterError(f"provenance: expected a mapping, got {type(doc['provenance']).__name__}")
    if check_stability:
        loads = tuned_loads(doc["provenance"], machine, tuned_on)
        stability.check_loads(servo, hybrid, rates, mode, floors, loads, along="the paths it was tuned on")
    else:
        stability.check_values(servo, hybrid, rates)
    if checksum:
        fresh = _discrete(servo, rates)
        inputs.check_keys(doc["discrete"], "discrete", fresh, ParameterError, required=fresh, what="block")
        for name, block in fresh.items():
            if not _same_block(doc["discrete"][name], block):
                raise ParameterError(
                    f"discrete.{name}: not the discretisation of the gains at the stated rates "
                    "(edited by hand? check the gains, then pusupu gains sign)"
                )
        if doc["checksum"] != _checksum(text[: text.rfind("checksum:")]):
            raise ParameterError(
                "checksum: does not match the content (edited or truncated file; after a deliberate "
                "edit, pusupu gains sign re-signs it once it validates)"
            )
    return GainFile(servo, hybrid, rates, mode, doc, tuned_on)


def tuned_loads(provenance: dict[str, Any], machine: Machine, tuned_on: dict[str, str]) -> dict[str, AxisLoad]:
    """The single-axis loads a gain file's margins are checked with on ``machine``: ``home``
    (:func:`~pusupu_jax.machine_file.axis_load`), then every other load its ``provenance.margin_loads_kg`` records
    the gains were tuned with (each slider's mass [kg], six values: the lightest and the heaviest pose along the tuned
    paths, :func:`~pusupu_jax.machine_file.margin_loads`), when it was tuned on ``machine`` (same digest).  On
    another machine, or with nothing recorded, home only."""
    home = machine_file.axis_load(machine)
    loads = {"home": home}
    recorded = provenance.get("margin_loads_kg")
    if recorded is None:
        return loads
    if not isinstance(recorded, dict):
        raise ParameterError(
            f"provenance.margin_loads_kg: expected a mapping of load names to masses, got {inputs.shown(recorded)}"
        )
    unknown = [name for name in recorded if name not in machine_file.MARGIN_LOADS]
    if unknown:  # on any machine: a record of other names is not one the tuner wrote
        raise ParameterError(
            f"provenance.margin_loads_kg: expected loads named from {machine_file.MARGIN_LOADS}, "
            f"got {inputs.shown(unknown[0])}"
        )
    if tuned_on["digest"] != machine_file.digest(machine):
        return loads
    for name, masses in recorded.items():
        mass = np.asarray(masses, dtype=float) if _numbers(masses) else None
        if mass is None or mass.shape != (len(home.mass),) or not np.all(np.isfinite(mass) & (mass > 0)):
            raise ParameterError(
                f"provenance.margin_loads_kg.{name}: expected {len(home.mass)} masses above 0 kg, "
                f"got {inputs.shown(masses)}"
            )
        if name != "home":
            loads[str(name)] = home.replace(mass=mass)
    return loads


def _numbers(value: Any) -> bool:
    """A list of plain numbers (no bools, strings or nested lists)."""
    return isinstance(value, list) and all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in value)


def _machine_reference(value: Any) -> dict[str, str]:
    """A gain file's ``machine``: ``{name, digest}`` (a sha256 in hex)."""
    inputs.check_keys(value, "machine", ("name", "digest"), ParameterError, required=("name", "digest"))
    if not isinstance(value["name"], str) or not value["name"]:
        raise ParameterError(f"machine.name: expected the machine's name, got {inputs.shown(value['name'])}")
    digest = value["digest"]
    if not (isinstance(digest, str) and len(digest) == 64 and all(c in "0123456789abcdef" for c in digest)):
        raise ParameterError(f"machine.digest: expected a sha256 in hex (64 characters), got {inputs.shown(digest)}")
    return {"name": value["name"], "digest": digest}


def _same_block(stored: Any, fresh: dict[str, Any]) -> bool:
    if not isinstance(stored, dict) or any(stored.get(k) != fresh[k] for k in ("sample_period_s",)):
        return False
    try:
        if "per_axis" in fresh:
            pairs = [(s[k], f[k]) for s, f in zip(stored["per_axis"], fresh["per_axis"], strict=True) for k in "ABCD"]
        else:
            pairs = [(stored[k], fresh[k]) for k in "ABCD"]
        return all(
            np.allclose(np.asarray(a, dtype=float), np.asarray(b, dtype=float), rtol=1e-12, atol=1e-15)
            for a, b in pairs
        )
    except (KeyError, TypeError, ValueError):
        return False


def _controller_fields(version: int) -> dict[str, list[str]]:
    """``{section: [field names]}`` that a file of ``version`` holds (its controller sections; version 2's plant)."""
    expected: dict[str, list[str]] = {name: [] for name in CONTROLLER_SECTIONS}
    for f in dataclasses.fields(ServoParams):
        section = f.metadata["section"]
        if section != "plant" and not (version == 2 and f.name in LIMITS_SINCE_V3):
            expected[section].append(f.name)
    expected["hybrid"] = ["form"] + [f.name for f in gain_fields()]
    if version == 2:
        expected["plant"] = list(PLANT_V2)
    return expected


def _check_plant(values: dict[str, Any], where: str, machine: Machine | None = None) -> None:
    """Refuse plant values other than ``machine``'s drives (default: the built-in plant, :func:`builtin_plant`), to
    1e-12 relative."""
    plant = builtin_plant() if machine is None else machine.drives
    for name, v in values.items():
        ours = np.asarray(plant[name], dtype=float)
        if not np.allclose(np.broadcast_to(np.asarray(v, dtype=float), ours.shape), ours, rtol=1e-12, atol=0):
            whose = "the built-in plant's" if machine is None else f"the drive of machine {machine.name!r},"
            raise ParameterError(
                f"{where}.{name}: expected {whose} {_compact(ours)!r}, got "
                f"{inputs.shown(_compact(v))} (gains tuned on another plant are not these gains)"
            )


def _parameters(doc: dict[str, Any], version: int, machine: Machine) -> tuple[ServoParams, HybridGains]:
    """The file's gains on ``machine``'s drives (the controller's values checked against the machine's ratings)."""
    expected = _controller_fields(version)
    controller = inputs.check_keys(
        doc["controller"],
        "controller",
        CONTROLLER_SECTIONS,
        ParameterError,
        required=CONTROLLER_SECTIONS,
        what="section",
    )
    sections = dict(controller, plant=doc["plant"]) if version == 2 else controller
    values, units = {}, {f.name: f.metadata["unit"] for f in array_fields(ServoParams)}
    units |= {f.name: f.metadata["unit"] for f in gain_fields()}
    for section, names in expected.items():
        where = section if section == "plant" else f"controller.{section}"
        inputs.check_keys(sections[section], where, names, ParameterError, required=names, what="field")
        for name in names:
            v = sections[section][name]
            if name in units:
                entry = inputs.check_keys(
                    v, f"{where}.{name}", ("value", "unit", "tuned"), ParameterError, required=("value", "unit")
                )
                if entry["unit"] != units[name]:
                    raise ParameterError(
                        f"{where}.{name}.unit: expected {units[name]!r}, got {inputs.shown(entry['unit'])}"
                    )
                if "tuned" in entry and not isinstance(entry["tuned"], bool):
                    raise ParameterError(
                        f"{where}.{name}.tuned: expected true or false, got {inputs.shown(entry['tuned'])}"
                    )
                v = entry["value"]
            values[name] = v
    hybrid = HybridGains.from_mapping({k: values.pop(k) for k in expected["hybrid"]})
    if version == 2:
        plant = ServoParams.from_mapping({k: values.pop(k) for k in PLANT_V2})
        try:
            _check_plant({k: getattr(plant, k) for k in PLANT_V2}, "plant")
        except ParameterError as e:
            raise ParameterError(f"{e}; a version 2 file is read only on the built-in plant") from None
    return ServoParams.from_mapping(values, base=ServoParams.table1().replace(**machine.drives)), hybrid


def sign(path: str | os.PathLike[str], floors: Sequence[float] = FLOORS, machine: Machine | None = None) -> Path:
    """Re-sign a deliberately edited gain file: its gains must pass every check on ``machine`` (default: the built-in
    one), which must be the machine the file names; the derived blocks (discrete coefficients, margins, stability)
    are recomputed and the checksum written anew (atomically, same mode and tuned marks).  A version 2 or 3 file is
    refused: :func:`migrate` converts it."""
    path = Path(path)
    machine = Machine.default() if machine is None else machine
    text = inputs.read_text(path, "gain file", ParameterError)
    try:
        g = parse(text, floors=floors, checksum=False, machine=machine)
    except ParameterError as e:
        raise ParameterError(f"{path}: {e}") from None
    if g.document["version"] != VERSION:
        raise ParameterError(
            f"{path}: version: expected {VERSION}, got {g.document['version']} (pusupu gains migrate "
            f"converts a version {g.document['version']} file)"
        )
    _check_machine(path, g, machine)
    return _rewrite(path, g, floors, "signed", machine)


def _check_machine(path: Path, g: GainFile, machine: Machine) -> None:
    """Refuse ``g`` unless it was tuned on ``machine``."""
    if not g.tuned_on(machine):
        raise ParameterError(
            f"{path}: machine: tuned on {g.machine['name']!r} (digest {g.machine['digest'][:12]}), "
            f"not on {machine.name!r} (digest {machine_file.digest(machine)[:12]}); give its machine "
            "file with --machine"
        )


def migrate(
    path: str | os.PathLike[str], out: str | os.PathLike[str] | None = None, floors: Sequence[float] = FLOORS
) -> Path:
    """Rewrite a version 2 or 3 gain file as version 4 at ``out`` (default: in its place, atomically), naming the
    built-in machine it was tuned on.

    The file must pass every check of its version (checksum included); a version 2 file's plant section must be the
    built-in plant: the plant leaves the file, and gains tuned on another plant would silently change meaning."""
    path = Path(path)
    g = load(path, floors)
    if g.document["version"] not in (2, 3):
        raise ParameterError(f"{path}: version: expected 2 or 3 to migrate, got {g.document['version']}")
    return _rewrite(Path(out) if out is not None else path, g, floors, "migrated", Machine.default())


def _rewrite(path: Path, g: GainFile, floors: Sequence[float], action: str, machine: Machine) -> Path:
    """``g`` written anew at ``path``: its gains, mode and tuned marks, and its provenance less what :func:`document`
    writes itself; ``action`` ('signed' or 'migrated') stamps when (``<action>_utc``), beside the creation time the
    file had (``created_utc_before``) and, for 'migrated', the version it came from."""
    tuned = g.document["provenance"].get("tuned_fields", [])
    provenance = {
        k: v
        for k, v in g.document["provenance"].items()
        if k not in ("tuned_fields", "created_utc") and k not in _versions()
    }
    provenance[f"{action}_utc"] = datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds")
    provenance["created_utc_before"] = g.document["provenance"].get("created_utc")
    if action == "migrated":
        provenance["migrated_from_version"] = g.document["version"]
    return write(
        path,
        g.servo,
        g.hybrid,
        g.rates,
        mode=g.mode,
        tuned=tuned,
        provenance=provenance,
        floors=floors,
        machine=machine,
    )
