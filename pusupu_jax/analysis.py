"""Linear analysis of the servo loops with python-control (host-side, float64).

The transfer functions are written here from the paper's equations, independently of
the JAX code in :mod:`pusupu_jax.loops`, so that they can serve as its test oracle.
For one axis:

* :func:`blocks`: every continuous block (eq. 1-9, motor, screw and load);
* :func:`closed_loops`: the closed current, velocity and position loops (inputs
  ``i_ref`` [A], ``w_ref`` [rad/s], ``th_ref`` [rad], and with ``load_torque=True`` a load
  torque ``tau_l`` [N m] on the motor shaft; outputs ``i``, ``w``, ``theta``),
  continuous, or discrete at the loop rates when ``rates`` is given (controllers sampled
  with ``rates.method``, the physical parts with a zero-order hold, each inner loop
  resampled to its outer loop's rate by :func:`hold_resample`);
* :func:`open_loops`: the loop gains broken at each controller output, for margins;
* :func:`loop_metrics` (:func:`axis_metrics` for one axis): crossover, phase and gain margins,
  closed-loop bandwidth and step metrics (:func:`step_metrics`);
* :func:`identify_T0` / :func:`kt_for_T0`: the velocity loop's first-order time
  constant identified from a step test (the ``T0`` that C2 models) and the torque
  constant that yields it.

The physical model includes the back-EMF, so the "current" open loop here is the one
the drive really has; :func:`current_open_loop_locked` is the paper's R-L form.
"""

from __future__ import annotations

import math
from typing import Any, cast

import control as ct
import numpy as np
import numpy.typing as npt
from scipy.optimize import brentq, minimize_scalar

from .cascade import Law, control_mode
from .params import N_AXES, AxisLoad, LoopRates, ServoParams, arrays

LOOPS = ("current", "velocity", "position")


def axis_values(p: ServoParams | AxisLoad, axis: int) -> dict[str, float]:
    """Plain floats of one axis of a parameter set."""
    return {k: float(np.asarray(v)[..., axis]) for k, v in arrays(p).items()}


def _sys(tf: ct.TransferFunction, inputs: str, outputs: str) -> ct.StateSpace:
    return ct.ss(tf, inputs=inputs, outputs=outputs)


def blocks(servo: ServoParams, load: AxisLoad, axis: int = 0) -> dict[str, ct.StateSpace]:
    """Continuous blocks of one axis as named python-control state-space systems."""
    p, q = axis_values(servo, axis), axis_values(load, axis)
    r = p["lead"] / (2 * math.pi)
    j_eff = p["J"] + q["mass"] * r**2 / p["eta"]
    b_eff = p["viscous"] * r**2 / p["eta"]
    l1, l2, T0 = p["lambda1"], p["lambda2"], p["T0"]
    elec = ct.ss(
        [[-1 / p["Tn"], 0], [1 / p["L"], -p["R"] / p["L"]]],
        [[p["Kn"] / p["Tn"], 0], [0, -p["Ke"] / p["L"]]],
        [[0, 1]],
        [[0, 0]],
        inputs=["u", "w"],
        outputs=["i"],
        name="electrical",
    )
    mech = ct.ss(
        [[0, 1], [0, -b_eff / j_eff]],
        [[0], [1 / j_eff]],
        np.eye(2),
        np.zeros((2, 1)),
        inputs=["tau"],
        outputs=["theta", "w"],
        name="mechanics",
    )
    return {
        "Gxi": _sys(ct.tf([1], [p["Tcf"], 1]), "i_ref", "i_r"),
        "Gcf": _sys(ct.tf([p["Kcf"]], [p["Tcf"], 1]), "i", "i_f"),
        "Gi": _sys(ct.tf([p["Ki"] * p["Ti"], p["Ki"]], [p["Ti"], 0]), "e_i", "u_pi"),
        "EMF": ct.ss([], [], [], [[p["emf_ff"] * p["Ke"] / p["Kn"]]], inputs="w", outputs="u_ff"),
        "u": ct.summing_junction(inputs=["u_pi", "u_ff"], output="u"),
        "Kt": ct.ss([], [], [], [[p["Kt"]]], inputs="i", outputs="tau"),
        "electrical": elec,
        "mechanics": mech,
        "Gxv": _sys(ct.tf([1], [p["Tw"], 1]), "w_ref", "w_r"),
        "Gw": _sys(ct.tf([p["Kw"]], [p["Tw"], 1]), "w", "w_f"),
        "Gv": _sys(ct.tf([p["Kv"] * p["Tv"], p["Kv"]], [p["Tv"], 0]), "e_w", "i_ref"),
        "C1": _sys(imc_c1(l1, l2, servo.imc_form), "th_ref", "r1"),
        "C2": _sys(ct.tf(np.polymul([3 * l2, 1], [T0, 1]), np.polymul([3 * l2**2, 0], [l2 / 3, 1])), "e_p", "w_ref"),
        "PID": _sys(
            ct.tf([p["Kp_pid"]], [1]) + ct.tf([p["Ki_pid"]], [1, 0]) + ct.tf([p["Kd_pid"], 0], [p["Tf_pid"], 1]),
            "e_p",
            "w_ref",
        ),
    }


