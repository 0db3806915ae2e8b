"""Fig. 9a: a peg on the platform enters a chamfered hole 3 mm off its axis, in real MJX contact.

The scene (:mod:`pusupu_jax.plant.model`, ``scene='peg_in_hole'``): a 16 mm capsule peg under
the platform, a square hole of 0.5 mm clearance with 4 mm chamfers, its axis 3 mm off the
peg's in x.  The path lowers the platform 12 mm at up to 50 mm/s to about 1.2 mm over the
chamfer, crosses the chamfer at up to 5 mm/s (6 mm of descent), then goes on down at up to
20 mm/s to 35 mm (the peg's tip 28 mm below the hole's top); ``--quick`` crosses the chamfer at
10 mm/s and inserts at 30 mm/s.  Crossing the chamfer slowly matters: at 20-30 mm/s the impact
on the chamfer sets the peaks (100-150 N lateral, 500-600 N axial, with or without the law), as
no outer loop at 1 kHz acts within an impact.  Runs, Table 1 gains:

* ``IMC, stiff``: 2-DOF IMC on all six branches, nothing yields;
* ``hybrid + admittance``: the hybrid machine (branch 6 force-controlled, eq. 13-14) under the
  admittance of :mod:`pusupu_jax.compliance`: x and y are force-controlled to zero (pure
  dampers of 1.5 kN s/m), z yields with a 20 kN/m spring.  The law is ours: the paper shows
  the task, not a law;
* (full run) ``IMC + admittance``: the same law on all-IMC, to tell the law's share from the
  hybrid machine's.

Reported: the contact force history, the insertion depth (the peg's tip below the hole's top)
against time, the peak and final lateral force, whether it jams (final depth short of 90 % of
the commanded), and, in the full run, the compliant run again with every step halved.
"""

from __future__ import annotations

import numpy as np

from pusupu_jax import LoopRates
from pusupu_jax.compliance import AdmittanceGains
from pusupu_jax.machine import MachineRun
from pusupu_jax.plant.geometry import Geometry
from pusupu_jax.plant.model import HOLE, PEG, ModelOptions
from pusupu_jax.plots import save_atomic
from pusupu_jax.trajectories import platform_waypoints

from . import Result, pct
from .contact import SOLVER, force_figure, halved, run_modes, tool_point

OFFSET = (0.003, 0.0)  # m, the hole's axis from the peg's
DESCENT = 0.035  # m
# (depth [m] of the platform below home at the end of the move, peak speed [m/s]): fast to about 1.2 mm over
# the chamfer, slowly over it (the chamfer takes the 3 mm misalignment within about 4 mm of descent), then into the hole
MOVES = ((0.012, 0.05), (0.018, 0.005), (DESCENT, 0.02))
QUICK_MOVES = ((0.012, 0.05), (0.018, 0.01), (DESCENT, 0.03))
ADMITTANCE = AdmittanceGains(
    mass=np.array([6.0, 6.0, 20.0]), damping=np.array([1500.0, 1500.0, 8000.0]), stiffness=np.array([0.0, 0.0, 2e4])
)
RUNS = {
    "IMC, stiff": ("imc", None),
    "hybrid + admittance": ("hybrid", ADMITTANCE),
    "IMC + admittance": ("imc", ADMITTANCE),
}
QUICK_RUNS = ("IMC, stiff", "hybrid + admittance")
JAM_FRACTION = 0.9


def options() -> ModelOptions:
    return ModelOptions(contacts=True, scene="peg_in_hole", hole_offset=OFFSET, **SOLVER)


def path(rates: LoopRates = LoopRates(), quick: bool = False):
    """Down from home in three straight moves, at rest between them (:data:`MOVES`)."""
    moves = QUICK_MOVES if quick else MOVES
    return platform_waypoints(
        Geometry.default().home,
        [[0, 0, 0]] + [[0, 0, -z] for z, _ in moves],
        rates,
        v_max=[v for _, v in moves],
        a_max=0.1,
        hold=0.1 if quick else 0.3,
    )


