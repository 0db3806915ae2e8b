"""Figures (host-side).  Every ``plot_*`` returns its matplotlib ``Figure``; given a ``path``, it also writes it
there, atomically (:func:`save_atomic`), as PNG, SVG or PDF after the path's suffix, and closes it in pyplot.

Importing this module leaves matplotlib's backend alone: a notebook keeps its inline backend, and the ``pusupu``
command selects Agg itself before it plots.
"""

from __future__ import annotations

import io
import os
from pathlib import Path
from typing import TYPE_CHECKING, Any

import control as ct
import matplotlib.pyplot as plt
import numpy as np
import numpy.typing as npt
from matplotlib.figure import Figure

from . import analysis
from .files import write_atomic
from .metrics import tracking_error
from .params import ParameterError
from .plant.axis import screw_ratio

if TYPE_CHECKING:
    from mpl_toolkits.mplot3d.axes3d import Axes3D

    from .params import AxisLoad, ServoParams
    from .trace import Trace


PLOT_FORMATS = ("png", "svg", "pdf")
"""The figure formats a plot's path may end in (``.png``, ``.svg``, ``.pdf``, in any case)."""


def plot_format(path: str | os.PathLike[str]) -> str:
    """The format of a figure written to ``path``: its suffix, one of :data:`PLOT_FORMATS`; raises
    :class:`~pusupu_jax.params.ParameterError` naming the path otherwise (a PNG under a ``.txt`` name is no help)."""
    suffix = Path(path).suffix.lower().lstrip(".")
    if suffix not in PLOT_FORMATS:
        names = ", ".join(f".{f}" for f in PLOT_FORMATS[:-1]) + f" or .{PLOT_FORMATS[-1]}"
        raise ParameterError(f"expected a name ending {names}, got {str(path)!r}")
    return suffix


def save_atomic(fig: Figure, path: str | os.PathLike[str]) -> Path:
    """Save ``fig`` to ``path`` atomically (:func:`~pusupu_jax.files.write_atomic`) in the format of its suffix
    (:func:`plot_format`), then close it."""
    data = io.BytesIO()
    try:
        fig.savefig(data, format=plot_format(path), dpi=110)
    finally:
        plt.close(fig)
    return write_atomic(path, data.getvalue())


def _output(fig: Figure, path: str | os.PathLike[str] | None) -> Figure:
    """``fig``, first written to ``path`` (:func:`save_atomic`) unless ``path`` is None."""
    if path is not None:
        save_atomic(fig, path)
    return fig


def plot_trace(
    trace: Trace, params: ServoParams, path: str | os.PathLike[str] | None = None, axis: int = 0, title: str = ""
) -> Figure:
    """Reference vs slider position, tracking error, and motor current/torque of one axis."""
    t = np.asarray(trace.t)
    ref = np.asarray(trace.reference)[:, axis] * float(np.asarray(screw_ratio(params))[axis]) * 1e3
    x = np.asarray(trace.position)[:, axis] * 1e3
    err = np.asarray(tracking_error(trace, params))[:, axis] * 1e3
    fig, ax = plt.subplots(3, 1, figsize=(8, 8), sharex=True)
    ax[0].plot(t, ref, "k--", label="reference")
    ax[0].plot(t, x, label="slider")
    ax[0].set_ylabel("position [mm]")
    ax[0].legend()
    ax[1].plot(t, err)
    ax[1].set_ylabel("error [mm]")
    ax[2].plot(t, np.asarray(trace.current)[:, axis], label="current [A]")
    ax[2].plot(t, np.asarray(trace.torque)[:, axis], label="torque [N m]")
    ax[2].set_xlabel("time [s]")
    ax[2].legend()
    for a in ax:
        a.grid(True, alpha=0.3)
    fig.suptitle(title or f"axis {axis}")
    fig.tight_layout()
    return _output(fig, path)


def plot_loops(
    servo: ServoParams, load: AxisLoad, path: str | os.PathLike[str] | None = None, axis: int = 0, mode: str = "imc"
) -> Figure:
    """Bode plots of the three open loops (with margins) and step responses of the closed loops."""
    cl = analysis.closed_loops(servo, load, axis, mode=mode)
    ol = analysis.open_loops(servo, load, axis, mode, closed=cl)
    fig, ax = plt.subplots(3, 3, figsize=(14, 9))
    spans = {"current": (1e1, 1e5), "velocity": (1e0, 1e4), "position": (1e-1, 1e3)}
    for col, (name, out) in enumerate(zip(analysis.LOOPS, (0, 1, 2))):
        (lo, hi), T = spans[name], analysis.STEP_SPAN_S[name]
        w = np.logspace(np.log10(lo), np.log10(hi), 600)
        resp = ol[name](1j * w)
        m = analysis.margins(ol[name])
        ax[0, col].semilogx(w / (2 * np.pi), 20 * np.log10(np.abs(resp)))
        ax[0, col].axhline(0, color="k", lw=0.5)
        ax[0, col].set_title(
            f"{name} loop: fc={_fmt(m['crossover_hz'])} Hz, PM={_fmt(m['phase_margin_deg'])} deg, "
            f"GM={_fmt(m['gain_margin_db'])} dB",
            fontsize=9,
        )
        ax[0, col].set_ylabel("|L| [dB]")
        ax[1, col].semilogx(w / (2 * np.pi), np.degrees(np.unwrap(np.angle(resp))))
        ax[1, col].axhline(-180, color="k", lw=0.5)
        ax[1, col].set_ylabel("phase L [deg]")
        ax[1, col].set_xlabel("frequency [Hz]")
        tt = np.linspace(0, T, 800)
        ax[2, col].plot(tt, ct.step_response(cl[name][out, 0], tt).outputs)
        ax[2, col].set_xlabel("time [s]")
        ax[2, col].set_ylabel(f"closed-loop step ({'i w theta'.split()[out]})")
        for r in range(3):
            ax[r, col].grid(True, which="both", alpha=0.3)
    fig.suptitle(f"axis {axis}, position mode {mode}")
    fig.tight_layout()
    return _output(fig, path)


