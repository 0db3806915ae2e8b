"""Hybrid mode across lambda2, with seeded kinematic errors: does it stay stable wherever IMC is?

lambda2 runs from the smallest value whose loops keep 45 deg and 6 dB (the position loop of
the single-axis model, ``pusupu_jax.margins``; found by bisection) to 0.3 s, with lambda1 =
lambda2 and lambda1 = 0.018 s (Table 1), seeds 1-5, on the p2p path, each grid point a member
of one vmapped batch.  It runs twice: with the default ``m6`` (branch 6 damped like its own
velocity loop, ``docs/hybrid.md``) and with the old ``m6 = 0.1 N s/m``, which diverged at
fast lambda2.  A run counts as diverged when the platform error exceeds 20 mm or a branch
force 1 kN (the stable runs stay under 5 mm and 130 N).

The machine runs without its drive train's friction (:func:`frictionless`): friction damps branch
6's oscillation, so it would hide the instability these runs look for, and the hybrid gains' bounds
taken from them (``docs/safety.md``) must hold on the least damped machine.  With the default
friction, the old ``m6`` on the whole p2p path (seed 3, the smallest lambda2, lambda1 = lambda2)
stays at 0.61 mm RMS, 1.48 mm max and 137 N; without it, 38.9 mm, 65.7 mm and 2382 N.
"""

from __future__ import annotations

import matplotlib.pyplot as plt
import numpy as np
from scipy.optimize import brentq

from pusupu_jax import AxisLoad, LoopRates, ServoParams
from pusupu_jax.hybrid import HybridGains, gain_fields
from pusupu_jax.machine import Scenario, simulate_scenarios
from pusupu_jax.margins import loop_margins
from pusupu_jax.metrics import Metric
from pusupu_jax.params import stack
from pusupu_jax.plant.geometry import Geometry
from pusupu_jax.plant.model import ModelOptions
from pusupu_jax.plots import save_atomic
from pusupu_jax.trajectories import platform_path

from . import Result

PM_MIN, GM_MIN = 45.0, 6.0
LAMBDA2_MAX = 0.3
DIVERGED_MM, DIVERGED_N = 20.0, 1000.0
SWEEP_DIVERGED_MM = 2.0  # the gain sweep's runs are 3 s of p2p from rest: the stable ones stay under 1 mm
OLD_M6 = 0.1


def frictionless() -> ServoParams:
    """Table 1 on the built-in drives without their friction (``coulomb = viscous = 0``)."""
    return ServoParams.table1().replace(coulomb=np.zeros(6), viscous=np.zeros(6))


def smallest_lambda2(servo: ServoParams = None, load: AxisLoad = None) -> float:
    """The smallest lambda2 [s] whose position loop keeps PM_MIN and GM_MIN (every other loop is unaffected by it)."""
    servo = servo or ServoParams.table1()
    load = load or AxisLoad.default()

    def slack(l2):
        m = loop_margins(servo.replace(lambda2=np.full(6, l2)), load, "imc")["position"]
        return min(float(m["phase_margin_deg"][0]) - PM_MIN, float(m["gain_margin_db"][0]) - GM_MIN)

    return float(brentq(slack, 0.02, 0.05, xtol=1e-5)) + 1e-5  # just inside: both margins at or above