FF_LAG_S = 0.5e-3  # s: half the default position period, the lag of the pid_ff backward difference


def velocity_feedforward(servo: ServoParams, axis: int, rates: LoopRates | None = None) -> ct.StateSpace:
    """The pid_ff feedforward ``th_ref -> w_ff``: exactly ``Kff (1 - z^-1)/dt`` at the position rate when ``rates``
    is given, else its continuous stand-in ``Kff s/(FF_LAG_S s + 1)`` (the backward difference lags by half a
    period)."""
    k = axis_values(servo, axis)["Kff_pid"]
    if rates is None:
        return _sys(ct.tf([k, 0], [FF_LAG_S, 1]), "th_ref", "w_ff")
    dt = rates.dt_position
    return _sys(ct.tf([k, -k], [dt, 0], dt), "th_ref", "w_ff")


def imc_c1(l1: float, l2: float, form: str) -> ct.TransferFunction:
    """The prefilter C1 (eq. 9) as a python-control transfer function, in the ``form`` of
    :func:`pusupu_jax.loops.imc_c1`."""
    if form == "printed":
        return ct.tf([3 * l1, 1], [3 * l2, 1])
    f_r = ct.tf([3 * l1, 1], np.polymul(np.polymul([l1, 1], [l1, 1]), [l1, 1]))
    f_d = ct.tf([3 * l2, 1], np.polymul(np.polymul([l2, 1], [l2, 1]), [l2, 1]))
    return ct.minreal(f_r / f_d, verbose=False)


_PHYSICAL = ("electrical", "mechanics")
_CONTROLLERS = ("Gxi", "Gcf", "Gi", "Gxv", "Gw", "Gv", "C1", "C2", "PID")


def sampled_blocks(b: dict[str, ct.StateSpace], dt: float, method: str) -> dict[str, ct.StateSpace]:
    """Blocks sampled at ``dt``: controllers with ``method``, physical parts with ZOH, static gains as they are."""
    out: dict[str, ct.StateSpace] = {}
    for name, sys in b.items():
        if name in _CONTROLLERS:
            out[name] = ct.sample_system(sys, dt, method, name=sys.name, copy_names=True)
        elif name in _PHYSICAL:
            out[name] = ct.sample_system(sys, dt, "zoh", name=sys.name, copy_names=True)
        else:
            out[name] = sys
    return out


def hold_resample(sysd: ct.StateSpace, n: int) -> ct.StateSpace:
    """A discrete system whose input is held for ``n`` samples and whose output is read every ``n``.

    ``x[k+n] = A^n x[k] + sum_j A^j B u``; ``C`` and ``D`` are unchanged.  This is how
    an inner loop at a fast rate looks to the outer loop at ``n`` times the period.
    """
    A, B, C, D = (np.asarray(m) for m in ct.ssdata(sysd))
    An, Bn = np.eye(A.shape[0]), np.zeros_like(B)
    for _ in range(n):
        Bn = Bn + An @ B
        An = An @ A
    return ct.ss(An, Bn, C, D, sysd.dt * n, inputs=sysd.input_labels, outputs=sysd.output_labels)