def _fmt(x: float | None) -> str:
    return "inf" if x is None else f"{x:.3g}"


def equal_axes_3d(ax: Axes3D, points: npt.ArrayLike) -> None:
    """Give a 3D axis the same scale on x, y and z around ``points`` ``(N, 3)`` (matplotlib stretches each to fit)."""
    points = np.asarray(points)
    mid = (points.max(axis=0) + points.min(axis=0)) / 2
    half = max(float(np.ptp(points, axis=0).max()) / 2, 1e-9)
    ax.set_xlim(mid[0] - half, mid[0] + half)
    ax.set_ylim(mid[1] - half, mid[1] + half)
    ax.set_zlim(mid[2] - half, mid[2] + half)


def plot_platform_path(trace: dict[str, Any], path: str | os.PathLike[str] | None = None, title: str = "") -> Figure:
    """3D reference vs actual platform path [mm] (``trace`` from :func:`pusupu_jax.machine.simulate_machine`)."""
    ref, act = np.asarray(trace["reference"]) * 1e3, np.asarray(trace["platform"]) * 1e3
    fig = plt.figure(figsize=(11, 5))
    ax = fig.add_subplot(1, 2, 1, projection="3d")
    ax.plot(*ref.T, "k--", label="reference")
    ax.plot(*act.T, label="platform")
    ax.set_xlabel("x [mm]")
    ax.set_ylabel("y [mm]")
    ax.set_zlabel("z [mm]")
    equal_axes_3d(ax, ref)
    ax.legend()
    ax2 = fig.add_subplot(1, 2, 2)
    err = np.linalg.norm(act - ref, axis=1)
    ax2.plot(trace["t"], err)
    ax2.set_xlabel("time [s]")
    ax2.set_ylabel("platform position error [mm]")
    ax2.grid(True, alpha=0.3)
    fig.suptitle(title)
    fig.tight_layout()
    return _output(fig, path)


def plot_identification(result: dict[str, Any], path: str | os.PathLike[str] | None = None, title: str = "") -> Figure:
    """The machine's velocity-step responses (:func:`pusupu_jax.identify.identify_T0_machine`) and their first-order
    fits."""
    t = np.asarray(result["t"])
    fig, axes = plt.subplots(
        len(result["directions"]), 1, figsize=(8, 3.2 * len(result["directions"])), sharex=True, squeeze=False
    )
    for ax, d, omega, ref in zip(axes[:, 0], result["directions"], result["omega"], result["omega_ref"]):
        for b in range(6):
            (line,) = ax.plot(t, omega[:, b], lw=1.2, label=f"branch {b + 1}: T0 {result['T0'][b] * 1e3:.1f} ms")
            ax.plot(t, ref[b] * (1 - np.exp(-t / result["T0"][b])), "--", lw=0.8, color=line.get_color())
        ax.set_ylabel(f"motor speed [rad/s]\n({d} step)")
        ax.grid(True, alpha=0.3)
    axes[0, 0].legend(fontsize=7, ncol=2)
    axes[-1, 0].set_xlabel("time [s] (dashed: first-order fits)")
    fig.suptitle(title or "velocity steps of the machine")
    fig.tight_layout()
    return _output(fig, path)


def plot_drive_fit(
    replays: list[dict[str, Any]], path: str | os.PathLike[str] | None = None, title: str = ""
) -> Figure:
    """Per axis, the logged motor current (or torque, for a log without currents) against the replay's with the
    machine file's values and with the fitted ones (:func:`pusupu_jax.machine_fit.fit`'s plot arrays; the first
    log's)."""
    r = replays[0]
    t = np.asarray(r["t"])
    label = "current [A]" if r["channel"] == "current" else "torque [N m]"
    fig, axes = plt.subplots(3, 2, figsize=(11, 8), sharex=True, squeeze=False)
    for b, ax in enumerate(axes.ravel()):
        ax.plot(t, np.asarray(r["logged"])[:, b], "k", lw=1.4, label="logged")
        ax.plot(t, np.asarray(r["before"])[:, b], "--", lw=1.0, label="replay, machine file's values")
        ax.plot(t, np.asarray(r["after"])[:, b], lw=1.0, label="replay, fitted values")
        ax.set_ylabel(f"axis {b + 1} {label}")
        ax.grid(True, alpha=0.3)
    axes[0, 0].legend(fontsize=7)
    for ax in axes[-1]:
        ax.set_xlabel("time along the path [s]")
    fig.suptitle(title or f"motor {label.split()[0]}s: logged against the closed-loop replay")
    fig.tight_layout()
    return _output(fig, path)
