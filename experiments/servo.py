"""Each servo loop on its own: Bode plot of its loop gain, reference and load-torque steps, margins; Table 1 vs gains.

For the current, velocity and position loops of every axis, from the linear models of
:mod:`pusupu_jax.analysis` (python-control, continuous, the single-axis load of the built-in machine,
:func:`pusupu_jax.machine_file.axis_load`, with the drive train's viscous friction; as ``pusupu analyze``): the loop
gain
``L`` broken at the controller's output (:func:`~pusupu_jax.analysis.open_loops`) with its gain
crossover [Hz], phase crossover [Hz], phase margin [deg] and gain margin [dB]; the closed loop's
step from its reference (10-90 % rise [s], 2 % settling [s], overshoot [%], -3 dB bandwidth [Hz]);
and its response to a step of load torque ``tau_l`` on the motor shaft (reference held), the
torque of a :data:`LOAD_FORCE_N` force on the slider (``F lead / (2 pi eta)``, 0.177 N m with the
default screw), with the peak deviation of the loop's output: current [A], speed [rad/s], angle
[rad] (and slider [mm]).  The position loop is the one of ``mode``: 2-DOF IMC (``C2`` in the loop,
``C1`` in front of the step) unless the gain file names another; in ``hybrid`` mode branches 1-5
run it and branch 6 is force-controlled, so its position loop is shown for reference only.

Without ``gains`` the Table 1 gains are analysed; with a gain file of ``pusupu tune`` its gains
(and plant values) are drawn over Table 1's.  Axes with identical parameters give identical
loops: they are computed and drawn once per group (``axis_groups``, axes numbered 1-6) and the
per-axis metrics repeat the group's.  ``quick`` changes nothing: the analysis takes seconds.
"""

from __future__ import annotations

import warnings

import control as ct
import matplotlib.pyplot as plt
import numpy as np

from pusupu_jax import AxisLoad, ServoParams, analysis, machine_file
from pusupu_jax.machine_file import Machine
from pusupu_jax.params import N_AXES
from pusupu_jax.plant.axis import screw_ratio
from pusupu_jax.plots import save_atomic

from . import Result

LOAD_FORCE_N = 100.0  # N on the slider: about the branch force peaks on the paths (116-137 N, docs/tuning.md)
BODE_HZ = {"current": (1.0, 2e4), "velocity": (0.1, 2e3), "position": (0.01, 200.0)}  # Hz, plotted band
STEP_PLOT_S = {"current": 0.01, "velocity": 0.25, "position": 0.5}  # s of the reference step drawn
OUTPUT = {
    "current": (0, "i", "A", "disturbance_peak_a"),
    "velocity": (1, "w", "rad/s", "disturbance_peak_rad_s"),
    "position": (2, "theta", "rad", "disturbance_peak_rad"),
}  # output index, name, unit, metric key


def axis_groups(servo: ServoParams, load: AxisLoad) -> list[list[int]]:
    """Axes (0-based) with identical servo and load parameters, in order of their first axis."""
    groups = {}
    for k in range(N_AXES):
        key = tuple(
            sorted(
                (
                    analysis.axis_values(servo, k) | {f"load.{n}": v for n, v in analysis.axis_values(load, k).items()}
                ).items()
            )
        )
        groups.setdefault(key, []).append(k)
    return list(groups.values())


def load_torque_nm(servo: ServoParams, axis: int) -> float:
    """The motor-shaft torque [N m] of :data:`LOAD_FORCE_N` on the slider: ``F lead / (2 pi eta)``."""
    return LOAD_FORCE_N * _ratio(servo, axis) / float(np.asarray(servo.eta)[axis])


def _ratio(servo: ServoParams, axis: int) -> float:
    return float(np.asarray(screw_ratio(servo))[axis])  # m of slider per rad of motor


