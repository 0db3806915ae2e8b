"""Closed-loop stability of the servo cascade, read from its poles: discrete, at the loop rates, with the plant.

What is analysed is what runs: one outer period of :func:`pusupu_jax.sim.pieces` (the cascade's
ticks that the simulator scans and the bridge calls, against the single-axis plant of
:mod:`pusupu_jax.plant.axis` with the default :class:`~pusupu_jax.params.AxisLoad`), at the gain
file's rates and discretisation.  Around rest, with the clamps inactive and without Coulomb
friction (the drive train's viscous friction stays), that period is a linear map of the
carry (every controller, electrical and mechanical state); its Jacobian at rest, taken with
``jax.jacfwd`` of the period function itself, is the monodromy matrix of the multirate loop.  The
loop is asymptotically stable exactly when every eigenvalue of that matrix lies inside the unit
circle, whatever the margins say: a margin read from a loop gain does not see an open loop that is
itself unstable (``emf_ff > 1`` feeds the back-EMF forward with the wrong sign, and the current loop
then has real poles at +400 s^-1 and more with 30 deg of "margin").

Three nested loops are checked on every axis, as a drive runs them:

* ``current``: the current loop closed, its reference an input (mode ``current``; one mechanical step);
* ``velocity``: current and velocity loops closed (mode ``velocity``; one velocity period);
* ``position``: the whole cascade with the file's position law (IMC for ``hybrid``, whose force law on
  branch 6 has no single-axis loop: its gains are bounded in :mod:`pusupu_jax.hybrid`).

In the current and velocity loops nothing feeds back the motor angle, which then integrates the speed
with an eigenvalue of exactly 1; such a state (its column of the monodromy matrix the unit vector) is
left out before the eigenvalues are taken.

A drive train without viscous friction leaves the speed itself free in the current loop (the velocity
loop open): a constant speed, with the current integrator holding the back-EMF, is a mode of eigenvalue
exactly 1 there, which rounding put 2.4e-15 below to 1.1e-15 above 1 (:data:`UNIT_CIRCLE_ROUNDING`).  The loops
around it control that speed, so the current and velocity loops may hold a pole on the unit circle to
that rounding; the position loop, which closes around everything, may not.

:func:`spectral_radii` is the check's one number per loop and axis: the largest eigenvalue modulus
over one period of that loop.  The test oracle is independent: python-control's sampled blocks
connected by ``interconnect`` (:func:`pusupu_jax.analysis.closed_loops` with rates), then their poles.
"""

from __future__ import annotations

import functools
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import jax
import jax.numpy as jnp
import numpy as np
from jax.flatten_util import ravel_pytree

from . import cascade
from .hybrid import HybridGains, validate_gains
from .margins import W_GRID, in_band, loop_margins
from .params import N_AXES, AxisLoad, LoopRates, ParameterError, ServoParams, bounds, validate
from .plant.axis import AxisPlant
from .programs import Program, describe

LOOPS = ("current", "velocity", "position")
# The inner loops' poles may reach the unit circle by this much (a modulus, over one period): rounding of a mode of
# eigenvalue exactly 1, never a growth (1e-9 per 0.25 ms is a time constant of 70 hours), where a back-EMF fed
# forward with the wrong sign (emf_ff > 1) puts the current loop's poles at +400 1/s and more, a modulus of 1.1.
UNIT_CIRCLE_ROUNDING = 1e-9


def loop_mode(loop: str, mode: "str | cascade.ControlMode") -> cascade.ControlMode:
    """The :class:`~pusupu_jax.cascade.ControlMode` that closes the cascade up to ``loop`` for a file of ``mode``."""
    if loop != cascade.Loop.POSITION:
        return cascade.control_mode(loop)
    m = cascade.control_mode(mode)
    if m.closed != cascade.Loop.POSITION:
        raise ValueError(f"stability: expected a mode with a position loop, got {m.name!r}")
    assert m.law is not None  # every position mode has a law
    return cascade.control_mode(m.law)  # hybrid: its position law, IMC