def _metrics(result: MachineRun, arrays: dict) -> dict:
    home = Geometry.default().home
    home_z, hole_axis = float(home[2]), np.asarray(home[:2]) + np.asarray(OFFSET)
    tip = tool_point(arrays, PEG["bottom"] + PEG["radius"])
    depth = (home_z - HOLE["top"]) - tip[:, 2]
    force = np.asarray(arrays["contact_force"])
    lateral = np.linalg.norm(force[:, :2], axis=1)
    commanded = DESCENT - (HOLE["top"] - PEG["bottom"] - PEG["radius"])
    arrays["insertion_depth"] = depth
    return {
        "final_depth_mm": float(depth[-1] * 1e3),
        "commanded_depth_mm": commanded * 1e3,
        "jammed": bool(depth[-1] < JAM_FRACTION * commanded),
        "peak_lateral_force_n": float(lateral.max()),
        "final_lateral_force_n": float(lateral[-1]),
        "peak_axial_force_n": float(np.abs(force[:, 2]).max()),
        # the share of position periods with more than 1 N of contact force on the tool
        "periods_in_contact_fraction": float(np.mean(np.linalg.norm(force, axis=1) > 1.0)),
        # where the peg's tip ends, x and y, from the hole's axis
        "tip_from_hole_axis_final_mm": ((tip[-1, :2] - hole_axis) * 1e3).tolist(),
        "highest_branch_force_peak_n": result.metrics.highest_branch_force_peak_n,
        "wall_s": result.wall_s,
    }


def run(quick: bool = False) -> Result:
    runs = {k: v for k, v in RUNS.items() if not quick or k in QUICK_RUNS}
    results, series = run_modes(path(quick=quick), options(), runs)
    metrics = {
        "hole_offset_mm": [v * 1e3 for v in OFFSET],
        "descent_mm": DESCENT * 1e3,
        "admittance": {k: np.asarray(getattr(ADMITTANCE, k)).tolist() for k in ("mass", "damping", "stiffness")},
        "runs": {label: _metrics(results[label], series[label]) for label in runs},
    }
    stiff, soft = metrics["runs"]["IMC, stiff"], metrics["runs"]["hybrid + admittance"]
    metrics["peak_lateral_change_pct"] = pct(soft["peak_lateral_force_n"], stiff["peak_lateral_force_n"])
    if not quick:
        opts, rates = halved(options())
        label = "hybrid + admittance"
        res, arr = run_modes(path(rates), opts, {label: RUNS[label]}, rates=rates)
        fine = _metrics(res[label], arr[label])
        metrics["halved_steps"] = {
            "run": label,
            **{k: fine[k] for k in ("final_depth_mm", "peak_lateral_force_n", "final_lateral_force_n", "jammed")},
            "final_depth_change_pct": pct(fine["final_depth_mm"], metrics["runs"][label]["final_depth_mm"]),
        }
    return Result("peg_in_hole", metrics, series)


def plot(result: Result, out) -> list:
    fig = force_figure(
        result.series,
        f"Fig. 9a: peg in hole, {result.metrics['hole_offset_mm'][0]:.0f} mm off axis (real MJX contact)",
        "insertion_depth",
        "peg tip below the hole's top [mm]",
    )
    return [save_atomic(fig, out / "peg_in_hole.png")]


def table(result: Result) -> str:
    m = result.metrics
    lines = [
        f"Peg in hole, hole {m['hole_offset_mm'][0]:.1f} mm off the peg's axis, {m['descent_mm']:.0f} mm "
        "descent, Table 1 gains.",
        "",
        "| run | final depth [mm] | jammed | peak lateral [N] | final lateral [N] | peak axial [N] |",
        "|---|---|---|---|---|---|",
    ]
    for label, r in m["runs"].items():
        lines.append(
            f"| {label} | {r['final_depth_mm']:.2f} of {r['commanded_depth_mm']:.0f} | "
            f"{'yes' if r['jammed'] else 'no'} | {r['peak_lateral_force_n']:.1f} | "
            f"{r['final_lateral_force_n']:.1f} | {r['peak_axial_force_n']:.1f} |"
        )
    lines += ["", f"Peak lateral force, hybrid + admittance against IMC stiff: {m['peak_lateral_change_pct']:+.1f} %."]
    if "halved_steps" in m:
        h = m["halved_steps"]
        lines.append(
            f"Every step halved ({h['run']}): final depth {h['final_depth_mm']:.2f} mm "
            f"({h['final_depth_change_pct']:+.2f} %), peak lateral {h['peak_lateral_force_n']:.1f} N, "
            f"final lateral {h['final_lateral_force_n']:.1f} N."
        )
    return "\n".join(lines)
