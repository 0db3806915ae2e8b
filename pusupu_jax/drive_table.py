"""A drive log as a CSV table, for robots whose own controller does the logging (host-side): the layout and its
reader, which gives the same :class:`~pusupu_jax.run_log.DriveLog` as an MCAP run log.

The layout (``docs/logs.md``)::

    # mode: pid
    # trajectory: arc
    path_time_s,reference_rad_1,...,reference_rad_6,position_rad_1,...,torque_nm_6[,current_a_1,...,current_a_6]
    0.000,0.1234,...

* Comment lines ``# key: value`` before the header: ``mode`` (required: the control mode that ran), and optionally
  ``trajectory`` (the path's name or file; else ``pusupu identify --trajectory``), ``rate_hz`` (the sample rate
  [Hz]; else from the median step of ``path_time_s``), ``gain_file_checksum`` and ``source``.
* The header: ``path_time_s`` [s], the time along the path of each sample's reference, then per axis ``k`` (1 to
  6) ``reference_rad_k`` [rad] (the motor angle followed), ``position_rad_k`` [rad], ``velocity_rad_s_k`` [rad/s],
  ``torque_nm_k`` [N m] and, where the drives measure it, ``current_a_k`` [A]; columns in any order.
* One row per sample: finite numbers, ``path_time_s`` never decreasing.
"""

from __future__ import annotations

import hashlib
import os

import numpy as np

from . import inputs
from .params import ParameterError
from .run_log import LOG_LIMIT, DriveLog

AXES = 6
LAYOUT = (
    "path_time_s, then reference_rad_k, position_rad_k, velocity_rad_s_k, torque_nm_k and optionally current_a_k "
    "for k = 1 to 6, in any order (docs/logs.md)"
)
TIME = "path_time_s"
PER_AXIS = ("reference_rad", "position_rad", "velocity_rad_s", "torque_nm")  # required
OPTIONAL = ("current_a",)
KEYS = ("mode", "trajectory", "rate_hz", "gain_file_checksum", "source")


def columns(current: bool = True) -> list[str]:
    """The header's column names, in the documented order (``current``: with the measured currents)."""
    groups = PER_AXIS + (OPTIONAL if current else ())
    return [TIME] + [f"{g}_{k}" for g in groups for k in range(1, AXES + 1)]


def read(path: str | os.PathLike[str]) -> DriveLog:
    """The drive samples of the CSV drive table ``path``; :class:`~pusupu_jax.params.ParameterError` with one line
    naming the row or column for a file that is not one."""
    data = inputs.read_bytes(path, "CSV drive log", ParameterError, limit=LOG_LIMIT)
    try:
        text = data.decode("utf-8").lstrip("\ufeff")  # a spreadsheet's byte order mark
    except UnicodeDecodeError:
        raise ParameterError(f"{path}: expected a CSV drive log in UTF-8, got bytes that are not UTF-8") from None
    lines = [(n, line.strip()) for n, line in enumerate(text.splitlines(), 1) if line.strip()]
    meta: dict[str, str] = {}
    while lines and lines[0][1].startswith("#"):
        n, line = lines.pop(0)
        key, colon, value = line[1:].partition(":")
        key = key.strip()
        if not colon or key not in KEYS:
            raise ParameterError(
                f"{path}: row {n}: expected a comment '# key: value' with a key of {KEYS}, got {inputs.shown(line, 80)}"
            )
        meta[key] = value.strip()
    if "mode" not in meta:
        raise ParameterError(f"{path}: expected a comment line '# mode: ...' naming the control mode, found none")
    if not lines:
        raise ParameterError(f"{path}: expected the header {LAYOUT}, got no rows")
    n, header = lines[0]
    names = [c.strip() for c in header.split(",")]
    wanted = set(columns(False))
    allowed = set(columns(True))
    if not wanted <= set(names) or not set(names) <= allowed or len(set(names)) != len(names):
        missing = [c for c in columns(True) if c in wanted and c not in names]
        unknown = [c for c in names if c not in allowed]
        raise ParameterError(
            f"{path}: row {n}: expected the header {LAYOUT}, "
            + (f"missing {missing[0]}" if missing else f"got {inputs.shown(unknown[0] if unknown else header, 60)}")
        )
    currents = [c for c in names if c.startswith(OPTIONAL[0])]
    if currents and len(currents) != AXES:
        raise ParameterError(f"{path}: row {n}: expected current_a_1 to current_a_{AXES} or none, got {currents}")
    rows = []
    for n, line in lines[1:]:
        cells = line.split(",")
        if len(cells) != len(names):
            raise ParameterError(f"{path}: row {n}: expected {len(names)} values, got {len(cells)}")
        try:
            row = [float(c) for c in cells]
        except ValueError:
            raise ParameterError(f"{path}: row {n}: expected numbers, got {inputs.shown(line, 80)}") from None
        if not np.isfinite(row).all():
            bad = names[int(np.flatnonzero(~np.isfinite(row))[0])]
            raise ParameterError(f"{path}: row {n}: {bad}: expected a finite number, got {cells[names.index(bad)]}")
        rows.append(row)
    if len(rows) < 2:
        raise ParameterError(f"{path}: expected at least 2 samples, got {len(rows)}")
    table = np.asarray(rows)
    time = table[:, names.index(TIME)]
    back = np.flatnonzero(np.diff(time) < 0)
    if back.size:
        k = int(back[0]) + 1
        raise ParameterError(
            f"{path}: sample {k + 1}: {TIME}: expected no less than the sample before ({time[k - 1]:g} s), "
            f"got {time[k]:g} s"
        )

    def group(name: str) -> np.ndarray:
        return table[:, [names.index(f"{name}_{k}") for k in range(1, AXES + 1)]]

    steps = np.diff(time)[np.diff(time) > 0]
    if not steps.size:  # a rate_hz given does not make a log of one instant a run
        raise ParameterError(f"{path}: {TIME}: expected times that advance, got {time[0]:g} s in every sample")
    rate = meta.get("rate_hz") or str(1.0 / float(np.median(steps)))
    try:
        rate_hz = float(rate)
    except ValueError:
        rate_hz = float("nan")
    if not (np.isfinite(rate_hz) and rate_hz > 0):
        raise ParameterError(f"{path}: rate_hz: expected a positive number of samples per second, got {rate!r}")
    return DriveLog(
        path=str(path),
        digest=hashlib.sha256(data).hexdigest(),
        source=meta.get("source", "CSV drive log"),
        gain_checksum=meta.get("gain_file_checksum") or None,
        mode=meta["mode"],
        trajectory=meta.get("trajectory", ""),
        rate_hz=rate_hz,
        path_time=time,
        reference=group("reference_rad"),
        position=group("position_rad"),
        velocity=group("velocity_rad_s"),
        torque=group("torque_nm"),
        current=group("current_a") if currents else None,
    )
