"""Fig. 9b: the tool follows an unknown, slightly tilted surface while holding a normal force, in real MJX contact.

The scene (``scene='surface'``): a 10 mm tool sphere 150 mm under the platform over a work
surface tilted by 10 mrad about y (0.57 deg: 1 mm of height over the 100 mm sweep) that the
path does not know: it is planned on the level surface.  Sliding friction 0.2 (a polished
tool).  The path lowers the tool onto the nominal surface (at up to 50 mm/s, the last 3 mm at
20 mm/s), then sweeps 100 mm along x at up to 20 mm/s.  Force setpoint: 30 N pressing down,
ramped in over 0.3 s once the tool reaches the nominal surface.  ``--quick`` sweeps 20 mm.
Runs, Table 1 gains:

* ``IMC, stiff``: position control of the planned path; it holds no force, it only presses
  where the surface rises into the path;
* ``IMC + force control``: the admittance of :mod:`pusupu_jax.compliance` on z alone, a
  pure damper (K = 0), so z moves until the measured normal force equals the setpoint;
* ``hybrid + force control``: the same on the hybrid machine.

The damper is slow on purpose, ``D`` = 60 kN s/m: the contact and the IMC's integral action
make the loop from the offset to the force about 6e5 N/m stiff, and ``k / D`` (10 rad/s) must
stay well under the position loops' bandwidth, or the tool chatters on the surface.  A 1 mm/s
climb of the surface then costs ``D v`` = 60 N of force error: the sweep is slow.

Reported after the force has settled (0.5 s after the nominal contact): the normal force error
(RMS, max), contact losses (periods with under 1 N, and how many times contact was lost),
and the path error: the tool's lateral deviation from the planned path and its height over the
real surface.
"""

from __future__ import annotations

import numpy as np

from pusupu_jax import LoopRates
from pusupu_jax.compliance import AdmittanceGains
from pusupu_jax.machine import MachineRun
from pusupu_jax.plant.geometry import Geometry
from pusupu_jax.plant.model import ModelOptions
from pusupu_jax.plots import save_atomic
from pusupu_jax.trajectories import platform_waypoints

from . import Result
from .contact import SOLVER, force_figure, halved, run_modes, tool_point

TILT = 0.01  # rad
FRICTION = 0.2
FORCE = 30.0  # N
RAMP_S, SETTLE_S = 0.3, 0.5
TOOL = dict(below=0.15, radius=0.01)  # m: the tool sphere's centre under the platform, its radius
SURFACE = dict(centre_below=0.2, half_thickness=0.01)  # m: the surface box's centre under home, its half thickness
GAP = 0.03  # m: tool over the level surface at home
SWEEP, QUICK_SWEEP = 0.1, 0.02  # m
SLOW_GAP = 0.003  # m: the last of the descent, at up to 20 mm/s instead of 50
ADMITTANCE = AdmittanceGains(
    mass=np.full(3, 120.0), damping=np.full(3, 6e4), stiffness=np.zeros(3), selection=np.array([0.0, 0.0, 1.0])
)
RUNS = {
    "IMC, stiff": ("imc", None),
    "IMC + force control": ("imc", ADMITTANCE),
    "hybrid + force control": ("hybrid", ADMITTANCE),
}
QUICK_RUNS = ("IMC, stiff", "IMC + force control")
LOST_N = 1.0  # N: under this the tool counts as off the surface


def options() -> ModelOptions:
    return ModelOptions(contacts=True, scene="surface", surface_tilt=TILT, friction=FRICTION, **SOLVER)


def path_and_setpoint(rates: LoopRates = LoopRates(), quick: bool = False):
    """The platform path ``(N, 5)``, the force setpoint ``(N, 3)`` [N] and the period of the nominal contact."""
    sweep = QUICK_SWEEP if quick else SWEEP
    path = platform_waypoints(
        Geometry.default().home,
        [[0, 0, 0], [0, 0, -GAP + SLOW_GAP], [0, 0, -GAP], [sweep, 0, -GAP]],
        rates,
        v_max=[0.05, 0.02, 0.02],
        a_max=0.1,
        hold=0.2 if quick else 0.5,
    )
    touch = int(np.argmax(path[:, 2] <= Geometry.default().home[2] - GAP + 1e-12))
    setpoint = np.zeros((len(path), 3))
    setpoint[:, 2] = FORCE * np.clip((np.arange(len(path)) - touch) * rates.dt_position / RAMP_S, 0.0, 1.0)
    return path, setpoint, touch


def surface_height(x):
    """Height [m] of the tilted surface's top at world ``x`` [m] (the box turned by ``-TILT`` about y)."""
    centre = float(Geometry.default().home[2]) - SURFACE["centre_below"]
    return centre + np.asarray(x) * np.tan(TILT) + SURFACE["half_thickness"] / np.cos(TILT)