@functools.lru_cache(maxsize=32)
def _monodromy_program(rates: LoopRates, mode: cascade.ControlMode) -> Program:
    """A jitted ``(servo, load) -> (monodromy matrix (n, n), axis of each state (n,))`` for one rate set and mode."""
    from .sim import pieces  # sim imports much of the package; only this needs it

    def program(servo: ServoParams, load: AxisLoad) -> tuple[jax.Array, jax.Array]:
        p = pieces(servo, load, plant=AxisPlant(), rates=rates, mode=mode, hybrid=None)
        carry = p.init("zero", None, None)
        flat, unravel = ravel_pytree(carry)
        axis_of = ravel_pytree(
            jax.tree.map(
                lambda x: jnp.broadcast_to(
                    jnp.arange(N_AXES, dtype=x.dtype).reshape((N_AXES,) + (1,) * (x.ndim - 1)), x.shape
                ),
                carry,
            )
        )[0]
        rest = jnp.zeros(N_AXES, flat.dtype)
        return jax.jacfwd(lambda x: ravel_pytree(p.period(unravel(x), rest)[0])[0])(flat), axis_of

    # kept on disk (pusupu_jax.programs): every command that reads a gain file checks it, and tracing these programs
    # again in each process cost seconds of every `pusupu gains check`
    return Program(program, describe((rates, mode)))


@functools.lru_cache(maxsize=8)
def _margins_program(mode: str) -> Program:
    """A jitted ``(servo, load) -> (loop_margins, in_band)`` for one position law."""
    return Program(lambda servo, load: (loop_margins(servo, load, mode), in_band(servo, load, mode)), describe(mode))


def margins(
    servo: ServoParams, mode: str | cascade.ControlMode = "imc", load: AxisLoad | None = None
) -> tuple[dict[str, dict[str, np.ndarray]], dict[str, np.ndarray]]:
    """``(margins, in_band)`` of every loop of every axis, as numpy float64: :func:`pusupu_jax.margins.loop_margins`
    and :func:`pusupu_jax.margins.in_band` in one jitted program per position law (``mode``'s: IMC for hybrid; ROS's
    PID for ``ros_pid``); ``load`` default :meth:`AxisLoad.default`."""
    load = AxisLoad.default() if load is None else load
    law = cascade.control_mode(mode).law
    with jax.enable_x64(True):
        found: tuple[dict[str, dict[str, np.ndarray]], dict[str, np.ndarray]] = jax.tree.map(
            np.asarray,
            _margins_program(law)(*(jax.tree.map(lambda x: np.asarray(x, dtype=np.float64), p) for p in (servo, load))),
        )
        return found


def _in_loop(m: np.ndarray) -> np.ndarray:
    """Mask of the states that take part in the loop: not those whose column is a unit vector (pure integrators that
    nothing reads, as the motor angle below the position loop)."""
    eye = np.eye(len(m))
    mask: np.ndarray = ~np.all(m == eye, axis=0)
    return mask


def monodromy(
    servo: ServoParams,
    rates: LoopRates,
    loop: str,
    mode: str | cascade.ControlMode = "imc",
    load: AxisLoad | None = None,
) -> list[np.ndarray]:
    """Per axis, the monodromy matrix of ``loop`` over one of its periods (float64, numpy), pure integrators left out.

    ``servo``: one parameter set ``(6,)`` per field; ``load``: the single-axis load (default
    :meth:`AxisLoad.default`); the drive train's Coulomb friction is set to zero (the model is linearised at rest).
    """
    load = AxisLoad.default() if load is None else load
    servo = servo.replace(coulomb=np.zeros_like(np.asarray(servo.coulomb, dtype=float)))
    with jax.enable_x64(True):
        servo64, load64 = (jax.tree.map(lambda x: np.asarray(x, dtype=np.float64), p) for p in (servo, load))
        m, axis_of = _monodromy_program(rates, loop_mode(loop, mode))(servo64, load64)
    m, axis_of = np.asarray(m), np.asarray(axis_of).astype(int)
    out = []
    for a in range(N_AXES):
        idx = np.flatnonzero(axis_of == a)
        block = m[np.ix_(idx, idx)]
        keep = _in_loop(block)
        out.append(block[np.ix_(keep, keep)])
    return out


def spectral_radii(
    servo: ServoParams, rates: LoopRates, mode: str | cascade.ControlMode = "imc", load: AxisLoad | None = None
) -> dict[str, np.ndarray]:
    """``{loop: (6,) array}``: the largest eigenvalue modulus of each loop's monodromy matrix, per axis.

    Below 1: asymptotically stable.  A non-finite matrix (gains that overflow the discretisation) gives ``inf``.
    """
    out: dict[str, np.ndarray] = {}
    for loop in LOOPS:
        radii: list[float] = []
        for block in monodromy(servo, rates, loop, mode, load):
            radii.append(float(np.max(np.abs(np.linalg.eigvals(block)))) if np.isfinite(block).all() else np.inf)
        out[loop] = np.asarray(radii)
    return out


def poles_per_second(radius: np.ndarray, period: float) -> np.ndarray:
    """A discrete eigenvalue modulus as the real part of the continuous pole it stands for [1/s]: ``ln|z| / T``."""
    with np.errstate(divide="ignore"):
        growth: np.ndarray = np.log(radius) / period
        return growth


