"""Gain files: a versioned, validated YAML schema with units, discrete coefficients and provenance.

Schema ``pusupu-gains`` version 2 (every key required, in this order)::

    schema: pusupu-gains
    version: 2
    units: {lambda1: s, ..., m6: N*s/m, ...}      # must match exactly (SI, docs/parameters.md)
    servo: {lambda1: [6 values], ..., imc_form: full}   # every ServoParams field, one value per axis;
                                                   # imc_form (full | printed) is machine-wide
    hybrid: {m6: .., c6: .., g: .., form: signed}
    rates: {f_current: .., n_velocity: .., n_position: .., n_mech: .., method: ..}
    discrete:                                      # per axis, at those rates: x' = A x + B u, y = C x + D u
      current_pi: [{A, B, C, D} x 6]               # and velocity_pi, imc_c1, imc_c2, pid
    margins: {current|velocity|position: {phase_margin_deg: [6], gain_margin_db: [6]}}
    provenance: {package_version, created_utc, config_hash, objective_before, objective_after, ...}
    checksum: sha256 of everything above           # last: a truncated file fails here

:func:`write_gains` refuses gains that are non-finite, out of their positive ranges, or
whose loops miss the margins (``pm_min``/``gm_min``), and writes atomically (a temporary
file renamed over the target).  :func:`load_gains` checks everything, including that the
discrete coefficients are those of the continuous gains at the stated rates, and raises
:class:`~pusupu_jax.params.ParameterError` with one line naming the problem; the checksum
is checked last, so that a hand-edited bad value is named rather than reported as an edit.

:func:`write_ros2_pid` exports the PID baseline in ros2_control's ``pid`` key layout.
"""

from __future__ import annotations

import dataclasses
import datetime
import hashlib
from pathlib import Path

import jax
import numpy as np
import yaml

import pusupu_jax
from pusupu_jax import loops
from pusupu_jax.config import write_atomic
from pusupu_jax.hybrid import HybridGains, gain_fields
from pusupu_jax.margins import loop_margins
from pusupu_jax.params import (AxisLoad, LoopRates, ParameterError, ServoParams, array_fields, arrays,
                               static_fields, validate)

SCHEMA, VERSION = "pusupu-gains", 2
KEYS = ("schema", "version", "units", "servo", "hybrid", "rates", "discrete", "margins", "provenance", "checksum")
CONTROLLERS = {"current_pi": lambda d: d.current.pi, "velocity_pi": lambda d: d.velocity.pi,
               "imc_c1": lambda d: d.imc.c1, "imc_c2": lambda d: d.imc.c2, "pid": lambda d: d.pid}


def units() -> dict:
    return ({f.name: f.metadata["unit"] for f in array_fields(ServoParams)}
            | {f.name: f.metadata["unit"] for f in gain_fields()})


def _discrete(servo: ServoParams, rates: LoopRates) -> dict:
    with jax.enable_x64(True):  # the file holds float64 coefficients, whatever the caller's JAX precision
        drive = jax.tree.map(np.asarray, loops.discretize(servo, rates))
    out = {}
    for name, get in CONTROLLERS.items():
        block = get(drive)
        mats = {k: np.asarray(getattr(block, k)) for k in ("A", "B", "C", "D")}
        out[name] = [{k: m[a].tolist() for k, m in mats.items()} for a in range(6)]
    return out


def margins_report(servo: ServoParams, mode: str = "imc") -> dict:
    """Phase [deg] and gain [dB] margins of every loop of every axis, float64 host lists (``inf`` where none)."""
    with jax.enable_x64(True):
        m = loop_margins(servo, AxisLoad.default(), mode=mode)
    return {loop: {k: np.asarray(v[k]).tolist() for k in ("phase_margin_deg", "gain_margin_db")}
            for loop, v in m.items()}