def _metrics(result: MachineRun, arrays: dict, path, setpoint, settled: int) -> dict:
    force = np.asarray(arrays["contact_force"])[settled:]
    error = force[:, 2] - setpoint[settled:, 2]
    lost = force[:, 2] < LOST_N
    centre = tool_point(arrays, TOOL["below"])
    height = centre[:, 2] - TOOL["radius"] - surface_height(centre[:, 0])
    planned = tool_point(
        {"platform": path[:, :3], "platform_mat": np.broadcast_to(np.eye(3), (len(path), 3, 3))}, TOOL["below"]
    )
    lateral = np.linalg.norm(centre[:, :2] - planned[:, :2], axis=1)[settled:]
    arrays["height_over_surface"] = height
    return {
        "force_error_rms_n": float(np.sqrt(np.mean(error**2))),
        "force_error_max_n": float(np.abs(error).max()),
        "normal_force_mean_n": float(force[:, 2].mean()),
        "normal_force_peak_n": float(force[:, 2].max()),
        "contact_lost_fraction": float(lost.mean()),
        "contact_losses": int(np.sum(lost[1:] & ~lost[:-1])),
        "lateral_path_error_rms_mm": float(np.sqrt(np.mean(lateral**2)) * 1e3),
        "height_over_surface_mm": [float(height[settled:].min() * 1e3), float(height[settled:].max() * 1e3)],
        "wall_s": result.wall_s,
    }


def run(quick: bool = False) -> Result:
    rates = LoopRates()
    path, setpoint, touch = path_and_setpoint(rates, quick)
    settled = touch + int(SETTLE_S / rates.dt_position)
    runs = {k: v for k, v in RUNS.items() if not quick or k in QUICK_RUNS}
    results, series = run_modes(path, options(), runs, force_setpoint=setpoint)
    metrics = {
        "tilt_rad": TILT,
        "friction": FRICTION,
        "force_setpoint_n": FORCE,
        "sweep_mm": path[-1, 0] * 1e3,
        "admittance": {
            k: np.asarray(getattr(ADMITTANCE, k)).tolist() for k in ("mass", "damping", "stiffness", "selection")
        },
        "runs": {label: _metrics(results[label], series[label], path, setpoint, settled) for label in runs},
    }
    if not quick:
        opts, fine_rates = halved(options(), rates)
        fine_path, fine_setpoint, fine_touch = path_and_setpoint(fine_rates)
        label = "IMC + force control"
        res, arr = run_modes(fine_path, opts, {label: RUNS[label]}, rates=fine_rates, force_setpoint=fine_setpoint)
        fine = _metrics(
            res[label], arr[label], fine_path, fine_setpoint, fine_touch + int(SETTLE_S / fine_rates.dt_position)
        )
        metrics["halved_steps"] = {
            "run": label,
            **{
                k: fine[k]
                for k in ("force_error_rms_n", "force_error_max_n", "contact_lost_fraction", "normal_force_mean_n")
            },
        }
    for a in series.values():
        a["setpoint"] = setpoint
    return Result("surface_tracking", metrics, series)


def plot(result: Result, out) -> list:
    fig = force_figure(
        result.series,
        f"Fig. 9b: {result.metrics['force_setpoint_n']:.0f} N on a surface tilted "
        f"{np.degrees(result.metrics['tilt_rad']):.2f} deg (real MJX contact)",
        "height_over_surface",
        "tool over the real surface [mm]",
    )
    for ax, a in zip(fig.axes[: len(result.series)], result.series.values()):
        ax.plot(a["t"], np.asarray(a["setpoint"])[:, 2], "k--", lw=0.8, label="Fz setpoint")
        ax.legend(fontsize=7)
    return [save_atomic(fig, out / "surface_tracking.png")]


def table(result: Result) -> str:
    m = result.metrics
    lines = [
        f"Surface tracking: {m['force_setpoint_n']:.0f} N on a surface tilted {m['tilt_rad'] * 1e3:.0f} mrad, "
        f"{m['sweep_mm']:.0f} mm sweep, friction {m['friction']}, Table 1 gains.",
        "",
        "| run | force error RMS [N] | max [N] | mean normal force [N] | periods off the surface | losses | "
        "lateral path error RMS [mm] | tool over surface [mm] |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for label, r in m["runs"].items():
        lo, hi = r["height_over_surface_mm"]
        lines.append(
            f"| {label} | {r['force_error_rms_n']:.1f} | {r['force_error_max_n']:.1f} | "
            f"{r['normal_force_mean_n']:.1f} | {r['contact_lost_fraction'] * 100:.1f} % | "
            f"{r['contact_losses']} | {r['lateral_path_error_rms_mm']:.3f} | {lo:.3f} .. {hi:.3f} |"
        )
    if "halved_steps" in m:
        h = m["halved_steps"]
        lines.append(
            f"\nEvery step halved ({h['run']}): force error RMS {h['force_error_rms_n']:.1f} N, max "
            f"{h['force_error_max_n']:.1f} N, {h['contact_lost_fraction'] * 100:.1f} % of periods off the "
            "surface."
        )
    return "\n".join(lines)