def _sum(a: str, b: str, out: str) -> ct.StateSpace:
    return ct.summing_junction(inputs=[a, "-" + b], output=out)


def closed_loops(
    servo: ServoParams,
    load: AxisLoad,
    axis: int = 0,
    rates: LoopRates | None = None,
    mode: str = "imc",
    load_torque: bool = False,
) -> dict[str, ct.StateSpace]:
    """Closed current, velocity and position loops of one axis (continuous, or discrete at ``rates``).

    Each maps its reference to the outputs ``(i, w, theta)``: ``current`` from ``i_ref``
    [A], ``velocity`` from ``w_ref`` [rad/s], ``position`` from ``th_ref`` [rad].
    ``load_torque``: each loop gets a second input ``tau_l`` [N m], a load torque on the motor
    shaft against the motor's (``tau = Kt i - tau_l``), for disturbance responses.
    """
    b = blocks(servo, load, axis)
    disturbance: list[str] = []
    if load_torque:
        b["Kt"] = ct.ss([], [], [], [[axis_values(servo, axis)["Kt"], -1.0]], inputs=["i", "tau_l"], outputs="tau")
        disturbance = ["tau_l"]
    levels = [None, None, None] if rates is None else [rates.dt_current, rates.dt_velocity, rates.dt_position]
    out = ["i", "w", "theta"]

    def at(level: int) -> dict[str, ct.StateSpace]:
        dt = levels[level]
        return b if dt is None else sampled_blocks(b, dt, cast(LoopRates, rates).method)  # dt is set from rates

    bi = at(0)
    cl_i = ct.interconnect(
        [
            bi["Gxi"],
            bi["Gcf"],
            bi["Gi"],
            bi["EMF"],
            bi["u"],
            bi["Kt"],
            bi["electrical"],
            bi["mechanics"],
            _sum("i_r", "i_f", "e_i"),
        ],
        inputs=["i_ref"] + disturbance,
        outputs=out,
        name="current_loop",
    )
    inner = cl_i if rates is None else hold_resample(cl_i, rates.n_velocity)
    bv = at(1)
    cl_v = ct.interconnect(
        [bv["Gxv"], bv["Gw"], bv["Gv"], inner, _sum("w_r", "w_f", "e_w")],
        inputs=["w_ref"] + disturbance,
        outputs=out,
        name="velocity_loop",
    )
    inner = cl_v if rates is None else hold_resample(cl_v, rates.n_position)
    bp = at(2)
    law = control_mode(mode).law
    if law == Law.IMC:
        parts = [bp["C1"], bp["C2"], _sum("r1", "theta", "e_p")]
    elif law == Law.PID:
        parts = [bp["PID"], _sum("th_ref", "theta", "e_p")]
    elif law == Law.PID_FF:
        parts = [
            ct.ss(bp["PID"], inputs="e_p", outputs="w_pid"),
            velocity_feedforward(servo, axis, rates),
            ct.summing_junction(inputs=["w_pid", "w_ff"], output="w_ref"),
            _sum("th_ref", "theta", "e_p"),
        ]
    else:
        raise ValueError(f"closed_loops: expected a mode of imc, pid, pid_ff or hybrid, got {mode!r}")
    cl_p = ct.interconnect(parts + [inner], inputs=["th_ref"] + disturbance, outputs=out, name="position_loop")
    return {"current": cl_i, "velocity": cl_v, "position": cl_p}


def open_loops(
    servo: ServoParams,
    load: AxisLoad,
    axis: int = 0,
    mode: str = "imc",
    closed: dict[str, ct.StateSpace] | None = None,
) -> dict[str, ct.StateSpace]:
    """Continuous loop gains ``L`` (closed loop = ``L/(1+L)`` at that point) of each loop, broken at the controller.

    ``closed``: the continuous :func:`closed_loops` of the same axis and mode, when the caller has them.
    """
    b = blocks(servo, load, axis)
    cl = closed_loops(servo, load, axis, mode=mode) if closed is None else closed
    p_i = ct.interconnect(
        [b["EMF"], b["u"], b["Kt"], b["electrical"], b["mechanics"], b["Gcf"]],
        inputs="u_pi",
        outputs="i_f",
        check_unused=False,
    )
    p_v = ct.interconnect([cl["current"], b["Gw"]], inputs="i_ref", outputs="w_f", check_unused=False)
    p_p = cl["velocity"][2, 0]
    c_p = b["C2"] if control_mode(mode).law == Law.IMC else b["PID"]  # pid_ff: the feedforward acts outside the loop
    return {"current": _siso(b["Gi"]) * p_i, "velocity": _siso(b["Gv"]) * p_v, "position": _siso(c_p) * p_p}