def run(quick: bool = False) -> Result:
    l2_min = smallest_lambda2()
    lambdas = [l2_min, 0.3] if quick else list(np.geomspace(l2_min, LAMBDA2_MAX, 6))
    seeds = (3,) if quick else (1, 2, 3, 4, 5)
    path = platform_path("p2p", Geometry.default().home, LoopRates())
    if quick:
        path = path[:3000]
    rows = []
    for m6 in (HybridGains().m6, OLD_M6):
        for l1_rule in ("lambda1 = lambda2", "lambda1 = 0.018"):
            grid = [(l2, s) for l2 in lambdas for s in seeds]
            servo = stack(
                [
                    frictionless().replace(
                        lambda2=np.full(6, l2), lambda1=np.full(6, l2 if l1_rule[-1] == "2" else 0.018)
                    )
                    for l2, _ in grid
                ]
            )
            scenarios = [Scenario(path, ModelOptions(kin_error_seed=s), f"seed{s}") for _, s in grid]
            out = simulate_scenarios(servo, scenarios, mode="hybrid", hybrid=HybridGains(m6=m6))
            for (l2, s), (r, _) in zip(grid, out):
                m = r.metrics
                rms, mx, peak = m.rms_tracking_error_mm, m.max_tracking_error_mm, m.highest_branch_force_peak_n
                rows.append(
                    {
                        "m6": m6,
                        "rule": l1_rule,
                        "lambda2": l2,
                        "seed": s,
                        Metric.RMS_TRACKING_ERROR_MM: rms,
                        Metric.MAX_TRACKING_ERROR_MM: mx,
                        "highest_force_peak_n": peak,
                        "diverged": bool(not np.isfinite(rms) or mx > DIVERGED_MM or peak > DIVERGED_N),
                    }
                )
    sweep = [] if quick else gain_sweep(path[:SWEEP_SAMPLES], l2_min)
    default = [r for r in rows if r["m6"] == HybridGains().m6]
    worst = max(default, key=lambda r: r[Metric.MAX_TRACKING_ERROR_MM])
    metrics = {
        "duration_s": len(path) * LoopRates().dt_position,
        "lambda2_min": l2_min,
        "lambda2": lambdas,
        "seeds": list(seeds),
        "m6_default": HybridGains().m6,
        "rows": rows,
        "default_m6_diverged": int(sum(r["diverged"] for r in default)),
        "old_m6_diverged": int(sum(r["diverged"] for r in rows if r["m6"] == OLD_M6)),
        "runs_per_m6": len(default),
        "worst_default": worst,
        "gain_sweep": sweep,
    }
    return Result("hybrid_grid", metrics)


SWEEP = {
    "m6": (1.0, 10.0, 15.0, 20.0, 30.0, 50.0, 100.0),
    "c6": (1.0, 100.0, 1e3, 2e3, 3e3, 5e3, 1e4),
    "g": (1.0, 1e2, 1e3, 1e4, 1e5),
}  # multiples of each default
SWEEP_SEED = 3
SWEEP_SAMPLES = 3000  # the first 3 s of p2p, as the quick grid


def gain_sweep(path, l2_min: float) -> list:
    """Each hybrid gain alone at multiples of its default (:data:`SWEEP`), the others at theirs, at lambda2 = 0.15 s
    (Table 1) and ``l2_min``, seed :data:`SWEEP_SEED`: one row per run, diverged as in the lambda2 grid.  What bounds
    the gains a gain file may hold (:data:`pusupu_jax.hybrid.HYBRID_BOUNDS_WHY`)."""
    base = HybridGains()
    grid = [(name, k, l2) for l2 in (0.15, l2_min) for name, ks in SWEEP.items() for k in ks]
    hybrid = HybridGains(
        **{name: np.array([getattr(base, name) * (k if n == name else 1.0) for n, k, _ in grid]) for name in SWEEP}
    )
    servo = stack([frictionless().replace(lambda2=np.full(6, l2)) for *_, l2 in grid])
    scenarios = [Scenario(path, ModelOptions(kin_error_seed=SWEEP_SEED), f"seed{SWEEP_SEED}") for _ in grid]
    rows = []
    for (name, k, l2), (r, _) in zip(grid, simulate_scenarios(servo, scenarios, mode="hybrid", hybrid=hybrid)):
        m = r.metrics
        rms, mx, peak = m.rms_tracking_error_mm, m.max_tracking_error_mm, m.highest_branch_force_peak_n
        rows.append(
            {
                "gain": name,
                "value": float(getattr(base, name) * k),
                "lambda2": l2,
                Metric.RMS_TRACKING_ERROR_MM: rms,
                Metric.MAX_TRACKING_ERROR_MM: mx,
                "highest_force_peak_n": peak,
                "diverged": bool(not np.isfinite(rms) or mx > SWEEP_DIVERGED_MM or peak > DIVERGED_N),
            }
        )
    return rows


