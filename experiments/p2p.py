"""Section 4 and Table 2: PID against hybrid synchronous control on (0,0,0) -> (-100,-100,0) -> (100,100,0) mm.

The simulated machine has seeded kinematic errors (0.5 mm std on rail points, platform joints
and rod lengths; the references use the nominal model), seeds 1-5, Table 1 gains, start at
rest.  The paper's claims: the platform error about 15 % below PID, the torque peak of each
branch 1-5 about 10 % below PID, and the branches balanced.  PID with velocity feedforward and
all-six IMC are run beside them.  Branch forces [N] and motor torques [N m] are both reported:
the paper's Table 2 figures (thousands of "N m") belong to another, larger machine, so only the
relative changes compare.
"""

from __future__ import annotations

import matplotlib.pyplot as plt
import numpy as np

from pusupu_jax import LoopRates, ServoParams
from pusupu_jax.cascade import Mode
from pusupu_jax.machine import MachineRun, Scenario, simulate_scenarios
from pusupu_jax.metrics import Metric
from pusupu_jax.plant.geometry import Geometry
from pusupu_jax.plant.model import ModelOptions
from pusupu_jax.plots import save_atomic
from pusupu_jax.trajectories import platform_path

from . import Result, pct

MODES = {"PID": Mode.PID, "PID + velocity FF": Mode.PID_FF, "IMC, six branches": Mode.IMC, "hybrid": Mode.HYBRID}
SEEDS = (1, 2, 3, 4, 5)
QUICK = dict(seconds=3.0, seeds=(1, 3))


def run(quick: bool = False, seeds=None) -> Result:
    seeds = tuple(seeds or (QUICK["seeds"] if quick else SEEDS))
    path = platform_path("p2p", Geometry.default().home, LoopRates())
    if quick:
        path = path[: int(QUICK["seconds"] / LoopRates().dt_position)]
    scenarios = [Scenario(path, ModelOptions(kin_error_seed=s), f"seed{s}") for s in seeds]
    runs, series = {}, {}
    for label, mode in MODES.items():
        out = simulate_scenarios(ServoParams.table1(), scenarios, mode=mode)
        runs[label] = {sc.name: _keep(r) for sc, (r, _) in zip(scenarios, out)}
        series[label] = {sc.name: a for sc, (_, a) in zip(scenarios, out)}
    pid, hyb = runs["PID"], runs["hybrid"]
    per_seed = {}
    for name in pid:
        per_seed[name] = {
            "rms_change_pct": pct(hyb[name][Metric.RMS_TRACKING_ERROR_MM], pid[name][Metric.RMS_TRACKING_ERROR_MM]),
            "highest_peak_1_5_change_pct": pct(hyb[name]["highest_peak_1_5_n"], pid[name]["highest_peak_1_5_n"]),
            "branch_peak_change_pct": [
                pct(h, p)
                for h, p in zip(hyb[name][Metric.BRANCH_FORCE_PEAK_N][:5], pid[name][Metric.BRANCH_FORCE_PEAK_N][:5])
            ],
        }
    rms = [v["rms_change_pct"] for v in per_seed.values()]
    peak = [v["highest_peak_1_5_change_pct"] for v in per_seed.values()]
    branch = np.array([v["branch_peak_change_pct"] for v in per_seed.values()])
    metrics = {
        "duration_s": len(path) * LoopRates().dt_position,
        "seeds": list(seeds),
        "runs": runs,
        "hybrid_vs_pid": per_seed,
        "summary": {
            "rms_change_pct_mean": float(np.mean(rms)),
            "rms_change_pct_range": [min(rms), max(rms)],
            "seeds_rms_at_least_15pct_lower": int(sum(r <= -15 for r in rms)),
            "highest_peak_1_5_change_pct_mean": float(np.mean(peak)),
            "highest_peak_1_5_change_pct_range": [min(peak), max(peak)],
            "seeds_highest_peak_at_least_10pct_lower": int(sum(p <= -10 for p in peak)),
            "branch_peak_change_pct_mean": branch.mean(axis=0).tolist(),
            "branches_lower_on_every_seed": [bool((branch[:, b] < 0).all()) for b in range(5)],
        },
    }
    return Result("p2p", metrics, series)


