"""Loop gains measured by sine injection at a controller output, with the loop closed (host-side).

A loop broken at its controller's output has the loop gain ``L``: the controller's output is
``y = -L x`` for a signal ``x`` entering the plant side there.  With the loop closed, a small
sine ``d`` is added at that point (:class:`pusupu_jax.sim.Injected`), so that ``x = y + d``;
once the transient of the start has died away, the loop gain at the sine's frequency ``w`` is

    L(jw) = -Y / X

with ``X`` and ``Y`` the Fourier coefficients of ``x`` and ``y`` at ``w`` over whole periods
(a lock-in: :func:`fourier`).  The trace records ``x``; ``y`` is ``x`` less the injection.

Break points (:data:`BREAKS`):

* ``'velocity'``: the velocity controller's output, the current reference [A], sampled at the
  velocity rate;
* ``'position'``: the position controller's output, the velocity reference [rad/s], sampled at
  the position rate.

Every loop of the cascade stays closed, so the velocity loop's ``y`` also carries what the
axis's own position loop returns (the break of the running machine; :func:`pusupu_jax.analysis.open_loops`
breaks it with the position loop open).  The frequencies are ``f_position / n`` with ``n`` whole
(:func:`grid`): each period is then a whole number of samples at both rates, and the sum over whole
periods is exact for the steady state and rejects its harmonics.  The injection fades in over its
first :data:`FADE_PERIODS` periods (a raised cosine), so that its start excites the loops' slow modes
(the velocity PI's 5 s integrator) less than a sine switched on at once.
"""

from __future__ import annotations

import math

import numpy as np
import numpy.typing as npt

from .params import LoopRates
from .sim import Injected
from .trace import Trace

BREAKS = {
    "velocity": "the velocity controller's output, the current reference [A]",
    "position": "the position controller's output, the velocity reference [rad/s]",
}
FADE_PERIODS = 2  # periods of the sine over which the injection fades in


def grid(f_low: float, f_high: float, count: int, rates: LoopRates = LoopRates()) -> np.ndarray:
    """About ``count`` frequencies [Hz] log-spaced over ``[f_low, f_high]``, each ``f_position / n`` (``n`` whole),
    distinct and increasing."""
    f_p = 1.0 / rates.dt_position
    n = np.unique(np.round(f_p / np.geomspace(f_low, f_high, count)).astype(int))
    return f_p / n[::-1]


def _samples(loop: str, n_outer: int, rates: LoopRates, m: int) -> np.ndarray:
    """The break's sample times [s] ``(n_outer * m,)``: ``m`` inner periods per outer period for 'velocity'."""
    if loop not in BREAKS:
        raise ValueError(f"loop: expected one of {tuple(BREAKS)}, got {loop!r}")
    if loop == "position":
        return np.arange(n_outer) * rates.dt_position
    return (np.arange(n_outer)[:, None] * (m * rates.dt_velocity) + np.arange(m) * rates.dt_velocity).ravel()


def sine(t: npt.ArrayLike, f_hz: float, amplitude: float) -> np.ndarray:
    """The injected signal at times ``t`` [s]: ``amplitude sin(2 pi f t)`` faded in over :data:`FADE_PERIODS`."""
    phase = 2 * np.pi * f_hz * np.asarray(t)
    fade = np.where(phase < 2 * np.pi * FADE_PERIODS, 0.5 - 0.5 * np.cos(phase / (2 * FADE_PERIODS)), 1.0)
    return amplitude * fade * np.sin(phase)


def injected(
    reference: npt.ArrayLike,
    loop: str,
    axis: int,
    f_hz: float,
    amplitude: float,
    rates: LoopRates = LoopRates(),
    inner: int | None = None,
) -> Injected:
    """``reference`` ``(N, n_axes)`` (one sample per outer period of the rollout) with a sine of ``amplitude`` (the
    break's unit, :data:`BREAKS`) at ``f_hz`` injected at ``loop``'s break on ``axis``.

    ``inner``: velocity periods per outer period, ``rates.n_position`` (a position mode, the default) or 1
    ('velocity' mode, where only the velocity loop can be broken).
    """
    reference = np.asarray(reference, dtype=float)
    n, n_axes = reference.shape
    m = rates.n_position if inner is None else inner
    if loop == "position" and m != rates.n_position:
        raise ValueError("injected: the position loop's break needs a position mode (inner = rates.n_position)")
    d = sine(_samples(loop, n, rates, m), f_hz, amplitude)
    velocity, current = np.zeros((n, n_axes)), np.zeros((n, m, n_axes))
    if loop == "position":
        velocity[:, axis] = d
    else:
        current[:, :, axis] = d.reshape(n, m)
    return Injected(reference, velocity, current)


