"""The JSON Schema of a gain file (``pusupu gains schema``), built from the parameter classes' metadata and shipped as
``schemas/pusupu-gains.schema.json`` for editors (a test keeps the two equal)."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path
from typing import Any

from . import gains, stability
from .gains import BLOCKS, CONTROLLER_SECTIONS, KEYS, MODES, SCHEMA, VERSION
from .hybrid import gain_fields
from .params import LoopRates, ServoParams, bounds


def json_schema() -> dict[str, Any]:
    """The JSON Schema of a gain file, built from the parameter classes' metadata (shipped as a file; a test keeps the
    two equal).  Each bounded value carries its range and the reason for it."""
    number = {"type": "number"}

    def per_axis(low: float | None = None, high: float | str | None = None) -> dict[str, Any]:
        item = (
            dict(number)
            | ({"minimum": low} if low is not None else {})
            | ({"maximum": high} if isinstance(high, (int, float)) else {})
        )
        return {"oneOf": [item, {"type": "array", "items": item, "minItems": 6, "maxItems": 6}]}

    def field_schema(f: dataclasses.Field[Any]) -> dict[str, Any]:
        b = bounds(f)
        value = per_axis(*b[:2]) if b else per_axis()
        out = {
            "type": "object",
            "required": ["value", "unit"],
            "additionalProperties": False,
            "description": f.metadata["doc"]
            + (
                f" Range {b[0]:g} to {b[1]:g}"
                if b and not isinstance(b[1], str)
                else f" Range {b[0]:g} to the plant's {b[1]}"
                if b
                else ""
            )
            + (f": {b[2]}." if b else ""),
            "properties": {"value": value, "unit": {"const": f.metadata["unit"]}, "tuned": {"type": "boolean"}},
        }
        return out

    sections: dict[str, dict[str, Any]] = {
        name: {"type": "object", "additionalProperties": False, "properties": {}, "required": []}
        for name in CONTROLLER_SECTIONS
    }
    for f in dataclasses.fields(ServoParams):
        if f.metadata["section"] == "plant":
            continue
        sec = sections[f.metadata["section"]]
        sec["properties"][f.name] = (
            {"enum": list(f.metadata["choices"])} if f.metadata.get("static") else field_schema(f)
        )
        sec["required"].append(f.name)
    sections["hybrid"]["properties"]["form"] = {"enum": ["rms", "signed"]}
    for f in gain_fields():
        sections["hybrid"]["properties"][f.name] = field_schema(f)
    sections["hybrid"]["required"] = ["form"] + [f.name for f in gain_fields()]
    matrix = {"type": "array", "items": {"type": "array", "items": number}}
    coefficients = {k: matrix for k in "ABCD"}
    block = {
        "type": "object",
        "required": ["sample_period_s", "input", "output", "clamp"],
        "properties": {
            "sample_period_s": number,
            "input": {"type": "string"},
            "output": {"type": "string"},
            "clamp": {"type": "string"},
            **coefficients,
            "per_axis": {
                "type": "array",
                "minItems": 6,
                "maxItems": 6,
                "items": {"type": "object", "properties": coefficients, "required": list("ABCD")},
            },
        },
    }
    loop = {"type": "object", "properties": {"phase_margin_deg": per_axis(), "gain_margin_db": per_axis()}}
    radius = {
        "type": "object",
        "required": ["spectral_radius"],
        "properties": {"spectral_radius": per_axis(0, 1 + stability.UNIT_CIRCLE_ROUNDING)},
        "description": "the largest eigenvalue modulus of the loop's closed-loop map over one period, at the "
        "file's rates on the machine named (pusupu_jax.stability): stable below 1 (the current and velocity "
        "loops: below 1 + 1e-9, the free speed of a drive train without viscous friction)",
    }
    rates = {
        name: (low, high, why)
        for name, (low, high, why) in (
            ("current", stability.F_CURRENT),
            ("velocity", stability.F_VELOCITY),
            ("position", stability.F_POSITION),
        )
    }
    return {
        "$schema": "https://json-schema.org/draft/2020-12/schema",
        "$id": "https://pusupu-jax/schemas/pusupu-gains.schema.json",
        "title": "pusupu gain file",
        "description": (gains.__doc__ or "").split("\n\n")[0],
        "type": "object",
        "required": list(KEYS),
        "additionalProperties": False,
        "properties": {
            "schema": {"const": SCHEMA},
            "version": {"const": VERSION},
            "mode": {"enum": [str(m) for m in MODES]},
            "machine": {
                "type": "object",
                "additionalProperties": False,
                "required": ["name", "digest"],
                "description": "the machine file the gains were tuned on (pusupu_jax.machine_file.digest)",
                "properties": {
                    "name": {"type": "string", "minLength": 1},
                    "digest": {"type": "string", "pattern": "^[0-9a-f]{64}$"},
                },
            },
            "controller": {
                "type": "object",
                "additionalProperties": False,
                "required": list(CONTROLLER_SECTIONS),
                "properties": {name: sections[name] for name in CONTROLLER_SECTIONS},
            },
            "rates": {
                "type": "object",
                "additionalProperties": False,
                "required": [f.name for f in dataclasses.fields(LoopRates)],
                "description": "; ".join(
                    f"the {k} loop's rate {lo:g} to {hi:g} Hz ({why})" for k, (lo, hi, why) in rates.items()
                ),
                "properties": {
                    "f_current": number | {"minimum": stability.F_CURRENT[0], "maximum": stability.F_CURRENT[1]},
                    "n_velocity": {"type": "integer", "minimum": 1},
                    "n_position": {"type": "integer", "minimum": 1},
                    "n_mech": {"type": "integer", "minimum": 1},
                    "method": {"enum": ["tustin", "zoh"]},
                },
            },
            "discrete": {
                "type": "object",
                "additionalProperties": False,
                "required": list(BLOCKS),
                "properties": {name: block for name in BLOCKS},
            },
            "margins": {"type": "object", "properties": {k: loop for k in ("current", "velocity", "position")}},
            "stability": {
                "type": "object",
                "required": list(stability.LOOPS),
                "properties": {k: radius for k in stability.LOOPS},
            },
            "provenance": {"type": "object"},
            "checksum": {"type": "string", "pattern": "^[0-9a-f]{64}$"},
        },
    }


SCHEMA_FILE = Path(__file__).parent / "schemas" / "pusupu-gains.schema.json"


def schema_text() -> str:
    """:func:`json_schema` as the shipped file's text."""
    return json.dumps(json_schema(), indent=2) + "\n"
