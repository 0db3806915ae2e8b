"""Do the linear models match the MJX machine?  Loop gains measured by injection against the models.

The single-axis model (:mod:`pusupu_jax.analysis`, ``pusupu analyze``) sees each axis as a motor
driving one lumped mass; the MJX machine's six sliders drive one 5-DOF platform together, which the coupled model
(:mod:`pusupu_jax.coupled`, ``pusupu analyze --coupled``: the six cascades on the mechanism linearised at the pose)
takes in.
Here the velocity and position loops of a machine (the built-in one by default, with Table 1's
gains; a machine file, ``pusupu experiment loop_match --machine FILE``, with the start gains derived
for it; mode 'imc', drive-train friction off: ``coulomb = viscous = 0``) are measured at two poses,
and compared with the single-axis model of two loads, the lumped :class:`~pusupu_jax.params.AxisLoad` of 20 kg
and the mass the slider carries at the pose (:func:`pusupu_jax.plant.dynamics.reflected_mass`:
54.7 kg at home on the built-in machine), and with the coupled model at the pose (its velocity loop broken as the
machine's is, ``velocity_in_position``).  On another machine the frequency grids move with the
model's crossover (:func:`_band_scale`).

Measurement (:mod:`pusupu_jax.injection`): from rest at the pose, held by the drives, one axis's
loop gets a small sine at its controller's output, at :data:`GRID` frequencies around its
crossover (one vmapped batch per loop, both poses together); every loop of every axis stays
closed, the other five holding their position.  ``L = -Y/X`` at each frequency over whole
periods after the transient (:data:`SETTLE_S`).  Amplitudes (:data:`AMPLITUDE`): 0.05 A at the
current reference (0.5 % of ``I_max``) and 0.5 rad/s at the velocity reference move the slider by
0.2-0.3 mm (a three-thousandth of the rods' 0.9 m, so the mechanism's geometry stays linear), keep
every controller far from its clamp (current references below 0.2 A against 10 A), and are some
twelve orders of magnitude above float64's rounding.  That it is linear there is measured: the run
at the middle frequency is repeated at twice the amplitude (``linearity``: the change of ``L``).
That the transient has died away is measured too: ``L`` over the second half of the window against
the whole (``settling``).

The model is broken where the machine is: the position loop at its controller's output
(:func:`pusupu_jax.analysis.open_loops`), the velocity loop at the current reference with the
axis's own position loop closed (:func:`model_loops`: ``Gv (Gw P_w + Gxv C2 P_theta)``, what the
running machine's velocity controller returns; :func:`~pusupu_jax.analysis.open_loops` opens that
position loop, which moves the crossover by 1.5-3.5 % and the margin by 1.5-3 deg, also reported).
The same injections on the single-axis plant (:class:`~pusupu_jax.plant.AxisPlant`, carried mass)
show what the sampled, multirate loop alone changes against the continuous model (``sampled``).

A model matches when crossover and phase margin agree within :data:`TOLERANCE`: 10 % and 5 deg.  The
measurement agrees with python-control to 1e-5 on a linear plant (``tests/test_loop_match.py``) and the
sampled, multirate loop moves the continuous model by less than 1 % and 1 deg here, so the tolerance is
left to what the model leaves out.  It is tighter than the difference between the two loads (about 30 %
and 7 deg in the velocity loop), so that it can tell them apart, and a margin known to 5 deg is what a
45 deg margin check needs.
"""

from __future__ import annotations

import functools
import re
import warnings

import jax
import matplotlib.pyplot as plt
import numpy as np
from matplotlib.ticker import FuncFormatter, LogLocator, NullFormatter

from pusupu_jax import AxisLoad, LoopRates, ServoParams, analysis, coupled, injection, machine_file, margins
from pusupu_jax.machine import machine_plant, machine_rates
from pusupu_jax.machine_file import Machine
from pusupu_jax.params import stack
from pusupu_jax.plant import AxisPlant
from pusupu_jax.plant.dynamics import reflected_mass
from pusupu_jax.plant.geometry import Geometry
from pusupu_jax.plots import save_atomic
from pusupu_jax.chunked import run_chunked
from pusupu_jax.sim import rollout
from pusupu_jax.start_gains import derive

