"""Reference trajectories for the single-axis plant: slider positions [m] at the position-loop rate.

Every trajectory starts at rest at zero, where the simulated machine starts.
"""

from __future__ import annotations

import numpy as np

from .params import N_AXES, LoopRates, ParameterError

AXIS_TRAJECTORIES = ("step", "ramp", "sine")


def axis_reference(kind: str, rates: LoopRates = LoopRates(), duration: float | None = None) -> np.ndarray:
    """Slider reference of shape ``(N, 6)`` [m], ``N = duration / rates.dt_position``.

    * ``step``: 5 mm step at t = 0 (default 2 s);
    * ``ramp``: 50 mm/s from t = 0.1 s (default 1 s);
    * ``sine``: 10 mm amplitude, 1 Hz, ``10 mm * sin(2 pi t)`` (default 2 s).
    """
    if kind not in AXIS_TRAJECTORIES:
        raise ParameterError(f"trajectory: expected one of {AXIS_TRAJECTORIES}, got {kind!r}")
    duration = {"step": 2.0, "ramp": 1.0, "sine": 2.0}[kind] if duration is None else duration
    if not (np.isfinite(duration) and duration > 0):
        raise ParameterError(f"trajectory duration: expected a positive number of seconds, got {duration!r}")
    t = np.arange(max(1, int(round(duration / rates.dt_position)))) * rates.dt_position
    if kind == "step":
        x = np.full_like(t, 0.005)
    elif kind == "ramp":
        x = 0.05 * np.clip(t - 0.1, 0.0, None)
    else:
        x = 0.01 * np.sin(2 * np.pi * t)
    return np.repeat(x[:, None], N_AXES, axis=1)
