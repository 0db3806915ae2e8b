"""A gain file for people: its values as a table (:func:`show`: ``pusupu gains show``) and the values two files disagree
on (:func:`diff`: ``pusupu gains diff``), from a gain document (:attr:`pusupu_jax.gains.GainFile.document`)."""

from __future__ import annotations

from typing import Any

import numpy as np


def rows(doc: dict[str, Any]) -> list[tuple[str, str, object, str, bool]]:
    """``(section, field, value, unit, tuned)`` of every gain (and a version 2 file's plant value), in file order."""
    out = []
    for section, fields in list(doc["controller"].items()) + [("plant", doc.get("plant", {}))]:
        for name, v in fields.items():
            if isinstance(v, dict):
                out.append((section, name, v["value"], v["unit"], bool(v.get("tuned"))))
            else:
                out.append((section, name, v, "", False))
    return out


def show(doc: dict[str, Any]) -> str:
    """A gain file as a table for people: sections, values (six when they differ), units, what was tuned."""
    machine = doc.get("machine", {"name": "built-in (version 3 or older)", "digest": ""})
    lines = [
        f"{doc['schema']} v{doc['version']}, mode {doc['mode']}, rates {doc['rates']['f_current']:g} Hz current / "
        f"{doc['rates']['n_velocity']} / {doc['rates']['n_position']} ({doc['rates']['method']})",
        f"tuned on machine {machine['name']!r}" + (f" (digest {machine['digest'][:12]})" if machine["digest"] else ""),
        f"{'section':<9} {'field':<10} {'value':<44} {'unit':<12} tuned",
    ]
    for section, name, value, unit, tuned in rows(doc):
        text = (
            " ".join(f"{x:.6g}" for x in value)
            if isinstance(value, list)
            else f"{value:.6g}"
            if isinstance(value, float)
            else str(value)
        )
        lines.append(f"{section:<9} {name:<10} {text:<44} {unit:<12} {'yes' if tuned else ''}")
    for loop, m in doc["margins"].items():
        pm, gm = np.min(m["phase_margin_deg"]), np.min(m["gain_margin_db"])
        lines.append(f"margins   {loop:<10} {pm:.1f} deg, {gm:.1f} dB (smallest over the axes)")
    for loop, st in doc.get("stability", {}).items():
        lines.append(
            f"poles     {loop:<10} largest modulus {np.max(st['spectral_radius']):.6f} over one period (stable below 1)"
        )
    p = doc["provenance"]
    lines.append(
        f"made by {p.get('package')} {p.get('package_version')} (jax {p.get('jax_version')}, mujoco "
        f"{p.get('mujoco_version')}, commit {p.get('git_commit')}) at {p.get('created_utc')}"
    )
    return "\n".join(lines)


def diff(a: dict[str, Any], b: dict[str, Any]) -> list[str]:
    """The values two gain documents disagree on, one line each (empty when their gains and rates are equal)."""
    left, right = ({(s, n): (v, u) for s, n, v, u, _ in rows(d)} for d in (a, b))
    out = []
    for key in sorted(set(left) | set(right)):
        if left.get(key) != right.get(key):
            unit = left[key][1] if key in left else right[key][1]
            out.append(f"{key[0]}.{key[1]}: {left.get(key, ('-', ''))[0]} -> {right.get(key, ('-', ''))[0]} {unit}")
    for k in sorted(set(a["rates"]) | set(b["rates"])):
        if a["rates"].get(k) != b["rates"].get(k):
            out.append(f"rates.{k}: {a['rates'].get(k)} -> {b['rates'].get(k)}")
    if a["mode"] != b["mode"]:
        out.append(f"mode: {a['mode']} -> {b['mode']}")
    return out
