"""Table 1 against the gains of ``pusupu tune`` on the arc and p2p paths, in every control mode.

Both gain sets run the default machine without kinematic errors (the tuner's default scenarios),
started at rest, on the paper's arc and p2p paths, in the modes PID, PID with velocity
feedforward, IMC on all six branches and hybrid (branches 1-5 IMC, branch 6 force-controlled;
with its gain file's hybrid gains ``m6, c6, g``, Table 1 with the defaults).  Reported per path,
mode and gain set: the platform's RMS and max position error [mm], the reversal glitch (the largest
slider error within 0.1 s after a reversal of a slider's reference speed, where the drive train's
Coulomb friction changes sign: :func:`pusupu_jax.machine.reversal_error`, highest branch) [mm] and
the highest of the six branch force peaks [N], and the tuned gains' change against Table 1 [%].

The tuned gains come from ``gains`` (a gain file of ``pusupu tune``, ``--gains FILE``), or,
without it, from running the tuner here on its default configuration (``pusupu_jax.tune.config.TuneConfig``,
what ``pusupu tune`` runs; README gives its time), or on its quick one with ``quick``
(``pusupu tune --quick``).  The tuner tunes in one mode (hybrid by default) the
fields of its groups; in the other modes only the fields they use differ from Table 1 (PID and
PID + velocity feedforward: the velocity loop's ``Kv``, ``Tv``).  Not a claim of the paper.
``quick`` runs the first :data:`QUICK_S` seconds of each path.
"""

from __future__ import annotations

import dataclasses
import tempfile
from pathlib import Path

import matplotlib.pyplot as plt
import numpy as np

from pusupu_jax import LoopRates, ServoParams, workload
from pusupu_jax import gain_view, gains as gain_files
from pusupu_jax.cascade import control_mode
from pusupu_jax.hybrid import HybridGains
from pusupu_jax.machine import Scenario, machine_rates, simulate_scenarios
from pusupu_jax.metrics import Metric
from pusupu_jax.params import ParameterError
from pusupu_jax.plant.geometry import Geometry
from pusupu_jax.plots import save_atomic
from pusupu_jax.trajectories import path_seconds, platform_path

from . import Result, pct
from .arc import QUICK_S  # 3 s, as arc and p2p: two 3 s paths are the batch shape of p2p --quick (one compile)
from .p2p import MODES

PATHS = ("arc", "p2p")
SETS = ("Table 1", "tuned")
KEYS = {
    Metric.RMS_TRACKING_ERROR_MM: "RMS error [mm]",
    Metric.MAX_TRACKING_ERROR_MM: "max error [mm]",
    "highest_reversal_error_mm": "reversal glitch [mm]",
    Metric.HIGHEST_BRANCH_FORCE_PEAK_N: "highest branch force peak [N]",
}


def highest(values) -> float:
    """The largest of the branches' values that exist (NaN when none does: no branch's reference reverses)."""
    present = [v for v in values if v is not None]
    return max(present) if present else float("nan")


def tune(quick: bool = False):
    """Run ``pusupu tune`` (default or quick configuration) in a temporary folder; ``(GainFile, its source)``."""
    from pusupu_jax.tune.config import TuneConfig
    from pusupu_jax.tune.job import run_job

    cfg = TuneConfig.quick() if quick else TuneConfig()
    with tempfile.TemporaryDirectory(prefix="pusupu-tuned-") as folder:
        report, status = run_job(cfg, Path(folder))
        if status:
            raise ParameterError(f"tune: no gains exported: {report.export.error}")
        g = gain_files.load(Path(folder) / "gains.yaml", floors=(cfg.pm_min, cfg.gm_min))
    return g, {
        "source": f"pusupu tune{' --quick' if quick else ''}, run by this experiment",
        "config_hash": cfg.digest(),
        "objective_before": report.objective_before,
        "objective_after": report.objective_after,
        "tune_wall_s": report.wall_s,
    }