def _break_signals(trace: Trace, injection: Injected, loop: str, axis: int) -> tuple[np.ndarray, np.ndarray]:
    """``(x, d)`` at the break, flattened along time: what entered the plant side, and what was injected."""
    if loop == "position":
        return np.asarray(trace.command)[..., axis], np.asarray(injection.velocity)[..., axis]
    x = np.asarray(trace.current_reference)[..., axis]
    d = np.asarray(injection.current)[..., axis]
    return x.reshape(x.shape[:-2] + (-1,)), d.reshape(d.shape[:-2] + (-1,))


def fourier(x: npt.ArrayLike, t: np.ndarray, f_hz: float, settle_s: float) -> complex:
    """The Fourier coefficient of samples ``x`` at times ``t`` (uniform) at ``f_hz``, over the last whole periods
    after ``settle_s`` [s]: ``(2/K) sum x_k exp(-j w t_k)`` over ``K`` samples (ValueError when no whole period
    fits, or a period is not a whole number of samples)."""
    dt = float(t[1] - t[0])
    per = 1.0 / (f_hz * dt)
    if abs(per - round(per)) > 1e-6:
        raise ValueError(f"fourier: expected a period of whole samples, got {per:.6g} samples at {f_hz:g} Hz")
    per = int(round(per))
    periods = int((len(t) - math.ceil(settle_s / dt)) // per)
    if periods < 1:
        raise ValueError(f"fourier: no whole period of {f_hz:g} Hz fits after {settle_s:g} s in {len(t) * dt:g} s")
    k = slice(len(t) - periods * per, len(t))
    return complex(2.0 / (periods * per) * np.sum(np.asarray(x)[k] * np.exp(-2j * np.pi * f_hz * np.asarray(t)[k])))


def loop_gain(
    trace: Trace,
    injection: Injected,
    loop: str,
    axis: int,
    f_hz: float,
    rates: LoopRates = LoopRates(),
    settle_s: float = 0.0,
) -> complex:
    """``L(j 2 pi f) = -Y/X`` of one injection run (``trace`` and ``injection`` unbatched), over the whole periods
    after ``settle_s`` [s]."""
    x, d = _break_signals(trace, injection, loop, axis)
    m = np.asarray(injection.current).shape[-2]
    t = _samples(loop, len(x) // (1 if loop == "position" else m), rates, m)
    X = fourier(x, t, f_hz, settle_s)
    return -fourier(x - d, t, f_hz, settle_s) / X


def unwrapped_deg(L: npt.ArrayLike) -> np.ndarray:
    """The phase [deg] of loop gains along increasing frequency, continuous, the first in (-360, 0]."""
    u = np.degrees(np.unwrap(np.angle(np.asarray(L))))
    phase: np.ndarray = u - 360.0 * np.ceil(u[0] / 360.0)
    return phase


def crossover(f_hz: npt.ArrayLike, L: npt.ArrayLike) -> dict[str, float | None]:
    """Gain crossover [Hz] and phase margin [deg] from loop gains measured at increasing ``f_hz``.

    The first crossing of ``|L| = 1`` from above, interpolated linearly in ``log |L|`` against ``log f``; the
    phase (:func:`unwrapped_deg`) interpolated alike at it.  None for both when ``|L|`` does not cross 1 on the
    grid.
    """
    f, mag, phase = np.log(np.asarray(f_hz)), np.log(np.abs(np.asarray(L))), unwrapped_deg(L)
    down = np.nonzero((mag[:-1] > 0) & (mag[1:] <= 0))[0]
    if not down.size:
        return {"crossover_hz": None, "phase_margin_deg": None}
    k = down[0]
    a = mag[k] / (mag[k] - mag[k + 1])
    return {
        "crossover_hz": float(np.exp(f[k] + a * (f[k + 1] - f[k]))),
        "phase_margin_deg": float(180.0 + phase[k] + a * (phase[k + 1] - phase[k])),
    }