def check_gains(servo: ServoParams, hybrid: HybridGains, pm_min: float, gm_min: float, mode: str = "imc") -> dict:
    """Validate values and margins; returns :func:`margins_report` or raises ParameterError."""
    validate(servo)
    HybridGains.from_mapping({}, base=hybrid)
    m = margins_report(servo, mode)
    for loop, v in m.items():
        pm, gm = np.asarray(v["phase_margin_deg"]), np.asarray(v["gain_margin_db"])
        if not (np.isfinite(pm).all() or np.isinf(pm).all()) or (pm < pm_min).any() or (gm < gm_min).any():
            a = int(np.argmin(np.minimum(pm - pm_min, gm - gm_min)))
            raise ParameterError(f"gains: the {loop} loop of axis {a + 1} has {pm[a]:.1f} deg phase margin and "
                                 f"{gm[a]:.1f} dB gain margin; expected at least {pm_min} deg and {gm_min} dB "
                                 "(unstable or too little margin: not written)")
    return m


def _checksum(text: str) -> str:
    return hashlib.sha256(text.encode()).hexdigest()


def gains_document(servo: ServoParams, hybrid: HybridGains, rates: LoopRates, provenance: dict,
                   pm_min: float = 45.0, gm_min: float = 6.0, margins: dict | None = None) -> str:
    """The YAML text of a gain file (validated: raises ParameterError rather than describe bad gains).

    ``margins``: the result of :func:`check_gains` for these gains, when the caller has it.
    """
    margins = check_gains(servo, hybrid, pm_min, gm_min) if margins is None else margins
    doc = {
        "schema": SCHEMA, "version": VERSION, "units": units(),
        "servo": {**{k: np.asarray(v, dtype=float).tolist() for k, v in arrays(servo).items()},
                  **{f.name: getattr(servo, f.name) for f in static_fields(ServoParams)}},
        "hybrid": {**{f.name: float(getattr(hybrid, f.name)) for f in gain_fields()}, "form": hybrid.form},
        "rates": dataclasses.asdict(rates), "discrete": _discrete(servo, rates), "margins": margins,
        "provenance": {"package_version": pusupu_jax.__version__,
                       "created_utc": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
                       "pm_min": pm_min, "gm_min": gm_min, **provenance},
    }
    body = yaml.safe_dump(doc, sort_keys=False)
    return body + yaml.safe_dump({"checksum": _checksum(body)})


def write_gains(path, servo: ServoParams, hybrid: HybridGains, rates: LoopRates, provenance: dict,
                pm_min: float = 45.0, gm_min: float = 6.0, margins: dict | None = None) -> None:
    write_atomic(path, gains_document(servo, hybrid, rates, provenance, pm_min, gm_min, margins))


def load_gains(path) -> tuple[ServoParams, HybridGains, LoopRates, dict]:
    """Read and check a gain file; returns ``(servo, hybrid, rates, document)``."""
    path = Path(path)
    try:
        text = path.read_text()
    except OSError as e:
        raise ParameterError(f"{path}: cannot read gain file ({e.strerror})") from None
    try:
        doc = yaml.safe_load(text)
    except yaml.YAMLError as e:
        raise ParameterError(f"{path}: not valid YAML, truncated? ({str(e).splitlines()[0]})") from None
    try:
        return _parse(doc, text) + (doc,)
    except ParameterError as e:
        raise ParameterError(f"{path}: {e}") from None


