"""Phase and gain margins of every loop, in JAX (differentiable in the gains), for the tuner's constraints.

The loop gains are those of :func:`pusupu_jax.analysis.open_loops` (continuous, broken at
each controller's output, single-axis load ``AxisLoad``), written here as complex
frequency responses ``L(jw)`` so that they can be traced:

* current: ``L_i = Gi P_u Gcf`` with ``P_u = i/u_pi = Ginv / (L s + R + Ke M (1 - emf_ff/(Tn s + 1)))``,
  ``Ginv = Kn/(Tn s + 1)`` and ``M = w/i = Kt/(J_eff s + b_eff)`` (back-EMF and its feedforward);
* velocity: ``L_v = Gv T_i M Gw``, ``T_i = Gxi Gi P_u / (1 + Gi P_u Gcf)`` the closed current loop;
* position: ``L_p = C T_v / s``, ``T_v = Gxv Gv T_i M / (1 + L_v)``, ``C = C2`` (IMC) or the PID.

Margins are read on a log-spaced grid (:data:`W_GRID`, 1e-4 to 1e7 rad/s): the gain crossover where ``|L|``
falls through 1 and the phase crossover where ``L`` crosses the negative real axis, each
located by linear interpolation of the grid and refined by two secant steps on the exact
response.  The phase margin is ``180 deg`` plus the phase unwrapped along the grid from its lowest
frequency (:func:`unwrapped_phase`), so it can be negative.  Where a loop has several gain
crossovers, the smallest phase margin is taken; of several phase crossovers, the one whose gain
margin is smallest in size, with its sign (as python-control's ``stability_margins`` does: a
conditionally stable loop whose phase dips below -180 deg where its gain is high reports the margin
nearest 0 dB); where a loop has none, the margin is ``inf``; :func:`in_band` says whether every gain crossover lies on
the grid.  Margins describe robustness
only: whether a loop is stable is read from its poles (:mod:`pusupu_jax.stability`).
Agreement with python-control is a test (0.5 deg, 0.1 dB).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import jax
import jax.numpy as jnp
import numpy as np
import numpy.typing as npt
from jax.typing import ArrayLike

from .cascade import Law, control_mode
from .params import AxisLoad, ServoParams, arrays
from .plant.axis import screw_ratio

# rad/s; numpy, so that it is float64 whenever it is made: a jnp array made on import, before
# float64 is enabled (as in a Ray worker, which imports this before calling setup_jax), was float32
W_GRID = np.logspace(-4, 7, 5501)


def _tf(num: Sequence[jax.Array], den: Sequence[jax.Array], s: jax.Array) -> jax.Array:
    """``polyval(num, s) / polyval(den, s)`` with coefficient lists (highest power first)."""
    return jnp.polyval(jnp.stack(num), s) / jnp.polyval(jnp.stack(den), s)


def axis_blocks(servo: ServoParams, s: ArrayLike, mode: str = "imc") -> dict[str, jax.Array]:
    """Each axis's continuous controller and drive blocks at the complex frequencies ``s``; parameters ``(..., 6)``,
    each block ``(..., 6, len(s))``.

    ``armature`` ``L s + R`` [V/A], ``inverter`` ``Kn/(Tn s + 1)``, ``emf`` ``Ke (1 - emf_ff/(Tn s + 1))`` [V s/rad]
    (the back-EMF less its feedforward through the inverter), the current PI ``Gi`` with its feedback filter ``Gcf``
    and reference filter ``Gxi``, the velocity PI ``Gv`` with ``Gw`` and ``Gxv``, and the position controller ``C``
    (``C2`` for IMC; the PID, whose velocity feedforward acts outside the loop).  The mechanics are the caller's: one
    lumped load (:func:`loop_gains`) or the coupled mechanism (:mod:`pusupu_jax.coupled`).
    """
    p = {k: jnp.asarray(v)[..., None] for k, v in arrays(servo).items()}
    s = jnp.asarray(s)
    zero = jnp.zeros_like(p["Ki"])
    law = control_mode(mode).law
    if law == Law.IMC:
        l2, T0 = p["lambda2"], p["T0"]
        c = (3 * l2 * s + 1) * (T0 * s + 1) / (3 * l2**2 * s * (l2 / 3 * s + 1))
    elif law in (Law.PID, Law.PID_FF):  # the velocity feedforward acts outside the loop
        c = p["Kp_pid"] + p["Ki_pid"] / s + p["Kd_pid"] * s / (p["Tf_pid"] * s + 1)
    elif law == Law.ROS_PID:  # ROS's PID: no derivative filter (its d acts on the measured velocity error)
        c = p["Kp_pid"] + p["Ki_pid"] / s + p["Kd_pid"] * s
    else:
        raise ValueError(f"axis_blocks: expected a mode with a position loop, got {mode!r}")
    return {
        "armature": p["L"] * s + p["R"],
        "inverter": p["Kn"] / (p["Tn"] * s + 1),
        "emf": p["Ke"] * (1 - p["emf_ff"] / (p["Tn"] * s + 1)),
        "Gi": _tf([p["Ki"] * p["Ti"], p["Ki"]], [p["Ti"], zero], s),
        "Gcf": p["Kcf"] / (p["Tcf"] * s + 1),
        "Gxi": 1 / (p["Tcf"] * s + 1),
        "Gv": _tf([p["Kv"] * p["Tv"], p["Kv"]], [p["Tv"], zero], s),
        "Gw": p["Kw"] / (p["Tw"] * s + 1),
        "Gxv": 1 / (p["Tw"] * s + 1),
        "C": c,
    }


def loop_gains(servo: ServoParams, load: AxisLoad, w: ArrayLike, mode: str = "imc") -> dict[str, jax.Array]:
    """``L(jw)`` of the current, velocity and position loops; parameters ``(..., 6)``, result ``(..., 6, len(w))``."""
    p = {k: jnp.asarray(v)[..., None] for k, v in arrays(servo).items()}
    q = {k: jnp.asarray(v)[..., None] for k, v in arrays(load).items()}
    s = 1j * jnp.asarray(w)
    b = axis_blocks(servo, s, mode)
    r = screw_ratio(servo)[..., None]
    j_eff = p["J"] + q["mass"] * r**2 / p["eta"]
    b_eff = p["viscous"] * r**2 / p["eta"]
    motion = p["Kt"] / (j_eff * s + b_eff)
    # the blocks' own expressions, in the same order of operations as before they were shared: the same rounding
    p_u = b["inverter"] / (b["armature"] + p["Ke"] * motion * (1 - p["emf_ff"] / (p["Tn"] * s + 1)))
    l_i = b["Gi"] * p_u * b["Gcf"]
    t_i = b["Gi"] * p_u / (p["Tcf"] * s + 1) / (1 + l_i)
    l_v = b["Gv"] * t_i * motion * p["Kw"] / (p["Tw"] * s + 1)
    t_v = b["Gv"] * t_i * motion / (p["Tw"] * s + 1) / (1 + l_v)
    return {"current": l_i, "velocity": l_v, "position": b["C"] * t_v / s}


def _crossings(f: jax.Array, log_w: npt.NDArray[np.float64]) -> tuple[jax.Array, jax.Array]:
    """Interpolated roots of the real sequence ``f`` along the last axis (the grid ``log_w``, numpy): (mask, log w) per
    grid interval."""
    a, b = f[..., :-1], f[..., 1:]
    mask = (a > 0) & (b <= 0) | (a < 0) & (b >= 0)
    frac = jnp.where(mask, a / jnp.where(mask, a - b, 1.0), 0.0)  # 0 (the grid point) where no root
    return mask, frac * (log_w[1:] - log_w[:-1]) + log_w[:-1]


def unwrapped_phase(angle: ArrayLike) -> jax.Array:
    """The phase [rad] of a frequency response along the grid (last axis), continuous, its first sample in (-2 pi, 0].

    A loop gain's phase at the grid's lowest frequency is ``-90 deg`` per integrator (and a lag or lead); anchored
    there, a phase that falls through ``-180 deg`` reads ``-200 deg``, not ``+160 deg``, so that a loop at -20 deg of
    phase margin says so (a margin taken modulo 360 deg read 340 deg).
    """
    u = jnp.unwrap(angle, axis=-1)
    return u - 2 * jnp.pi * jnp.ceil(u[..., :1] / (2 * jnp.pi))


CANDIDATES = 4  # crossings refined per loop and kind: those of the smallest margins on the grid


def margins(gain_fn: Callable[[ArrayLike], jax.Array], w: npt.NDArray[np.float64] = W_GRID) -> dict[str, jax.Array]:
    """Smallest phase margin [deg] and gain margin [dB] of ``gain_fn(w) -> L(jw)`` (``inf`` where none).

    Also the gain crossover [rad/s] of the smallest phase margin.  Differentiable
    almost everywhere in whatever ``gain_fn`` closes over.

    The grid only finds the crossings (no gradient flows through it); the :data:`CANDIDATES`
    crossings of each kind with the smallest margins read on the grid are refined on the exact
    response, and the gradient flows through those few points.  Refining every grid interval, as
    this did before, kept about 100 MB of the gradient's intermediates per parameter set (6
    axes, 3 loops): 6.6 GB for a batch of 64 on the CPU, and a batch of 4096 asked a GPU for
    135 GiB.
    """
    # numpy's log, so that no JAX operation takes the grid itself: JAX reuses such an operation's result on one
    # numpy array across its enable_x64 context, and a program traced in float32 before (a tuner's in a notebook
    # that skipped setup_jax) left stability.margins, which runs in float64, a float32 grid that XLA's verifier refused
    log_w = np.log(w)

    def refine(g: Callable[[jax.Array], jax.Array], x: jax.Array, mask: jax.Array) -> jax.Array:
        """Two secant steps on g(log w) = 0 from the interpolated roots, kept on the grid's span.

        Only where ``mask`` holds a root: elsewhere x stays, and its step is not formed at all. Its
        gradient is taken all the same (with a zero cotangent), and in float32 a fast loop's
        near-equal tiny values far from any root made that step's derivative overflow: zero times
        inf is NaN, which reached every gain (the same holds for ``at_roots``).
        """
        x0, x1 = x, x + 1e-4
        g0 = g(x0)
        for _ in range(2):
            g1 = g(x1)
            use = mask & (g1 != g0)
            step = jnp.where(use, g1 * (x1 - x0) / jnp.where(use, g1 - g0, 1.0), 0.0)
            x0, x1, g0 = x1, jnp.clip(x1 - step, log_w[0], log_w[-1]), g1
        return x1

    # L at the roots, 1 elsewhere: there the angle's and the log's gradients would be NaN
    def at_roots(x: jax.Array, mask: jax.Array) -> jax.Array:
        return jnp.where(mask, gain_fn(jnp.exp(x)), 1.0)

    # the crossings of the smallest margins: (mask, log w), K per loop
    def candidates(mask: jax.Array, x: jax.Array, margin_on_grid: jax.Array) -> tuple[jax.Array, jax.Array]:
        k = jnp.argsort(jnp.where(mask, margin_on_grid, jnp.inf), axis=-1)[..., :CANDIDATES]
        return jnp.take_along_axis(mask, k, axis=-1), jnp.take_along_axis(x, k, axis=-1)

    L = jax.lax.stop_gradient(gain_fn(w))
    wrapped = jnp.angle(L)
    unwrapped = unwrapped_phase(wrapped)
    crossing_g, x_grid_g = _crossings(jnp.log(jnp.abs(L)), log_w)
    mask_g, x_g = candidates(crossing_g, x_grid_g, 180.0 + jnp.degrees(unwrapped[..., :-1]))
    x_g = refine(lambda x: jnp.log(jnp.abs(gain_fn(jnp.exp(x)))), x_g, mask_g)
    # the exact response's phase at each refined crossing, continued from the nearest grid point's unwrapped phase
    near = jnp.clip(jnp.searchsorted(log_w, x_g), 0, len(w) - 1)
    on_grid = [jnp.take_along_axis(a, near, axis=-1) for a in (wrapped, unwrapped)]
    step = jnp.mod(jnp.angle(at_roots(x_g, mask_g)) - on_grid[0] + jnp.pi, 2 * jnp.pi) - jnp.pi
    pm_all = jnp.where(mask_g, 180.0 + jnp.degrees(on_grid[1] + step), jnp.inf)
    k = jnp.argmin(pm_all, axis=-1)
    mask_p, x_p = _crossings(jnp.imag(L), log_w)
    mask_p, x_p = candidates(mask_p & (jnp.real(L[..., :-1]) < 0), x_p, jnp.abs(jnp.log(jnp.abs(L[..., :-1]))))
    x_p = refine(lambda x: jnp.imag(gain_fn(jnp.exp(x))), x_p, mask_p)
    gm = jnp.where(mask_p, -20 * jnp.log10(jnp.abs(at_roots(x_p, mask_p))), jnp.inf)
    gm = jnp.take_along_axis(gm, jnp.argmin(jnp.abs(gm), axis=-1)[..., None], axis=-1)[..., 0]
    return {
        "phase_margin_deg": jnp.min(pm_all, axis=-1),
        "gain_margin_db": gm,
        "crossover_rad_s": jnp.take_along_axis(jnp.exp(x_g), k[..., None], axis=-1)[..., 0],
    }


def in_units(m: dict[str, jax.Array], axis: int) -> dict[str, float | None]:
    """Axis ``axis`` of a :func:`margins` result in Hz, deg and dB: ``crossover_hz``, ``phase_margin_deg`` and
    ``gain_margin_db``, None where the loop has no such crossing (no crossover where the phase margin is infinite)."""
    pm, gm = float(m["phase_margin_deg"][axis]), float(m["gain_margin_db"][axis])
    crossing = bool(np.isfinite(pm))
    return {
        "crossover_hz": float(m["crossover_rad_s"][axis]) / (2 * np.pi) if crossing else None,
        "phase_margin_deg": pm if crossing else None,
        "gain_margin_db": gm if np.isfinite(gm) else None,
    }


LOOPS = ("current", "velocity", "position")


def loop_margins(servo: ServoParams, load: AxisLoad, mode: str = "imc") -> dict[str, dict[str, jax.Array]]:
    """:func:`margins` of each loop of each axis: ``{loop: {phase_margin_deg, gain_margin_db, crossover_rad_s}}``.

    The three loops go through :func:`margins` as one stack (leading axis), so that each evaluation of
    :func:`loop_gains` serves all three: a third of the program that tracing them apart made (the tuner's gradient
    compiles that much less)."""

    # w: the grid (n,), or points per loop (3, ..., 6, k) where each loop refines its own
    def stack(w: ArrayLike) -> jax.Array:
        gains = loop_gains(servo, load, w, mode)
        return jnp.stack([gains[name] if jnp.ndim(w) == 1 else gains[name][i] for i, name in enumerate(LOOPS)])

    stacked = margins(stack)
    return {name: {k: v[i] for k, v in stacked.items()} for i, name in enumerate(LOOPS)}


def envelope_margins(servo: ServoParams, loads: AxisLoad, mode: str = "imc") -> dict[str, dict[str, jax.Array]]:
    """:func:`loop_margins` with one load, or with each of several stacked ones (:func:`pusupu_jax.params.stack` of
    :func:`pusupu_jax.machine_file.margin_loads`: a leading axis on every field, and on every margin)."""
    if jnp.ndim(loads.mass) < 2:
        return loop_margins(servo, loads, mode)

    def margins_with(load: AxisLoad) -> dict[str, dict[str, jax.Array]]:
        return loop_margins(servo, load, mode)

    return jax.vmap(margins_with)(loads)


def in_band(servo: ServoParams, load: AxisLoad, mode: str = "imc") -> dict[str, jax.Array]:
    """``{loop: (..., 6) bool}``: ``|L|`` above 1 at the grid's lowest frequency and below 1 at its highest, so that
    every gain crossover of the loop lies on :data:`W_GRID` and :func:`loop_margins` has seen it."""
    ends = loop_gains(servo, load, W_GRID[[0, -1]], mode)
    return {loop: (jnp.abs(ends[loop][..., 0]) > 1) & (jnp.abs(ends[loop][..., 1]) < 1) for loop in LOOPS}