def changed_fields(g) -> dict:
    """``{field: {table1, tuned, unit}}`` of every gain or plant value of ``g`` that differs from Table 1."""
    base = {"hybrid": HybridGains()}
    out = {}
    for section, name, value, unit, _ in gain_view.rows(g.document):
        ref = getattr(base.get(section, ServoParams.table1()), name)
        same = (
            value == ref
            if isinstance(value, str)
            else np.allclose(np.asarray(value, float), np.asarray(ref, float), rtol=1e-12, atol=0.0)
        )
        if not same:
            out[name] = {
                "table1": ref if isinstance(ref, str) else float(np.asarray(ref).flat[0]),
                "tuned": value,
                "unit": unit,
            }
    return out


def run(quick: bool = False, gains=None) -> Result:
    if gains is None:
        gains, source = tune(quick)
    else:
        p = gains.document["provenance"]
        source = {
            "source": "gain file",
            "checksum": gains.document["checksum"],
            "created_utc": p.get("created_utc"),
            "config_hash": p.get("config_hash"),
        }
    sets = {"Table 1": (ServoParams.table1(), None, LoopRates()), "tuned": (gains.servo, gains.hybrid, gains.rates)}
    runs, series, duration = {}, {}, {}
    for set_label, (_, _, rates) in sets.items():  # every mode on both paths: bounded before any of it runs
        seconds = sum(min(QUICK_S, path_seconds(kind)) if quick else path_seconds(kind) for kind in PATHS)
        workload.check_run(
            f"experiment tuned, the {set_label} gains' rates",
            len(MODES) * seconds,
            machine_rates(rates=rates),
            machine=True,
        )
    for set_label, (servo, hybrid, rates) in sets.items():
        scenarios = []
        for kind in PATHS:
            path = platform_path(kind, Geometry.default().home, rates)
            path = path[: int(QUICK_S / rates.dt_position)] if quick else path
            duration[kind] = len(path) * rates.dt_position
            scenarios.append(Scenario(path, name=kind))
        for label, mode in MODES.items():
            # hybrid gains only in hybrid mode: a None elsewhere keeps the compiled rollout of the other experiments
            out = simulate_scenarios(
                servo, scenarios, mode=mode, rates=rates, hybrid=hybrid if control_mode(mode).hybrid else None
            )
            for sc, (r, a) in zip(scenarios, out):
                runs.setdefault(sc.name, {}).setdefault(label, {})[set_label] = {
                    k.value: r.metrics.value(k)
                    for k in (
                        Metric.RMS_TRACKING_ERROR_MM,
                        Metric.MAX_TRACKING_ERROR_MM,
                        Metric.BRANCH_FORCE_PEAK_N,
                        Metric.LOOP_CLOSURE_RESIDUAL_MAX_MM,
                        Metric.HIGHEST_BRANCH_FORCE_PEAK_N,
                    )
                } | {"highest_reversal_error_mm": highest(r.metrics.branch_reversal_error_mm)}
                series.setdefault(sc.name, {}).setdefault(label, {})[set_label] = {
                    "t": np.asarray(a["t"]),
                    "error_mm": np.linalg.norm(np.asarray(a["platform"]) - np.asarray(a["reference"]), axis=1) * 1e3,
                }
    for per_mode in runs.values():
        for r in per_mode.values():
            r["change_pct"] = {k: pct(r["tuned"][k], r["Table 1"][k]) for k in KEYS}
    tuned_mode = next(label for label, mode in MODES.items() if mode == gains.mode)
    changes = [r["change_pct"][Metric.RMS_TRACKING_ERROR_MM] for per_mode in runs.values() for r in per_mode.values()]
    metrics = {
        "duration_s": duration,
        "quick": quick,
        "start": "rest",
        "kin_errors": None,
        "gains": source
        | {
            "mode": gains.mode,
            "imc_form": gains.servo.imc_form,
            "changed": changed_fields(gains),
            "rates_as_table1": dataclasses.replace(gains.rates, n_mech=1) == LoopRates(),
        },
        "tuned_mode": tuned_mode,
        "runs": runs,
        "summary": {
            "rms_change_pct_in_tuned_mode": {
                k: runs[k][tuned_mode]["change_pct"][Metric.RMS_TRACKING_ERROR_MM] for k in PATHS
            },
            "runs_with_lower_rms": int(sum(c < 0 for c in changes)),
            "runs": len(changes),
        },
    }
    return Result("tuned", metrics, series)