def _parse(doc, text):
    if not isinstance(doc, dict):
        raise ParameterError(f"expected a {SCHEMA} mapping, got {type(doc).__name__}")
    if doc.get("schema") != SCHEMA:
        raise ParameterError(f"schema: expected {SCHEMA!r}, got {doc.get('schema')!r}")
    if doc.get("version") == 1:
        raise ParameterError(f"version: expected {VERSION}, got 1: version 1 files predate the choice of IMC "
                             "prefilter (they meant eq. 9 as printed); re-run pusupu tune, or use its gains with "
                             "--imc-form printed in a params file")
    if doc.get("version") != VERSION:
        raise ParameterError(f"version: expected {VERSION} (this pusupu_jax reads only that), "
                             f"got {doc.get('version')!r}")
    missing = [k for k in KEYS if k not in doc]
    if missing:
        raise ParameterError(f"missing key {missing[0]!r} (truncated file?); expected {list(KEYS)}")
    unknown = sorted(set(doc) - set(KEYS))
    if unknown:
        raise ParameterError(f"unknown key {unknown[0]!r}; expected {list(KEYS)}")
    expected = units()
    if doc["units"] != expected:
        bad = sorted(k for k in set(expected) | set(doc["units"] or {})
                     if (doc["units"] or {}).get(k) != expected.get(k))[0]
        raise ParameterError(f"units.{bad}: expected {expected.get(bad)!r}, got {(doc['units'] or {}).get(bad)!r}")
    servo_fields = {f.name for f in dataclasses.fields(ServoParams)}
    if not isinstance(doc["servo"], dict) or set(doc["servo"]) != servo_fields:
        got = set(doc["servo"]) if isinstance(doc["servo"], dict) else set()
        diff = sorted((servo_fields - got) or (got - servo_fields))
        which = "missing" if servo_fields - got else "unknown"
        raise ParameterError(f"servo: expected every ServoParams field, {which} "
                             f"{diff[0] if diff else doc['servo']!r}")
    static = {f.name for f in static_fields(ServoParams)}
    for name, v in doc["servo"].items():
        if name not in static and not (isinstance(v, list) and len(v) == 6):
            raise ParameterError(f"servo.{name}: expected a list of 6 numbers (one per axis), got {v!r}")
    servo = ServoParams.from_mapping(doc["servo"])
    hybrid = HybridGains.from_mapping(doc["hybrid"] if isinstance(doc["hybrid"], dict) else {"form": doc["hybrid"]})
    try:
        rates = LoopRates(**doc["rates"])
    except TypeError as e:
        raise ParameterError(f"rates: {e}") from None
    provenance = doc["provenance"] if isinstance(doc["provenance"], dict) else {}
    check_gains(servo, hybrid, float(provenance.get("pm_min", 45.0)), float(provenance.get("gm_min", 6.0)))
    fresh = _discrete(servo, rates)
    for name, per_axis in fresh.items():
        for a, mats in enumerate(per_axis):
            try:
                stored = doc["discrete"][name][a]
                ok = all(np.allclose(np.asarray(stored[k], dtype=float), mats[k], rtol=1e-12, atol=1e-15)
                         for k in mats)
            except (KeyError, IndexError, TypeError, ValueError):
                ok = False
            if not ok:
                raise ParameterError(f"discrete.{name}[{a}]: not the discretisation of the servo gains at the "
                                     "stated rates")
    if doc["checksum"] != _checksum(text[:text.rfind("checksum:")]):
        raise ParameterError("checksum: does not match the content (edited or truncated file)")
    return servo, hybrid, rates


def write_ros2_pid(path, servo: ServoParams, joint_prefix: str = "slide_") -> None:
    """The PID baseline in ros2_control's pid key layout (one entry per slider joint).

    Units: position error [rad of motor angle] to velocity command [rad/s]; ``p`` [1/s],
    ``i`` [1/s^2], ``d`` [1] (ros2_control's plain derivative; our ``Tf_pid`` filter is
    kept in a comment-free extra key ``d_filter_time_constant`` [s]).  ``i_clamp_max``/``min``
    [rad/s] bound the integral term at the motor speed whose back-EMF reaches ``V_max``.
    """
    gains = {}
    for a in range(6):
        clamp = float(np.asarray(servo.V_max)[a] / np.asarray(servo.Ke)[a])
        gains[f"{joint_prefix}{a}"] = {
            "p": float(np.asarray(servo.Kp_pid)[a]), "i": float(np.asarray(servo.Ki_pid)[a]),
            "d": float(np.asarray(servo.Kd_pid)[a]), "i_clamp_max": clamp, "i_clamp_min": -clamp,
            "antiwindup": True, "d_filter_time_constant": float(np.asarray(servo.Tf_pid)[a])}
    write_atomic(path, yaml.safe_dump({"pid_controller": {"ros__parameters": {"gains": gains}}}, sort_keys=False))
