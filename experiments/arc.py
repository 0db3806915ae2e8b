"""Fig. 7: the 200 mm-radius major arc with the traditional PID, PID with velocity feedforward and the 2-DOF IMC.

Table 1 gains on the default machine, started at rest.  The IMC runs in both forms of its
prefilter (``docs/imc.md``): ``full``, the default, and ``printed`` (eq. 9 as printed).  The
paper's claim: the 2-DOF IMC tracks closer than the traditional control.  Here it must beat
both baselines, the stronger PID with velocity feedforward included.
"""

from __future__ import annotations

import matplotlib.pyplot as plt
import numpy as np

from pusupu_jax import LoopRates, ServoParams
from pusupu_jax.cascade import Mode
from pusupu_jax.machine import Scenario, simulate_scenarios
from pusupu_jax.metrics import Metric
from pusupu_jax.plant.geometry import Geometry
from pusupu_jax.plots import equal_axes_3d, save_atomic
from pusupu_jax.trajectories import platform_path

from . import Result

RUNS = {
    "PID": (Mode.PID, "full"),
    "PID + velocity FF": (Mode.PID_FF, "full"),
    "2-DOF IMC (full C1)": (Mode.IMC, "full"),
    "2-DOF IMC (printed eq. 9)": (Mode.IMC, "printed"),
}
QUICK_S = 3.0  # s of the arc in quick mode


def run(quick: bool = False) -> Result:
    path = platform_path("arc", Geometry.default().home, LoopRates())
    if quick:
        path = path[: int(QUICK_S / LoopRates().dt_position)]
    metrics, series = {"duration_s": len(path) * LoopRates().dt_position, "runs": {}}, {}
    for label, (mode, form) in RUNS.items():
        ((result, arrays),) = simulate_scenarios(
            ServoParams.table1().replace(imc_form=form), [Scenario(path)], mode=mode
        )
        row = result.to_json()
        metrics["runs"][label] = {
            k: row[k]
            for k in (
                "mode",
                "imc_form",
                Metric.RMS_TRACKING_ERROR_MM,
                Metric.MAX_TRACKING_ERROR_MM,
                Metric.BRANCH_REVERSAL_ERROR_MM,
                Metric.BRANCH_FORCE_PEAK_N,
                Metric.MOTOR_TORQUE_PEAK_NM,
                Metric.LOOP_CLOSURE_RESIDUAL_MAX_MM,
            )
        }
        series[label] = arrays
    runs = metrics["runs"]
    imc = runs["2-DOF IMC (full C1)"][Metric.RMS_TRACKING_ERROR_MM]
    best = min(runs["PID"][Metric.RMS_TRACKING_ERROR_MM], runs["PID + velocity FF"][Metric.RMS_TRACKING_ERROR_MM])
    metrics["imc_vs_best_baseline_pct"] = (imc / best - 1) * 100
    metrics["claim_imc_below_both_baselines"] = bool(imc < best)
    return Result("arc", metrics, series)


def plot(result: Result, out) -> list:
    fig = plt.figure(figsize=(13, 5.5))
    ax = fig.add_subplot(1, 2, 1, projection="3d")
    first = next(iter(result.series.values()))
    ax.plot(*(np.asarray(first["reference"]) * 1e3).T, "k--", lw=1, label="reference")
    for label, arrays in result.series.items():
        ax.plot(*(np.asarray(arrays["platform"]) * 1e3).T, lw=1, label=label)
    ax.set_xlabel("x [mm]")
    ax.set_ylabel("y [mm]")
    ax.set_zlabel("z [mm]")
    equal_axes_3d(ax, np.asarray(first["reference"]) * 1e3)
    ax.legend(fontsize=7)
    ax2 = fig.add_subplot(1, 2, 2)
    for label, arrays in result.series.items():
        err = np.linalg.norm(np.asarray(arrays["platform"]) - np.asarray(arrays["reference"]), axis=1) * 1e3
        rms = result.metrics["runs"][label][Metric.RMS_TRACKING_ERROR_MM]
        ax2.plot(arrays["t"], err, lw=1, label=f"{label}: RMS {rms:.3g} mm")
    for k, t_rev in enumerate(first["reversal_t"]):  # where a slider's Coulomb friction changes sign: the glitches
        ax2.axvline(t_rev, color="0.6", lw=0.6, ls=":", label="a slider's reference speed reverses" if k == 0 else None)
    ax2.set_yscale("log")
    ax2.set_xlabel("time [s]")
    ax2.set_ylabel("platform position error [mm]")
    ax2.grid(True, which="both", alpha=0.3)
    ax2.legend(fontsize=7)
    fig.suptitle(
        "Fig. 7: 200 mm major arc, Table 1 gains (equal axes: at this scale the paths overlap; the error is "
        "on the right)"
    )
    fig.tight_layout()
    return [save_atomic(fig, out / "arc.png")]


def table(result: Result) -> str:
    m = result.metrics
    lines = [
        f"Arc, {m['duration_s']:.1f} s, Table 1 gains, start at rest.",
        "",
        "| controller | RMS error [mm] | max error [mm] | reversal glitch, highest branch [mm] | "
        "highest branch force peak [N] |",
        "|---|---|---|---|---|",
    ]
    for label, r in m["runs"].items():
        glitch = [g for g in r[Metric.BRANCH_REVERSAL_ERROR_MM] if g is not None]
        lines.append(
            f"| {label} | {r['rms_tracking_error_mm']:.3f} | {r['max_tracking_error_mm']:.3f} | "
            f"{max(glitch) if glitch else float('nan'):.3f} | {max(r['branch_force_peak_n']):.1f} |"
        )
    lines += [
        "",
        "Reversal glitch: the largest slider error within 0.1 s after a reversal of a slider's reference "
        "speed (the drive train's Coulomb friction changes sign there).",
    ]
    lines += [
        "",
        f"2-DOF IMC (full) against the better baseline: {m['imc_vs_best_baseline_pct']:+.1f} % "
        f"({'below both' if m['claim_imc_below_both_baselines'] else 'NOT below both'}).",
    ]
    return "\n".join(lines)