def loop_period(rates: LoopRates, loop: str) -> float:
    """The period [s] over which :func:`monodromy` advances ``loop``."""
    return {"current": rates.dt_mech, "velocity": rates.dt_velocity, "position": rates.dt_position}[loop]


FLOORS = (45.0, 6.0)  # deg, dB: every loop of every axis, unless the caller says otherwise (and logs it)
F_CURRENT = (1e3, 1e5, "servo drives run their current loops at 4 to 32 kHz")
F_VELOCITY = (200.0, 5e4, "servo drives run their velocity loops at 0.5 to 16 kHz")
F_POSITION = (100.0, 2e4, "position loops, on a drive or a ROS 2 controller manager, run at 0.1 to 20 kHz")


def check_rates(rates: LoopRates) -> None:
    """Raise :class:`~pusupu_jax.params.ParameterError` unless each loop's rate [Hz] lies in its range
    (:data:`F_CURRENT`, :data:`F_VELOCITY`, :data:`F_POSITION`, each with its reason)."""
    for name, hz, (low, high, why) in (
        ("f_current", 1 / rates.dt_current, F_CURRENT),
        ("f_current / n_velocity", 1 / rates.dt_velocity, F_VELOCITY),
        ("f_current / (n_velocity n_position)", 1 / rates.dt_position, F_POSITION),
    ):
        if not low <= hz <= high:
            raise ParameterError(f"rates: {name} is {hz:.6g} Hz; expected {low:g} to {high:g} Hz ({why})")


@dataclass(frozen=True)
class LoopCheck:
    """One loop of every axis, as :func:`check` found it; arrays ``(6,)``."""

    spectral_radius: np.ndarray  # 1: the largest eigenvalue modulus of the loop's monodromy matrix (stable below 1)
    period_s: float  # s: the period the monodromy matrix spans
    phase_margin_deg: np.ndarray  # deg: unwrapped, single-axis continuous model (pusupu_jax.margins)
    gain_margin_db: np.ndarray  # dB
    in_band: np.ndarray  # bool: every gain crossover inside the margins' frequency grid

    @property
    def growth_per_s(self) -> np.ndarray:
        """The real part [1/s] of the least damped pole (positive: unstable), ``ln(radius) / period``."""
        return poles_per_second(self.spectral_radius, self.period_s)


@dataclass(frozen=True)
class GainCheck:
    """What :func:`check` found for a gain set: one :class:`LoopCheck` per loop and the floors it was held to."""

    loops: dict[str, LoopCheck]  # {loop: LoopCheck}
    floors: tuple[float, ...]  # (deg, dB)

    def margins(self) -> dict[str, dict[str, list[float]]]:
        """``{loop: {phase_margin_deg, gain_margin_db}}`` as lists of six floats (a gain file's ``margins``)."""
        return {
            loop: {"phase_margin_deg": c.phase_margin_deg.tolist(), "gain_margin_db": c.gain_margin_db.tolist()}
            for loop, c in self.loops.items()
        }

    def radii(self) -> dict[str, list[float]]:
        """``{loop: [six spectral radii]}`` (a gain file's ``stability``)."""
        return {loop: c.spectral_radius.tolist() for loop, c in self.loops.items()}

    def problem(self) -> str | None:
        """The first reason to refuse the gains, one line; None when every loop of every axis passes."""
        pm_min, gm_min = self.floors
        for loop, c in self.loops.items():
            limit = 1.0 if loop == cascade.Loop.POSITION else 1.0 + UNIT_CIRCLE_ROUNDING
            if not (c.spectral_radius < limit).all():
                a = int(np.argmax(c.spectral_radius))
                return (
                    f"the {loop} loop of axis {a + 1} is unstable: a closed-loop pole of modulus "
                    f"{c.spectral_radius[a]:.6g} over {c.period_s * 1e3:.4g} ms (growing at "
                    f"{c.growth_per_s[a]:.4g} 1/s) at the file's rates; expected every pole inside the unit circle"
                )
        for loop, c in self.loops.items():
            if not c.in_band.all():
                a = int(np.argmin(c.in_band))
                return (
                    f"the {loop} loop of axis {a + 1} crosses over outside {W_GRID[0]:g} to {W_GRID[-1]:g} rad/s, "
                    "where its margins are read; expected a loop gain above 1 at the lowest and below 1 at the "
                    "highest of those frequencies"
                )
            slack = np.minimum(c.phase_margin_deg - pm_min, c.gain_margin_db - gm_min)
            if not (slack >= 0).all():
                a = int(np.argmin(np.where(np.isnan(slack), -np.inf, slack)))
                return (
                    f"the {loop} loop of axis {a + 1} has {c.phase_margin_deg[a]:.1f} deg phase margin and "
                    f"{c.gain_margin_db[a]:.1f} dB gain margin; expected at least {pm_min:g} deg and {gm_min:g} dB"
                )
        return None