def _keep(run: MachineRun) -> dict:
    r = run.metrics
    peaks = r.branch_force_peak_n
    return {
        Metric.RMS_TRACKING_ERROR_MM: r.rms_tracking_error_mm,
        Metric.MAX_TRACKING_ERROR_MM: r.max_tracking_error_mm,
        Metric.BRANCH_FORCE_PEAK_N: peaks,
        Metric.MOTOR_TORQUE_PEAK_NM: r.motor_torque_peak_nm,
        "highest_peak_1_5_n": max(peaks[:5]),
        "balance_max_over_min_1_5": max(peaks[:5]) / min(peaks[:5]),
        Metric.LOOP_CLOSURE_RESIDUAL_MAX_MM: r.loop_closure_residual_max_mm,
    }


def plot(result: Result, out) -> list:
    m = result.metrics
    fig, axes = plt.subplots(1, 2, figsize=(13, 4.8))
    width = 0.8 / len(MODES)
    for k, label in enumerate(MODES):
        peaks = np.array([r[Metric.BRANCH_FORCE_PEAK_N] for r in m["runs"][label].values()])
        axes[0].bar(
            np.arange(6) + 1 + (k - len(MODES) / 2 + 0.5) * width,
            peaks.mean(axis=0),
            width,
            yerr=[peaks.mean(0) - peaks.min(0), peaks.max(0) - peaks.mean(0)],
            capsize=2,
            label=label,
        )
    axes[0].set_xlabel("branch (6: the redundant one, force-controlled in hybrid mode)")
    axes[0].set_ylabel("branch force peak [N] (mean, min-max over seeds)")
    axes[0].legend(fontsize=8)
    axes[0].grid(True, axis="y", alpha=0.3)
    seed = next(iter(m["runs"]["PID"]))
    for label in MODES:
        a = result.series[label][seed]
        err = np.linalg.norm(np.asarray(a["platform"]) - np.asarray(a["reference"]), axis=1) * 1e3
        axes[1].plot(a["t"], err, lw=1, label=f"{label}: RMS {m['runs'][label][seed]['rms_tracking_error_mm']:.3g} mm")
    axes[1].set_xlabel("time [s]")
    axes[1].set_ylabel(f"platform position error [mm], {seed}")
    axes[1].grid(True, alpha=0.3)
    axes[1].legend(fontsize=8)
    fig.suptitle("Section 4 / Table 2: p2p path with seeded kinematic errors, Table 1 gains")
    fig.tight_layout()
    return [save_atomic(fig, out / "p2p.png")]


def table(result: Result) -> str:
    m = result.metrics
    s = m["summary"]
    lines = [
        f"p2p, {m['duration_s']:.1f} s, seeded kinematic errors (seeds {m['seeds']}), Table 1 gains.",
        "",
        "| mode | seed | RMS [mm] | max [mm] | force peaks, branches 1-6 [N] | highest 1-5 | max/min 1-5 |",
        "|---|---|---|---|---|---|---|",
    ]
    for label, per in m["runs"].items():
        for seed, r in per.items():
            lines.append(
                f"| {label} | {seed} | {r['rms_tracking_error_mm']:.3f} | {r['max_tracking_error_mm']:.3f} | "
                + " ".join(f"{x:.1f}" for x in r[Metric.BRANCH_FORCE_PEAK_N])
                + f" | {r['highest_peak_1_5_n']:.1f} | {r['balance_max_over_min_1_5']:.2f} |"
            )
    lines += [
        "",
        "Table 2 shape: force peak of branches 1-5 [N], mean over seeds (motor torque = force x r / eta).",
        "",
        "| mode | branch 1 | branch 2 | branch 3 | branch 4 | branch 5 |",
        "|---|---|---|---|---|---|",
    ]
    for label in ("PID", "hybrid"):
        peaks = np.mean([r[Metric.BRANCH_FORCE_PEAK_N][:5] for r in m["runs"][label].values()], axis=0)
        lines.append(f"| {label} | " + " | ".join(f"{x:.1f}" for x in peaks) + " |")
    lines.append("| change | " + " | ".join(f"{x:+.1f} %" for x in s["branch_peak_change_pct_mean"]) + " |")
    lines += [
        "",
        f"Hybrid against PID: RMS error {s['rms_change_pct_mean']:+.1f} % on average "
        f"(range {s['rms_change_pct_range'][0]:+.1f} to {s['rms_change_pct_range'][1]:+.1f} %), at least 15 % "
        f"lower on {s['seeds_rms_at_least_15pct_lower']} of {len(m['seeds'])} seeds; highest branch 1-5 force "
        f"peak {s['highest_peak_1_5_change_pct_mean']:+.1f} % on average, at least 10 % lower on "
        f"{s['seeds_highest_peak_at_least_10pct_lower']} of {len(m['seeds'])} seeds.",
    ]
    return "\n".join(lines)