def plot(result: Result, out) -> list:
    m = result.metrics
    fig, axes = plt.subplots(1, 2, figsize=(12, 4.5))
    for ax, key, unit in (
        (axes[0], Metric.MAX_TRACKING_ERROR_MM, "max platform error [mm]"),
        (axes[1], "highest_force_peak_n", "highest branch force peak [N]"),
    ):
        for m6, style in ((m["m6_default"], "-"), (OLD_M6, ":")):
            for rule, marker in (("lambda1 = lambda2", "o"), ("lambda1 = 0.018", "s")):
                rows = [r for r in m["rows"] if r["m6"] == m6 and r["rule"] == rule]
                l2 = sorted({r["lambda2"] for r in rows})
                worst = [max(r[key] for r in rows if r["lambda2"] == x) for x in l2]
                ax.plot(l2, worst, style, marker=marker, label=f"m6 = {m6:g} N s/m, {rule}")
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_xlabel("lambda2 [s]")
        ax.set_ylabel(f"{unit}, worst seed")
        ax.grid(True, which="both", alpha=0.3)
    axes[0].axhline(DIVERGED_MM, color="k", lw=0.8)
    axes[1].axhline(DIVERGED_N, color="k", lw=0.8)
    axes[0].legend(fontsize=7)
    fig.suptitle(
        f"Hybrid mode on p2p with seeded errors, lambda2 from {m['lambda2_min']:.4f} s (45 deg, 6 dB) to 0.3 s"
    )
    fig.tight_layout()
    return [save_atomic(fig, out / "hybrid_grid.png")]


def table(result: Result) -> str:
    m = result.metrics
    lines = [
        f"Hybrid mode, p2p ({m['duration_s']:.1f} s), seeds {m['seeds']}; smallest admissible lambda2 "
        f"{m['lambda2_min']:.4f} s.",
        "",
        "| m6 [N s/m] | lambda1 | lambda2 [s] | worst RMS [mm] | worst max [mm] | worst force peak [N] | diverged |",
        "|---|---|---|---|---|---|---|",
    ]
    keys = sorted({(r["m6"], r["rule"], r["lambda2"]) for r in m["rows"]}, key=lambda k: (-k[0], k[1], k[2]))
    for m6, rule, l2 in keys:
        rows = [r for r in m["rows"] if (r["m6"], r["rule"], r["lambda2"]) == (m6, rule, l2)]
        lines.append(
            f"| {m6:g} | {rule.split(' = ')[1]} | {l2:.4f} | {max(r['rms_tracking_error_mm'] for r in rows):.3f}"
            f" | {max(r['max_tracking_error_mm'] for r in rows):.3f} | "
            f"{max(r['highest_force_peak_n'] for r in rows):.1f} | {sum(r['diverged'] for r in rows)}"
            f"/{len(rows)} |"
        )
    w = m["worst_default"]
    if m.get("gain_sweep"):
        lines += [
            "",
            f"Each hybrid gain alone, the others at their defaults (seed {SWEEP_SEED}, both lambda2): the "
            "largest value at which no run diverged, the smallest at which one did, and the bound a gain file "
            "may hold.",
            "",
            "| gain | largest stable | smallest diverged | bound |",
            "|---|---|---|---|",
        ]
        for name in SWEEP:
            rows = [r for r in m["gain_sweep"] if r["gain"] == name]
            values = sorted({r["value"] for r in rows})
            bad = [v for v in values if any(r["diverged"] for r in rows if r["value"] == v)]
            good = [v for v in values if not bad or v < bad[0]]
            bound = [f.metadata["bounds"][1] for f in gain_fields() if f.name == name][0]
            lines.append(f"| {name} | {good[-1]:g} | {f'{bad[0]:g}' if bad else 'none'} | {bound:g} |")
    lines += [
        "",
        f"Default m6: {m['default_m6_diverged']} of {m['runs_per_m6']} runs diverged; worst error "
        f"{w['max_tracking_error_mm']:.3f} mm max ({w['rms_tracking_error_mm']:.3f} mm RMS) at lambda2 = "
        f"{w['lambda2']:.4f} s, {w['rule']}, seed {w['seed']}.  Old m6 = {OLD_M6}: {m['old_m6_diverged']} of "
        f"{m['runs_per_m6']} diverged.",
    ]
    return "\n".join(lines)
