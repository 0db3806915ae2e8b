"""Timing convergence of the co-simulation: every step halved, the arc's tracking error must barely move.

Runs the arc with the 2-DOF IMC at the default steps (20 kHz current loop, 0.25 ms MJX step,
velocity and position loops at 4 kHz and 1 kHz) and with every step halved (40 kHz, 0.125 ms,
8 kHz, 2 kHz; the constraint stiffness is a physical time constant and stays 2 ms), and
reports both results and the relative change of the platform's RMS tracking error.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from pusupu_jax import LoopRates, ServoParams
from pusupu_jax.machine import simulate_machine
from pusupu_jax.metrics import Metric
from pusupu_jax.plant.geometry import Geometry
from pusupu_jax.plant.model import ModelOptions
from pusupu_jax.trajectories import platform_path

from . import Result

QUICK_S = 2.0
KEYS = (
    Metric.RMS_TRACKING_ERROR_MM,
    Metric.MAX_TRACKING_ERROR_MM,
    Metric.SYNC_ERROR_RHO,
    Metric.LOOP_CLOSURE_RESIDUAL_MAX_MM,
    "duration_s",
    "wall_s",
)


def run(quick: bool = False, trajectory: str = "arc", mode: str = "imc") -> Result:
    runs = {}
    for label, factor in (("default", 1), ("halved", 2)):
        rates = LoopRates().finer(factor)
        options = dataclasses.replace(ModelOptions(), timestep=ModelOptions().timestep / factor)
        path = platform_path(trajectory, Geometry.default().home, rates)
        if quick:
            path = path[: int(QUICK_S / rates.dt_position)]
        result, _ = simulate_machine(ServoParams.table1(), path, mode=mode, options=options, rates=rates)
        row = result.to_json()
        runs[label] = {k: row[k] for k in KEYS}
    a, b = runs["default"][Metric.RMS_TRACKING_ERROR_MM], runs["halved"][Metric.RMS_TRACKING_ERROR_MM]
    return Result(
        "timing", {"trajectory": trajectory, "mode": mode, "runs": runs, "rms_relative_change": abs(b - a) / a}
    )


def plot(result: Result, out) -> list:
    return []


def table(result: Result) -> str:
    m = result.metrics
    lines = [
        f"Timing convergence, {m['trajectory']}, {m['mode']}: every step halved.",
        "",
        "| steps | RMS [mm] | max [mm] | loop-closure residual [mm] |",
        "|---|---|---|---|",
    ]
    for label, r in m["runs"].items():
        lines.append(
            f"| {label} | {r['rms_tracking_error_mm']:.5f} | {r['max_tracking_error_mm']:.5f} | "
            f"{r['loop_closure_residual_max_mm']:.2e} |"
        )
    lines += [
        "",
        f"RMS relative change: {m['rms_relative_change'] * 100:.3f} % ({np.round(m['rms_relative_change'], 6)}).",
    ]
    return "\n".join(lines)