def _siso(sys: ct.StateSpace) -> ct.StateSpace:
    return ct.ss(*ct.ssdata(sys))


def current_open_loop_locked(servo: ServoParams, axis: int = 0) -> ct.TransferFunction:
    """The paper's current loop gain (locked rotor): ``Gi Ginv Grl Gcf`` (eq. 1-4)."""
    p = axis_values(servo, axis)
    return (
        ct.tf([p["Ki"] * p["Ti"], p["Ki"]], [p["Ti"], 0])
        * ct.tf([p["Kn"]], [p["Tn"], 1])
        * ct.tf([1], [p["L"], p["R"]])
        * ct.tf([p["Kcf"]], [p["Tcf"], 1])
    )


def nominal_position_open_loop(servo: ServoParams, axis: int = 0) -> ct.TransferFunction:
    """C2 times the position model it was designed for, ``1/(s (T0 s + 1))``."""
    p = axis_values(servo, axis)
    l2, T0 = p["lambda2"], p["T0"]
    c2 = ct.tf(np.polymul([3 * l2, 1], [T0, 1]), np.polymul([3 * l2**2, 0], [l2 / 3, 1]))
    return c2 * ct.tf([1], [T0, 1, 0])


def margins(L: ct.LTI, phase_crossover: bool = False) -> dict[str, float | None]:
    """Gain crossover [Hz], phase margin [deg], gain margin [dB] (None when infinite) of a loop gain.

    ``phase_crossover``: also ``phase_crossover_hz``, where the phase crosses -180 deg and the gain margin is read.
    """
    with np.errstate(invalid="ignore"):  # python-control compares NaNs when a crossing does not exist
        gm, pm, _, _, wgc, wpc = ct.stability_margins(L)
    out = {
        "crossover_hz": float(wgc) / (2 * math.pi) if np.isfinite(wgc) else None,
        "phase_margin_deg": float(pm) if np.isfinite(pm) else None,
        "gain_margin_db": 20 * math.log10(gm) if np.isfinite(gm) and gm > 0 else None,
    }
    if phase_crossover:
        out["phase_crossover_hz"] = float(wpc) / (2 * math.pi) if np.isfinite(wpc) else None
    return out


def bandwidth_hz(sys: ct.LTI, w_low: float = 1e-3, w_high: float = 1e6) -> float | None:
    """First frequency [Hz] where the gain falls 3 dB below its low-frequency value (at ``w_low`` rad/s).

    Computed from the frequency response, so that states the output does not see (the
    motor angle in the current and velocity loops) do not spoil a DC-gain computation.
    """

    def excess(log_w: float) -> float:
        return cast(float, abs(sys(1j * 10**log_w)) - ref / math.sqrt(2))  # python-control: untyped

    ref = abs(sys(1j * w_low))
    grid = np.linspace(math.log10(w_low), math.log10(w_high), 2000)
    gain = np.abs(sys(1j * 10**grid))  # the grid in one call: 5x faster than a call a point, the same to 3e-15
    below = np.nonzero(gain < ref / math.sqrt(2))[0]
    if not below.size:
        return None
    k = below[0]
    return cast(float, 10 ** brentq(excess, grid[k - 1], grid[k], xtol=1e-12) / (2 * math.pi))  # scipy: untyped


STEP_SPAN_S = {"current": 0.02, "velocity": 0.5, "position": 6.0}