from . import Result

POSES = {"home": (0.0, 0.0, 0.0, 0.0, 0.0), "home + (0.1, 0.1, 0) m": (0.1, 0.1, 0.0, 0.0, 0.0)}  # offsets from home
PROBES = (("home", 0), ("home + (0.1, 0.1, 0) m", 0), ("home + (0.1, 0.1, 0) m", 2))  # (pose, axis 0-based)
LOOPS = ("velocity", "position")
GRID = {"velocity": (3.0, 30.0, 12), "position": (0.4, 4.0, 12)}  # Hz, Hz, count: around crossover
AMPLITUDE = {"velocity": 0.05, "position": 0.5}  # A at the current reference, rad/s at the velocity reference
SETTLE_S = {"velocity": 1.0, "position": 6.0}  # s before the window
DURATION_S = {"velocity": 2.0, "position": 16.0}  # s of each run
TOLERANCE = {"crossover_pct": 10.0, "phase_margin_deg": 5.0}
COUPLED_LOOP = {"velocity": "velocity_in_position", "position": "position"}  # the coupled model's loop at the break
QUICK = dict(
    probes=(("home", 0),),
    count=3,
    duration_s={"velocity": 1.5, "position": 8.0},
    settle_s={"velocity": 0.75, "position": 4.0},
    band={"velocity": (6.0, 12.0), "position": (0.8, 1.6)},
)


def servo(machine: Machine | None = None) -> ServoParams:
    """The gains on ``machine`` (default the built-in one: Table 1; another: the start gains derived for it,
    :func:`pusupu_jax.start_gains.derive`) with the drive train's friction off."""
    if machine is None or machine_file.is_builtin(machine):
        gains = ServoParams.table1()
    else:
        gains = derive(machine)[0]
    return gains.replace(coulomb=np.zeros(6), viscous=np.zeros(6))


def geometry_at(pose: str, machine: Machine | None = None) -> Geometry:
    """The machine's geometry (default the built-in one's) assembled at the pose ``POSES[pose]`` (its ``home``),
    where the runs start."""
    geom = Geometry.default() if machine is None else machine.geometry
    return geom.replace(home=np.asarray(geom.home) + np.asarray(POSES[pose]))


def model_loops(params: ServoParams, mass: float, axis: int) -> dict:
    """The single-axis model's loop gains at the machine's breaks, continuous (python-control), with ``mass`` [kg].

    ``velocity``: at the current reference with the position loop closed, ``Gv (Gw P_w + Gxv C2 P_theta)``
    (``P``: the closed current loop from ``i_ref`` to speed and angle); ``velocity_open``: the same with the
    position loop open (:func:`~pusupu_jax.analysis.open_loops`, ``pusupu analyze``'s); ``position``: at the
    velocity reference.
    """
    load = AxisLoad.default().replace(mass=np.full(6, float(mass)))
    b = analysis.blocks(params, load, axis)
    closed = analysis.closed_loops(params, load, axis)
    p = closed["current"]
    opened = analysis.open_loops(params, load, axis, closed=closed)
    return {
        "velocity": b["Gv"] * (b["Gw"] * p[1, 0] + b["Gxv"] * b["C2"] * p[2, 0]),
        "velocity_open": opened["velocity"],
        "position": opened["position"],
    }


def _margins(sys) -> dict:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # python-control's NaN comparisons where a loop has no phase crossover
        m = analysis.margins(sys)
    return {"crossover_hz": m["crossover_hz"], "phase_margin_deg": m["phase_margin_deg"]}


@functools.lru_cache(maxsize=None)
def _axis_program(rates: LoopRates):
    """The single-axis plant's injection runs, vmapped over references (load shared), jitted."""
    return jax.jit(
        jax.vmap(functools.partial(rollout, plant=AxisPlant(), rates=rates, outer="imc"), in_axes=(None, None, 0))
    )