def plot(result: Result, out) -> list:
    m = result.metrics
    fig = plt.figure(figsize=(19, 9))
    grid = fig.add_gridspec(2, 2 * len(KEYS))
    groups = [(kind, label) for kind in PATHS for label in MODES]
    x = np.arange(len(groups))
    for col, (key, title) in enumerate(KEYS.items()):
        ax = fig.add_subplot(grid[0, 2 * col : 2 * col + 2])
        for s, set_label in enumerate(SETS):
            values = [m["runs"][kind][label][set_label][key] for kind, label in groups]
            ax.bar(x + (s - 0.5) * 0.4, values, 0.4, label=set_label)
        for k, (kind, label) in enumerate(groups):
            r = m["runs"][kind][label]
            ax.annotate(
                f"{r['change_pct'][key]:+.0f}%", (k + 0.2, r["tuned"][key]), ha="center", va="bottom", fontsize=7
            )
        ax.set_xticks(x, [f"{kind}\n{label}" for kind, label in groups], fontsize=6, rotation=90)
        ax.set_ylabel(title)
        ax.grid(True, axis="y", alpha=0.3)
        ax.legend(fontsize=8)
    mode = m["tuned_mode"]
    for col, kind in enumerate(PATHS):
        ax = fig.add_subplot(grid[1, len(KEYS) * col : len(KEYS) * (col + 1)])
        for set_label in SETS:
            a = result.series[kind][mode][set_label]
            ax.plot(
                a["t"],
                a["error_mm"],
                lw=1,
                label=f"{set_label}: RMS {m['runs'][kind][mode][set_label]['rms_tracking_error_mm']:.3g} mm",
            )
        ax.set_yscale("log")
        ax.set_xlabel("time [s]")
        ax.set_ylabel(f"platform position error [mm], {kind}, {mode}")
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=8)
    fig.suptitle(
        f"Table 1 vs tuned gains ({m['gains']['source']}, tuned in mode {m['gains']['mode']}), "
        f"arc {m['duration_s']['arc']:.1f} s and p2p {m['duration_s']['p2p']:.1f} s, no kinematic errors"
    )
    fig.tight_layout()
    return [save_atomic(fig, out / "tuned.png")]


def table(result: Result) -> str:
    m = result.metrics
    g = m["gains"]
    changed = ", ".join(
        f"{k} {v['table1']:g} -> {_value(v['tuned'])} {v['unit']}"
        if not isinstance(v["table1"], str)
        else f"{k} {v['table1']} -> {v['tuned']}"
        for k, v in g["changed"].items()
    )
    lines = [
        f"Table 1 vs tuned gains ({g['source']}; tuned in mode {g['mode']}: {changed or 'nothing changed'}). "
        f"Arc {m['duration_s']['arc']:.1f} s, p2p {m['duration_s']['p2p']:.1f} s, no kinematic errors, "
        "start at rest.",
        "",
        "| path | mode | " + " | ".join(f"{title} Table 1 | tuned | change" for title in KEYS.values()) + " |",
        "|---|---|" + "---|---|---|" * len(KEYS),
    ]
    for kind in PATHS:
        for label, r in m["runs"][kind].items():
            cells = [f"{r['Table 1'][k]:.3f} | {r['tuned'][k]:.3f} | {r['change_pct'][k]:+.1f} %" for k in KEYS]
            lines.append(f"| {kind} | {label} | " + " | ".join(cells) + " |")
    s = m["summary"]
    lines += [
        "",
        f"In the tuned mode ({m['tuned_mode']}) the RMS error changes by "
        + " and ".join(f"{v:+.1f} % on {k}" for k, v in s["rms_change_pct_in_tuned_mode"].items())
        + f"; the tuned gains track closer in {s['runs_with_lower_rms']} of {s['runs']} path x mode runs.",
    ]
    return "\n".join(lines)


def _value(v) -> str:
    return " ".join(f"{x:.4g}" for x in v) if isinstance(v, list) else f"{v:.4g}"
