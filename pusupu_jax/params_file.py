"""Parameter files (YAML, ``--params FILE``; host-side).

A parameter file has up to four sections, each optional; in ``servo`` and ``load`` a
scalar applies to every axis, a list gives one value per axis; SI units as documented in
``docs/parameters.md``::

    servo:   {lambda1: 0.018, Kv: [0.015, 0.015, 0.015, 0.015, 0.015, 0.02]}
    load:    {mass: 25.0, inclination: 1.5708}
    rates:   {f_current: 20000, n_velocity: 5, n_position: 4, method: tustin}
    hybrid:  {m6: 0.1, c6: 1000.0, g: 100.0, form: signed}   # eq. 14, machine-wide scalars
"""

from __future__ import annotations

import dataclasses
import os
from collections.abc import Mapping
from pathlib import Path
from typing import Any, NamedTuple

from . import inputs
from .files import read_yaml_mapping
from .hybrid import HybridGains
from .params import AxisLoad, LoopRates, ParameterError, ServoParams
from .stability import check_rates

SECTIONS = ("servo", "load", "rates", "hybrid")


class ParamsFile(NamedTuple):
    """A parameter file's sections, each at its defaults where the file leaves it out."""

    servo: ServoParams
    load: AxisLoad
    rates: LoopRates
    hybrid: HybridGains


def load_params_file(path: str | os.PathLike[str] | None = None) -> ParamsFile:
    """Read and validate a parameter file (None: every default); raises :class:`ParameterError` naming the problem."""
    if path is None:
        return ParamsFile(ServoParams.table1(), AxisLoad.default(), LoopRates(), HybridGains())
    path = Path(path)
    data = read_yaml_mapping(path, "section", SECTIONS)
    section = {name: {} if data.get(name) is None else data[name] for name in SECTIONS}
    try:
        return ParamsFile(
            ServoParams.from_mapping(section["servo"]),
            AxisLoad.from_mapping(section["load"]),
            rates_from_mapping(section["rates"]),
            HybridGains.from_mapping(section["hybrid"]),
        )
    except ParameterError as e:
        raise ParameterError(f"{path}: {e}") from None


def rates_from_mapping(values: Mapping[str, Any]) -> LoopRates:
    """A :class:`LoopRates` from a mapping of its fields (a params file's or gain file's ``rates``), checked: each
    field of its kind, and each loop's rate in its range (:func:`pusupu_jax.stability.check_rates`)."""

    where = "rates"
    inputs.check_keys(values, where, [f.name for f in dataclasses.fields(LoopRates)], ParameterError)
    out = dict(values)
    if "f_current" in out:
        out["f_current"] = inputs.number(out["f_current"], f"{where}.f_current", ParameterError, low=0.0, low_open=True)
    for name in ("n_velocity", "n_position", "n_mech"):
        if name in out:
            out[name] = inputs.integer(out[name], f"{where}.{name}", ParameterError, low=1, high=1000)
    if "method" in out:
        inputs.choice(out["method"], f"{where}.method", ("tustin", "zoh"), ParameterError)
    rates = LoopRates(**out)
    check_rates(rates)
    return rates