def step_metrics(sys: ct.LTI, span: float, w_low: float = 1e-4) -> dict[str, float | None]:
    """Rise time (10-90 %) [s], 2 % settling time [s] and overshoot [%] of a closed loop's step response.

    The final value is the gain at ``w_low`` rad/s (the motor-angle state that the current
    and velocity loops do not see would otherwise spoil a DC-gain computation).  The response
    is sampled at ``span / 30000`` (0.2 ms for the position loop, whose full-form IMC step rises
    in about 17 ms).
    """
    info = ct.step_info(sys, T=np.linspace(0.0, span, 30001), yfinal=float(np.real(sys(1j * w_low))))
    return {
        "rise_time_s": float(info["RiseTime"]),
        "settling_time_s": float(info["SettlingTime"]),
        "overshoot_pct": float(info["Overshoot"]),
    }


def loop_metrics(servo: ServoParams, load: AxisLoad, mode: str = "imc") -> dict[str, Any]:
    """Per axis and loop: crossover_hz, phase_margin_deg, gain_margin_db, bandwidth_hz and :func:`step_metrics`."""
    return {"mode": mode, "axes": [axis_metrics(servo, load, k, mode) for k in range(N_AXES)]}


def axis_metrics(
    servo: ServoParams,
    load: AxisLoad,
    axis: int = 0,
    mode: str = "imc",
    closed: dict[str, ct.StateSpace] | None = None,
    phase_crossover: bool = False,
) -> dict[str, dict[str, float | None]]:
    """One axis of :func:`loop_metrics`: ``{loop: metrics}``; ``closed`` and ``phase_crossover`` as in
    :func:`open_loops` and :func:`margins`."""
    cl = closed_loops(servo, load, axis, mode=mode) if closed is None else closed
    ol = open_loops(servo, load, axis, mode, closed=cl)
    return {
        name: (
            margins(ol[name], phase_crossover)
            | {"bandwidth_hz": bandwidth_hz(cl[name][out, 0])}
            | step_metrics(cl[name][out, 0], STEP_SPAN_S[name])
        )
        for name, out in zip(LOOPS, (0, 1, 2))
    }


def identify_T0(servo: ServoParams, load: AxisLoad, axis: int = 0, window: float = 0.2) -> float:
    """First-order time constant identified from the closed velocity loop's step response [s].

    ``T0`` minimises the squared difference between the step response of ``w_ref -> w``
    and ``1 - exp(-t/T0)`` over ``0 <= t <= window`` (4001 samples): the step test a
    technician runs on a drive.  (The impulse-response mean time is not used: the slow
    pole-zero dipole of the velocity PI, ``Tv = 5 s``, inflates it without changing the
    dominant dynamics.)  This is the plant ``1/(s (T0 s + 1))`` that ``C2`` is designed on.
    """
    t = np.linspace(0.0, window, 4001)
    return fit_first_order(t, ct.step_response(closed_loops(servo, load, axis)["velocity"][1, 0], t).outputs)


def fit_first_order(t: npt.ArrayLike, y: npt.ArrayLike, step: npt.ArrayLike = 1.0) -> float:
    """The time constant ``T0`` [s] minimising ``sum (y - step (1 - exp(-t/T0)))^2`` (least squares, bounded by ``t``).

    ``y`` may have a leading axis of several step tests of the same loop, with ``step`` their step sizes.
    """
    t, y, step = np.asarray(t, dtype=float), np.asarray(y, dtype=float), np.asarray(step, dtype=float)[..., None]
    fit = minimize_scalar(
        lambda tau: float(np.sum((y - step * (1.0 - np.exp(-t / tau))) ** 2)),
        bounds=(1e-5, float(t[-1])),
        method="bounded",
        options={"xatol": 1e-12},
    )
    return float(fit.x)


def kt_for_T0(servo: ServoParams, load: AxisLoad, T0: float | None = None, axis: int = 0) -> float:
    """The torque constant [N m/A] (with ``Ke = Kt``) for which :func:`identify_T0` gives ``T0``."""
    target = axis_values(servo, axis)["T0"] if T0 is None else T0

    def gap(kt: float) -> float:
        return identify_T0(servo.replace(Kt=np.full(N_AXES, kt), Ke=np.full(N_AXES, kt)), load, axis) - target

    return cast(float, brentq(gap, 0.3, 5.0, xtol=1e-9))  # scipy: untyped