def analyse_axis(servo: ServoParams, load: AxisLoad, axis: int, mode: str) -> tuple[dict, dict]:
    """``({loop: metrics}, {loop: plot arrays})`` of one axis (see the module docstring)."""
    cl = analysis.closed_loops(servo, load, axis, mode=mode, load_torque=True)
    ol = analysis.open_loops(servo, load, axis, mode, closed=cl)
    metrics = analysis.axis_metrics(servo, load, axis, mode, closed=cl, phase_crossover=True)
    tau = load_torque_nm(servo, axis)
    arrays = {}
    for name, (out, _, _, key) in OUTPUT.items():
        t = np.linspace(0.0, analysis.STEP_SPAN_S[name], 30001)  # the sampling of analysis.step_metrics
        dist = tau * ct.step_response(cl[name][out, 1], t).outputs
        k = int(np.argmax(np.abs(dist)))
        metrics[name] |= {key: float(abs(dist[k])), "disturbance_peak_time_s": float(t[k])}  # |deviation|
        if name == "position":
            metrics[name]["disturbance_peak_mm"] = float(abs(dist[k]) * _ratio(servo, axis) * 1e3)
        f = np.geomspace(*BODE_HZ[name], 500)
        resp = ol[name](2j * np.pi * f)
        t_step = np.linspace(0.0, STEP_PLOT_S[name], 1001)
        arrays[name] = {
            "f_hz": f,
            "mag_db": 20 * np.log10(np.abs(resp)),
            "phase_deg": np.degrees(np.unwrap(np.angle(resp))),
            "t_step": t_step,
            "step": ct.step_response(cl[name][out, 0], t_step).outputs,
            "t_dist": t[::30],
            "dist": dist[::30],
        }
    return metrics, arrays


def analyse(servo: ServoParams, load: AxisLoad, mode: str) -> tuple[dict, dict]:
    """Metrics of every axis (computed once per :func:`axis_groups` group) and plot arrays per group."""
    per_axis, series = [None] * N_AXES, {}
    groups = axis_groups(servo, load)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # python-control's NaN comparisons where a loop has no phase crossover
        for group in groups:
            metrics, arrays = analyse_axis(servo, load, group[0], mode)
            for k in group:
                per_axis[k] = metrics
            series[("axes " if len(group) > 1 else "axis ") + _axes([k + 1 for k in group])] = arrays
    return {
        "axis_groups": [[k + 1 for k in g] for g in groups],
        "load_torque_nm": [load_torque_nm(servo, k) for k in range(N_AXES)],
        "axes": per_axis,
    }, series


def _axes(numbers) -> str:
    """``[1, 2, 3]`` as '1-3', ``[1, 4]`` as '1, 4'."""
    if len(numbers) > 2 and numbers == list(range(numbers[0], numbers[-1] + 1)):
        return f"{numbers[0]}-{numbers[-1]}"
    return ", ".join(map(str, numbers))


def run(quick: bool = False, gains=None) -> Result:
    mode = "imc" if gains is None else gains.mode
    load = machine_file.axis_load(Machine.default())  # the gain check's load: the mass a slider carries at home
    sets = {"Table 1": ServoParams.table1()} | ({} if gains is None else {"tuned": gains.servo})
    metrics = {
        "mode": mode,
        "model": "continuous, single-axis load: the mass each slider of the built-in machine "
        "carries at home (machine_file.axis_load), with the drive train's viscous friction",
        "load_force_n": LOAD_FORCE_N,
        "sets": {},
    }
    series = {}
    for label, servo in sets.items():
        metrics["sets"][label], series[label] = analyse(servo, load, mode)
    return Result("servo", metrics, series)


def _num(x, fmt=".3g"):
    return "inf" if x is None else format(x, fmt)