def _runs(probes, loop, freqs, duration_s, rates):
    """The injections of one loop: per probe each frequency, then the middle one (near crossover) at twice the
    amplitude."""
    n = int(round(duration_s / rates.dt_position))
    runs = []
    for pose, axis in probes:
        for f in list(freqs) + [None]:
            scale = 2.0 if f is None else 1.0
            f = freqs[len(freqs) // 2] if f is None else f
            runs.append(
                ((pose, axis), f, injection.injected(np.zeros((n, 6)), loop, axis, f, scale * AMPLITUDE[loop], rates))
            )
    return runs


def _gains(traces, runs, loop, rates, settle_s):
    """``(L, L over the window's second half)`` of each run (traces batched like ``runs``)."""
    out = []
    for b, ((_, axis), f, inj) in enumerate(runs):
        trace = jax.tree.map(lambda x: np.asarray(x)[b], traces)
        half_s = (len(trace.t) * rates.dt_position - settle_s) / 2
        out.append(
            (
                injection.loop_gain(trace, inj, loop, axis, f, rates, settle_s),
                injection.loop_gain(trace, inj, loop, axis, f, rates, settle_s + half_s),
            )
        )
    return out


def _band_scale(params: ServoParams, machine: Machine, loop: str) -> float:
    """How far the loop's crossover on ``machine`` (the model, carried mass at home, axis 1) lies from the built-in
    machine's with Table 1: the frequency grid moves by this factor (1 on the built-in machine)."""

    def crossover(p, m):
        return _margins(model_loops(p, float(reflected_mass(m.geometry, m.geometry.home, m.options())[0][0]), 0)[loop])[
            "crossover_hz"
        ]

    return crossover(params, machine) / crossover(servo(), Machine.default())


def run(quick: bool = False, machine: Machine | None = None) -> Result:
    """The measurement on ``machine`` (default the built-in one; its gains: :func:`servo`)."""
    machine = Machine.default() if machine is None else machine
    params = servo(machine)
    options = machine.options()
    rates = machine_rates(options, LoopRates())
    probes = QUICK["probes"] if quick else PROBES
    duration = QUICK["duration_s"] if quick else DURATION_S
    settle = QUICK["settle_s"] if quick else SETTLE_S
    plant = machine_plant(options)
    poses = sorted({pose for pose, _ in probes}, key=list(POSES).index)
    models = {pose: plant.variant(options, geometry_at(pose, machine)) for pose in poses}
    carried = {pose: reflected_mass(machine.geometry, geometry_at(pose, machine).home, options)[0] for pose in poses}
    mechanisms = {
        pose: coupled.Mechanism.at(machine.geometry, geometry_at(pose, machine).home, options) for pose in poses
    }
    coupled_margins = {pose: coupled.loop_margins(params, mechanisms[pose]) for pose in poses}
    gains = "Table 1" if machine_file.is_builtin(machine) else "the start gains derived for it"
    metrics = {
        "machine": machine_file.reference(machine),
        "gains": f"{gains}, mode imc, coulomb = viscous = 0",
        "tolerance": TOLERANCE,
        "amplitude": {"velocity_a": AMPLITUDE["velocity"], "position_rad_s": AMPLITUDE["position"]},
        "settle_s": settle,
        "duration_s": duration,
        "rows": [],
    }
    series = {}
    for loop in LOOPS:
        band = np.asarray(QUICK["band"][loop] if quick else GRID[loop][:2])
        if not machine_file.is_builtin(machine):
            band = band * _band_scale(params, machine, loop)
        freqs = injection.grid(*band, QUICK["count"] if quick else GRID[loop][2], rates)
        runs = _runs(probes, loop, freqs, duration[loop], rates)
        inj = stack([r[2] for r in runs])
        traces, _ = run_chunked(
            params, stack([models[pose] for (pose, _), _, _ in runs]), inj, plant=plant, rates=rates, outer="imc"
        )
        measured = _gains(traces, runs, loop, rates, settle[loop])
        per = len(freqs) + 1
        for p, (pose, axis) in enumerate(probes):
            mine = measured[p * per : (p + 1) * per]
            trace = jax.tree.map(lambda x: np.asarray(x)[p * per : (p + 1) * per], traces)
            mass = float(carried[pose][axis])
            axis_runs = runs[p * per : (p + 1) * per - 1]  # the same injections on the single-axis plant
            axis_traces = _axis_program(rates)(
                params, AxisLoad.default().replace(mass=np.full(6, mass)), stack([r[2] for r in axis_runs])
            )
            sampled = [g for g, _ in _gains(axis_traces, axis_runs, loop, rates, settle[loop])]
            L = np.array([g for g, _ in mine[:-1]])
            m20, mc = model_loops(params, 20.0, axis), model_loops(params, mass, axis)
            mine_coupled = COUPLED_LOOP[loop]
            key = f"{pose}, axis {axis + 1}, {loop}"
            row = {
                "pose": pose,
                "pose_offset": list(POSES[pose]),
                "loop": loop,
                "axis": axis + 1,
                "carried_mass_kg": mass,
                "frequencies_hz": freqs.tolist(),
                "model_20kg": _margins(m20[loop]),
                "model_carried": _margins(mc[loop]),
                "model_coupled": margins.in_units(coupled_margins[pose][mine_coupled], axis),
                "mjx": injection.crossover(freqs, L),
                "sampled_single_axis": injection.crossover(freqs, sampled),
                "linearity": abs(mine[-1][0] / mine[len(freqs) // 2][0] - 1.0),
                "settling": max(abs(b / a - 1.0) for a, b in mine[:-1]),
                "peak_current_reference_a": float(np.abs(trace.current_reference[..., axis]).max()),
                "peak_slider_deviation_mm": float(np.abs(trace.position[..., axis]).max() * 1e3),
            }
            if loop == "velocity":
                row |= {
                    "model_20kg_position_open": _margins(m20["velocity_open"]),
                    "model_carried_position_open": _margins(mc["velocity_open"]),
                    "model_coupled_position_open": margins.in_units(coupled_margins[pose]["velocity"], axis),
                }
            for label in ("model_20kg", "model_carried", "model_coupled"):
                row[f"{label}_matches"] = _matches(row[label], row["mjx"])
            metrics["rows"].append(row)
            fine = np.geomspace(freqs[0] / 1.5, freqs[-1] * 1.5, 300)
            series[key] = {
                "f_hz": freqs,
                "mjx": L,
                "sampled": np.array(sampled),
                "f_model_hz": fine,
                "model_20kg": m20[loop](2j * np.pi * fine),
                "model_carried": mc[loop](2j * np.pi * fine),
                "model_coupled": np.asarray(
                    coupled.loop_gains(params, mechanisms[pose], 2 * np.pi * fine)[mine_coupled][axis]
                ),
                "carried_mass_kg": mass,
            }
    return Result("loop_match", metrics, series)


def _matches(model: dict, measured: dict) -> bool | None:
    """Whether ``model``'s crossover and phase margin agree with ``measured``'s within :data:`TOLERANCE`."""
    if None in (model["crossover_hz"], measured["crossover_hz"]):
        return None
    return bool(
        abs(model["crossover_hz"] / measured["crossover_hz"] - 1.0) * 100.0 <= TOLERANCE["crossover_pct"]
        and abs(model["phase_margin_deg"] - measured["phase_margin_deg"]) <= TOLERANCE["phase_margin_deg"]
    )


def plot(result: Result, out) -> list:
    """One Bode figure per pose and axis: measured (MJX, and the sampled single-axis plant) against the models."""
    files = []
    keys = {}
    for key, s in result.series.items():
        keys.setdefault(key.rsplit(", ", 1)[0], {})[key.rsplit(", ", 1)[1]] = s
    for probe, loops in keys.items():
        fig, ax = plt.subplots(2, len(loops), figsize=(6.5 * len(loops), 7.5), squeeze=False)
        for c, (loop, s) in enumerate(loops.items()):
            for label, L, style in (
                ("model, 20 kg", s["model_20kg"], "--"),
                (f"model, carried {s['carried_mass_kg']:.1f} kg", s["model_carried"], "-"),
                ("coupled model", s["model_coupled"], "-."),
            ):
                ax[0, c].semilogx(s["f_model_hz"], 20 * np.log10(np.abs(L)), style, label=label)
                ax[1, c].semilogx(s["f_model_hz"], injection.unwrapped_deg(L), style)
            for label, L, marker in (
                ("MJX machine, measured", s["mjx"], "o"),
                ("single-axis plant (carried), measured", s["sampled"], "x"),
            ):
                ax[0, c].semilogx(s["f_hz"], 20 * np.log10(np.abs(L)), marker, label=label)
                ax[1, c].semilogx(s["f_hz"], injection.unwrapped_deg(L), marker)
            ax[0, c].axhline(0, color="k", lw=0.6)
            ax[1, c].axhline(-180, color="k", lw=0.6)
            ax[0, c].set_title(f"{loop} loop, broken at {injection.BREAKS[loop]}", fontsize=8)
            ax[0, c].set_ylabel("|L| [dB]")
            ax[1, c].set_ylabel("phase of L [deg]")
            ax[1, c].set_xlabel("frequency [Hz]")
            ax[0, c].legend(fontsize=8)
            for a in ax[:, c]:
                a.grid(True, which="both", alpha=0.3)
                a.xaxis.set_major_locator(LogLocator(subs=(1.0, 2.0, 5.0)))
                a.xaxis.set_major_formatter(FuncFormatter(lambda x, _: f"{x:g}"))
                a.xaxis.set_minor_formatter(NullFormatter())
        fig.suptitle(
            f"Loop gains, {probe}: MJX machine {result.metrics['machine']['name']!r} against the linear models",
            fontsize=10,
        )
        fig.tight_layout()
        files.append(save_atomic(fig, out / f"loop_match_{re.sub('[^a-z0-9]+', '_', probe.lower()).strip('_')}.png"))
    return files


def _num(x, fmt="#.3g"):
    return "none" if x is None else format(x, fmt)


def _cell(m: dict) -> str:
    return f"{_num(m['crossover_hz'])} Hz, {_num(m['phase_margin_deg'], '.1f')} deg"


def table(result: Result) -> str:
    m = result.metrics
    tol = m["tolerance"]
    lines = [
        f"Loop gains of the MJX machine {m['machine']['name']!r} measured by injection ({m['gains']}) against the "
        "single-axis model with two loads and the coupled model; "
        f"a model matches (yes) when crossover is within {tol['crossover_pct']:g} % and phase margin within "
        f"{tol['phase_margin_deg']:g} deg of the measured.",
        "",
        "| pose | loop | axis | model 20 kg | match | model carried mass | match | coupled model | match | "
        "MJX measured | single-axis sampled (carried) | linearity | settling |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    yes = {True: "yes", False: "no", None: "n/a"}
    for r in m["rows"]:
        lines.append(
            f"| {r['pose']} | {r['loop']} | {r['axis']} | {_cell(r['model_20kg'])} | "
            f"{yes[r['model_20kg_matches']]} | {r['carried_mass_kg']:.1f} kg: {_cell(r['model_carried'])} | "
            f"{yes[r['model_carried_matches']]} | {_cell(r['model_coupled'])} | {yes[r['model_coupled_matches']]} | "
            f"{_cell(r['mjx'])} | {_cell(r['sampled_single_axis'])} | "
            f"{r['linearity']:.1e} | {r['settling']:.1e} |"
        )
    lines += [
        "",
        "The velocity loop's model is broken where the machine is, the axis's position loop closed; with it "
        "open (`pusupu analyze`):",
    ]
    for r in m["rows"]:
        if r["loop"] == "velocity":
            lines.append(
                f"- {r['pose']}, axis {r['axis']}: 20 kg {_cell(r['model_20kg_position_open'])}; "
                f"{r['carried_mass_kg']:.1f} kg {_cell(r['model_carried_position_open'])}; "
                f"coupled {_cell(r['model_coupled_position_open'])}"
            )
    return "\n".join(lines)