def check_values(servo: ServoParams, hybrid: HybridGains | None, rates: LoopRates) -> None:
    """The part of :func:`check` that needs no model: every field and rate inside its documented bounds."""
    validate(servo)
    if hybrid is not None:
        validate_gains(hybrid)
    check_rates(rates)


def check_loads(
    servo: ServoParams,
    hybrid: HybridGains | None,
    rates: LoopRates,
    mode: str | cascade.ControlMode,
    floors: Sequence[float],
    loads: Mapping[str, AxisLoad],
    along: str = "the paths",
) -> GainCheck:
    """:func:`check` with each of ``loads`` (:func:`pusupu_jax.machine_file.margin_loads`: home, and the lightest and
    the heaviest pose ``along`` the paths), in order; raises :class:`~pusupu_jax.params.ParameterError` with the
    first problem and the load it was found with; returns the first load's :class:`GainCheck`."""
    found = []
    for name, load in loads.items():
        try:
            found.append(check(servo, hybrid, rates, mode, floors, load=load))
        except ParameterError as e:
            if not found:
                raise
            raise ParameterError(f"{e} (with the mass the sliders carry at the {name} pose along {along})") from None
    return found[0]


def check(
    servo: ServoParams,
    hybrid: HybridGains | None,
    rates: LoopRates,
    mode: str | cascade.ControlMode = "imc",
    floors: Sequence[float] = FLOORS,
    raise_error: bool = True,
    load: AxisLoad | None = None,
) -> GainCheck:
    """The one check every gain set passes before it is simulated, run, exported or signed.

    In order: every field inside its documented bounds (:func:`pusupu_jax.params.validate`, the hybrid gains'
    :func:`pusupu_jax.hybrid.validate_gains`), the loop rates inside theirs (:func:`check_rates`), then every
    loop of every axis stable by its discrete poles at ``rates`` (:func:`spectral_radii`), its gain crossovers on
    the margins' grid and its margins at least ``floors`` = (deg, dB) (:func:`pusupu_jax.margins.loop_margins`,
    phase unwrapped).  Raises :class:`~pusupu_jax.params.ParameterError` with the first problem in one line;
    ``raise_error=False`` returns the :class:`GainCheck` of gains whose values are in bounds, stable or not, for a
    diagnosis (``pusupu analyze``), and the caller asks :meth:`GainCheck.problem`.  ``load``: the single-axis load
    the loops are analysed with (default :meth:`AxisLoad.default`, the built-in machine's).
    """
    check_values(servo, hybrid, rates)
    load = AxisLoad.default() if load is None else load
    radii = spectral_radii(servo, rates, mode, load)
    m, band = margins(servo, mode, load)
    loops = {
        loop: LoopCheck(
            radii[loop],
            loop_period(rates, loop),
            np.asarray(m[loop]["phase_margin_deg"], dtype=float),
            np.asarray(m[loop]["gain_margin_db"], dtype=float),
            np.asarray(band[loop]),
        )
        for loop in LOOPS
    }
    out = GainCheck(loops, tuple(floors))
    problem = out.problem()
    if raise_error and problem is not None:
        raise ParameterError(f"gains: {problem}")
    return out


def bounds_table() -> str:
    """Every bounded value a gain or parameter file holds, as a markdown table: range, unit and why (``docs/safety.md``
    holds it; a test keeps the two equal)."""
    from dataclasses import fields

    from .hybrid import HybridGains

    rows = ["| value | range | unit | why |", "|---|---|---|---|"]
    for cls in (ServoParams, HybridGains, AxisLoad):
        for f in fields(cls):
            b = bounds(f)
            if b is not None:
                high = b[1] if isinstance(b[1], str) else f"{b[1]:g}"
                rows.append(f"| `{cls.__name__}.{f.name}` | {b[0]:g} to {high} | {f.metadata['unit']} | {b[2]} |")
    for name, (f_low, f_high, why) in (
        ("current loop rate", F_CURRENT),
        ("velocity loop rate", F_VELOCITY),
        ("position loop rate", F_POSITION),
    ):
        rows.append(f"| {name} | {f_low:g} to {f_high:g} | Hz | {why} |")
    return "\n".join(rows)