def plot(result: Result, out) -> list:
    m = result.metrics
    files = []
    for name, (_, signal, unit, _) in OUTPUT.items():
        fig, ax = plt.subplots(2, 2, figsize=(13, 8))
        for s, (label, groups) in enumerate(result.series.items()):
            style = ("-", "--")[s]
            for g, (axes, (group, arrays)) in enumerate(zip(m["sets"][label]["axis_groups"], groups.items())):
                row, a = m["sets"][label]["axes"][axes[0] - 1][name], arrays[name]
                color = f"C{s * len(groups) + g}"
                ax[0, 0].semilogx(
                    a["f_hz"],
                    a["mag_db"],
                    style,
                    color=color,
                    label=f"{label}, {group}: crossover {_num(row['crossover_hz'])} Hz, "
                    f"PM {_num(row['phase_margin_deg'], '.1f')} deg, "
                    f"GM {_num(row['gain_margin_db'], '.1f')} dB",
                )
                ax[1, 0].semilogx(a["f_hz"], a["phase_deg"], style, color=color)
                ax[0, 1].plot(
                    a["t_step"],
                    a["step"],
                    style,
                    color=color,
                    label=f"{label}, {group}: rise {row['rise_time_s'] * 1e3:.3g} ms, overshoot "
                    f"{row['overshoot_pct']:.3g} %",
                )
                ax[1, 1].plot(
                    a["t_dist"],
                    a["dist"],
                    style,
                    color=color,
                    label=f"{label}, {group}: peak {row[OUTPUT[name][3]]:.3g} {unit}",
                )
        ax[0, 0].axhline(0, color="k", lw=0.6)
        ax[1, 0].axhline(-180, color="k", lw=0.6)
        ax[0, 0].set_ylabel("|L| [dB]")
        ax[1, 0].set_ylabel("phase of L [deg]")
        ax[1, 0].set_xlabel("frequency [Hz]")
        ax[0, 1].set_ylabel(f"{signal} per unit reference step")
        ax[0, 1].set_xlabel("time [s]")
        ax[1, 1].set_ylabel(f"{signal} [{unit}]")
        ax[1, 1].set_xlabel("time [s]")
        ax[0, 1].set_title("reference step (closed loop)", fontsize=9)
        ax[1, 1].set_title(f"load-torque step ({LOAD_FORCE_N:g} N on the slider), reference held", fontsize=9)
        ax[0, 0].set_title(f"loop gain L, broken at the {name} controller's output", fontsize=9)
        for a in ax.flat:
            a.grid(True, which="both", alpha=0.3)
        for a in (ax[0, 0], ax[0, 1], ax[1, 1]):
            a.legend(fontsize=7)
        position = f" of mode {m['mode']}" if name == "position" else ""
        fig.suptitle(
            f"{name} loop{position}: Table 1 (solid)" + (" vs tuned (dashed)" if "tuned" in result.series else "")
        )
        fig.tight_layout()
        files.append(save_atomic(fig, out / f"servo_{name}.png"))
    return files


def table(result: Result) -> str:
    m = result.metrics
    lines = [
        f"Servo loops, continuous model, single-axis load; position loop of mode {m['mode']}; load-torque step "
        f"of {LOAD_FORCE_N:g} N on the slider ({m['sets']['Table 1']['load_torque_nm'][0]:.3f} N m on axis 1's "
        "motor with Table 1's screw).",
        "",
        "| loop | gains | axes | crossover [Hz] | phase crossover [Hz] | PM [deg] | GM [dB] | bandwidth [Hz] | "
        "rise [ms] | settling [ms] | overshoot [%] | load-torque peak | at [ms] |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for name, (_, _, unit, key) in OUTPUT.items():
        for label, s in m["sets"].items():
            for group in s["axis_groups"]:
                r = s["axes"][group[0] - 1][name]
                peak = f"{r[key]:.3g} {unit}" + (f" ({r['disturbance_peak_mm']:.3g} mm)" if name == "position" else "")
                lines.append(
                    f"| {name} | {label} | {_axes(group)} | "
                    f"{_num(r['crossover_hz'])} | {_num(r['phase_crossover_hz'])} | "
                    f"{_num(r['phase_margin_deg'], '.1f')} | {_num(r['gain_margin_db'], '.1f')} | "
                    f"{_num(r['bandwidth_hz'])} | {r['rise_time_s'] * 1e3:.3g} | "
                    f"{r['settling_time_s'] * 1e3:.3g} | {r['overshoot_pct']:.3g} | {peak} | "
                    f"{r['disturbance_peak_time_s'] * 1e3:.3g} |"
                )
    return "\n".join(lines)
