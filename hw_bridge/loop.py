"""The simulator's cascade at the bridge's rate: :mod:`pusupu_jax.cascade`'s ticks, compiled ahead of time on the CPU.

Drive modes, per axis (CiA 402 modes of operation):

* ``csv`` (cyclic synchronous velocity): the bridge closes the position loop and sends the
  speed reference [rad/s]; the drive closes velocity and current;
* ``cst`` (cyclic synchronous torque): the bridge closes position and velocity and sends the
  torque ``Kt I_r`` [N m]; the drive closes current.  In hybrid mode branch 6 is always CST and
  its torque comes from the force law (eq. 13-14), ``F_q`` streamed from the precomputed path.

Rates: the bridge's cycle runs the fastest loop it closes.  With every axis in CSV that is the
position loop; with any axis in CST the velocity loop, and the position loop runs every
``n_position`` cycles, as in the gain file.  ``rate`` [Hz] scales the gain file's rates by the
same factor (the drive's inner loops with them); at the default it is the gain file's own.

The compiled steps take their state and return the next one (pure functions of
:class:`~pusupu_jax.cascade.CascadeState`): the bridge calls exactly the functions that
:func:`pusupu_jax.sim.rollout` scans (``tests/test_bridge.py`` checks the outputs to 1e-12
and the function objects).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import jax
import jax.numpy as jnp
import numpy as np

from pusupu_jax import cascade, loops
from pusupu_jax.gains import GainFile
from pusupu_jax.hybrid import HybridReference
from pusupu_jax.params import LoopRates, command_limits
from pusupu_jax.runtime import require_x64

from jax.flatten_util import ravel_pytree

from .compiled import FlatStep, cpu
from .protocol import CSV, CST

DRIVE_MODES = {"csv": CSV, "cst": CST}
MIN_RATE, MAX_RATE = 1.0, 4000.0  # Hz: the bridge's cycle rates
TAKEOVER_SPEED = 0.25  # of the velocity limit: the speed of the ramp from where the machine stands to the path


@dataclass(frozen=True)
class BridgeReference:
    """What the bridge streams, one sample per position period (computed offline: ``pusupu bridge`` does it).

    ``theta`` ``(N, n_axes)``: motor angles from home [rad]; in hybrid mode ``force_ff`` ``(N,)``
    branch 6's ``F_q`` [N] and ``coupling`` ``(N, 5)`` the row ``w`` [1]; ``platform`` ``(N, 3)``: the
    platform positions [m] the path means (for the tracking error when the robot reports its own).
    """

    theta: np.ndarray
    force_ff: np.ndarray | None = None
    coupling: np.ndarray | None = None
    platform: np.ndarray | None = None

    def __post_init__(self):
        theta = np.asarray(self.theta, dtype=float)
        if theta.ndim != 2 or len(theta) < 1 or not np.isfinite(theta).all():
            raise ValueError(f"reference.theta: expected finite motor angles (N, n_axes) [rad], got {theta.shape}")
        object.__setattr__(self, "theta", theta)
        for name, shape in (("force_ff", (len(theta),)), ("coupling", (len(theta), 5)), ("platform", (len(theta), 3))):
            v = getattr(self, name)
            if v is not None:
                v = np.asarray(v, dtype=float)
                if v.shape != shape or not np.isfinite(v).all():
                    raise ValueError(f"reference.{name}: expected finite values of shape {shape}, got {v.shape}")
                object.__setattr__(self, name, v)


def cycle_rate(rates: LoopRates, cst: bool) -> float:
    """The bridge's cycle rate [Hz] at ``rates``: its position loop's, or with CST axes its velocity loop's."""
    return rates.f_current / rates.n_velocity / (1 if cst else rates.n_position)


def bridge_rates(rates: LoopRates, cst: bool, rate: float | None) -> LoopRates:
    """The gain file's ``rates`` scaled so that the bridge's cycle (position loop, or velocity loop with CST) is
    ``rate`` (default the gain file's own), which must be in [:data:`MIN_RATE`, :data:`MAX_RATE`]."""
    cycle = cycle_rate(rates, cst)
    if rate is None:
        rate = cycle
    if not (isinstance(rate, (int, float)) and MIN_RATE <= rate <= MAX_RATE):
        raise ValueError(f"rate: expected a number of Hz in [{MIN_RATE:g}, {MAX_RATE:g}], got {rate!r}")
    return dataclasses.replace(rates, f_current=rates.f_current * rate / cycle)


def position_cycle(drive, mode, hybrid, s, ref, theta, omega, cst: bool):
    """A cycle that starts a position period: the position tick, then (with CST axes) the velocity tick."""
    s, w_ref, i_force = cascade.position_tick(drive, mode, s, ref, theta, omega, hybrid)
    if not cst:
        return s, (w_ref, jnp.zeros_like(w_ref), jnp.zeros(()) if i_force is None else i_force)
    s, i_ref = cascade.velocity_tick(drive, mode, s, w_ref, omega, i_force)
    return s, (w_ref, i_ref, jnp.zeros(()) if i_force is None else i_force)


def velocity_cycle(drive, mode, s, w_ref, i_force, omega):
    """A cycle inside a position period (CST): the velocity tick with the period's speed and force references held."""
    s, i_ref = cascade.velocity_tick(drive, mode, s, w_ref, omega, i_force if mode.hybrid else None)
    return s, i_ref


def plan(gains: GainFile, drive_modes=None, rate: float | None = None) -> tuple[np.ndarray, LoopRates]:
    """The drive mode of each axis (CiA 402 codes) and the bridge's rates, checked; ValueError names what is wrong.

    ``drive_modes``: 'csv' or 'cst' per axis (default all CSV; hybrid mode runs branch 6 in CST).  The
    reference streamed to :class:`BridgeLoop` has one sample per position period of these rates.
    """
    mode = cascade.control_mode(gains.mode)
    if mode.closed != cascade.Loop.POSITION:
        raise ValueError(f"gain file mode: expected a position mode, got {gains.mode!r}")
    n = int(np.shape(gains.servo.Kv)[-1])
    names = ["csv"] * n if drive_modes is None else list(drive_modes)
    if len(names) != n or not set(names) <= set(DRIVE_MODES):
        raise ValueError(f"drive modes: expected {n} of {tuple(DRIVE_MODES)}, got {names}")
    if mode.hybrid:
        if drive_modes is not None and names[mode.force_axis] != "cst":
            raise ValueError(
                f"drive modes: branch {mode.force_axis + 1} is force-controlled in hybrid mode, so its drive runs CST"
            )
        names[mode.force_axis] = "cst"
    codes = np.array([DRIVE_MODES[m] for m in names], dtype=np.int8)
    return codes, bridge_rates(gains.rates, bool((codes == CST).any()), rate)


class BridgeLoop:
    """The loops of one gain file for one run: compiled, warmed up, then stepped once per cycle.

    ``drive_modes``: 'csv' or 'cst' per axis (default all CSV; hybrid mode forces branch 6 to CST).
    Raises ValueError for a mode the bridge does not run or an inconsistent reference.
    """

    def __init__(self, gains: GainFile, reference: BridgeReference, drive_modes=None, rate: float | None = None):
        require_x64("the bridge's loops")
        self.mode = cascade.control_mode(gains.mode)
        self.drive_modes, self.rates = plan(gains, drive_modes, rate)
        n = len(self.drive_modes)
        if self.mode.hybrid and (reference.force_ff is None or reference.coupling is None):
            raise ValueError("reference: hybrid mode streams F_q and the coupling row; the reference has neither")
        if reference.theta.shape[1] != n:
            raise ValueError(f"reference.theta: expected {n} axes, got {reference.theta.shape[1]}")
        self.cst = bool((self.drive_modes == CST).any())
        self.n_position = self.rates.n_position if self.cst else 1
        self.rate = cycle_rate(self.rates, self.cst)
        self.gains = gains
        self.reference = reference
        # the path's rows as the steps take them, built once here: start() then computes only the takeover ramp (a
        # copy of the whole path at the first cycle of a run took 1-7 ms there, and the cycle missed its deadline)
        self.path_rows = np.ascontiguousarray(
            np.column_stack([reference.theta, reference.force_ff, reference.coupling])
            if self.mode.hybrid
            else reference.theta,
            dtype=float,
        )
        self.drive = jax.jit(loops.discretize, static_argnums=1)(jax.device_put(gains.servo, cpu()), self.rates)
        self.hybrid = gains.hybrid if self.mode.hybrid else None
        self.Kt = np.asarray(gains.servo.Kt, dtype=float)
        self.force_per_torque = np.asarray(gains.servo.eta / (gains.servo.lead / (2 * np.pi)), dtype=float)  # N/(N m)
        self._compile()

    # ------------------------------------------------------------------ compiled steps
    def _compile(self):
        mode, cst = self.mode, self.cst
        n = len(self.drive_modes)
        z = np.zeros(n)
        s0 = cascade.rest(self.drive, mode, jnp.zeros(n), jnp.zeros(n), jnp.zeros(n))
        ref0 = HybridReference(z, 0.0, np.zeros(5)) if mode.hybrid else z
        consts = (self.drive, self.hybrid if mode.hybrid else ())
        self._position = FlatStep(
            lambda d, h, s, r, th, w: position_cycle(d, mode, h or None, s, r, th, w, cst), consts, s0, (ref0, z, z)
        )
        self._velocity = None
        if cst:
            self._velocity = FlatStep(
                lambda d, s, w_ref, i_f, w: velocity_cycle(d, mode, s, w_ref, i_f, w), (self.drive,), s0, (z, 0.0, z)
            )
        rest = jax.jit(lambda d, i, th: ravel_pytree(cascade.rest(d, mode, i, jnp.zeros_like(i), th))[0])
        self._rest = lambda i, th: rest(self.drive, i, th)  # the state at rest, packed as the steps take it
        self._rest(z, z)  # compiled before any run

    # ------------------------------------------------------------------ a run
    def start(self, theta, torque, force_now: float | None = None) -> None:
        """Take over the machine standing at ``theta`` [rad] and pushing ``torque`` [N m] (its drives' actual values).

        The cascade starts at rest there, its velocity integrators holding the measured currents, and
        the reference ramps (quintic, at most :data:`TAKEOVER_SPEED` of the velocity limit) from
        ``theta`` to the path's first sample; in hybrid mode ``F_q`` ramps from ``force_now`` (branch 6's
        measured force [N], default ``F_q[0]``) alike.  So the first command continues what the drives
        were doing: no step.  Then call :meth:`step` once per cycle.
        """
        theta = np.asarray(theta, dtype=float)
        self.state = self._rest(np.asarray(torque, dtype=float) / self.Kt, theta)
        ref = self.reference
        delta = np.abs(ref.theta[0] - theta)
        vmax = TAKEOVER_SPEED * command_limits(self.gains.servo)[0]
        duration = float(np.max(1.875 * delta / vmax))
        force0 = None
        if self.mode.hybrid:
            force0 = ref.force_ff[0] if force_now is None else float(force_now)
            duration = max(duration, 0.2 if abs(force0 - ref.force_ff[0]) > 1.0 else 0.0)
        m = int(np.ceil(duration / self.rates.dt_position)) if duration > 1e-9 else 0
        tau = np.arange(1, m + 1) / max(m, 1)
        blend = (10 * tau**3 - 15 * tau**4 + 6 * tau**5)[:, None]
        ramp = theta + blend * (ref.theta[0] - theta)
        if self.mode.hybrid:  # HybridReference's fields in order: theta, force_ff, coupling
            force = force0 + blend * (ref.force_ff[0] - force0)
            ramp = np.column_stack([ramp, force, np.repeat(ref.coupling[:1], m, axis=0)])
        self.takeover, self.takeover_periods = np.ascontiguousarray(ramp), m
        self.held = (np.zeros(len(theta)), np.zeros(()))

    def step(self, cycle: int, theta, omega) -> np.ndarray:
        """Cycle ``cycle`` (from 0) with the encoders ``theta`` [rad], ``omega`` [rad/s]: the drives' targets.

        CSV axes: speed [rad/s]; CST axes: torque ``Kt I_r`` [N m] (the current reference clamped to ``I_max``).
        """
        n = len(self.drive_modes)
        if cycle % self.n_position == 0:
            self.state, out = self._position(self.state, self._row(cycle), theta, omega)
            w_ref, i_ref = out[:n], out[n : 2 * n]
            self.held = (w_ref, out[2 * n :].reshape(()))
        else:
            self.state, i_ref = self._velocity(self.state, self.held[0], self.held[1], omega)
        return np.where(self.drive_modes == CSV, self.held[0], self.Kt * i_ref)

    def warm(self, cycle: int) -> None:
        """Run the compiled step that cycle ``cycle`` will run, on the present state, and drop its result.

        Called just before the cycle's deadline (:class:`~pusupu_jax.hw_bridge.runner.CycleRunner`'s ``prepare``): the
        step's code and data are then in the CPU's caches when the cycle needs them.  Measured on this 2-core VM
        at 1 kHz, a step right after an idle sleep takes 3 to 5 times as long as one right after another.
        """
        w_ref, i_ff = self.held
        if cycle % self.n_position == 0:
            self._position(self.state, self._row(cycle), w_ref, w_ref)
        else:
            self._velocity(self.state, w_ref, i_ff, w_ref)

    def _row(self, cycle: int) -> np.ndarray:
        """The streamed reference row in force at ``cycle``: the takeover ramp's, then the path's (its last one after
        its end)."""
        p = cycle // self.n_position
        if p < self.takeover_periods:
            return self.takeover[p]
        return self.path_rows[min(p - self.takeover_periods, len(self.path_rows) - 1)]

    def path_time(self, cycle: int) -> float:
        """The time along the path [s] of the reference row in force at ``cycle`` (negative on the takeover ramp)."""
        return (cycle // self.n_position - self.takeover_periods) * self.rates.dt_position

    def reference_at(self, cycle: int) -> np.ndarray:
        """The motor-angle reference [rad] in force at ``cycle`` (for the tracking error)."""
        return self._row(cycle)[: len(self.drive_modes)]

    @property
    def cycles(self) -> int:
        """Cycles to the end of the path, the takeover ramp included."""
        return (self.takeover_periods + len(self.path_rows)) * self.n_position


def bridge_reference(g, trajectory: str, rates=None, machine=None):
    """The stream of the path ``trajectory`` (a name or a path file: :func:`pusupu_jax.paths.platform_path_from`) for
    the bridge at ``rates`` (default the gain file's) on ``machine`` (default: the built-in one), computed offline
    here (inverse kinematics, F_q of hybrid mode) once the path passed the machine's checks
    (:func:`pusupu_jax.paths.check_path`)."""
    from pusupu_jax.cascade import control_mode
    from pusupu_jax.machine import machine_reference
    from pusupu_jax.machine_file import Machine
    from pusupu_jax.paths import platform_path_from

    rates = g.rates if rates is None else rates
    machine = Machine.default() if machine is None else machine
    path = platform_path_from(trajectory, machine.geometry.home, rates)
    ref = machine_reference(g.servo, path, g.mode, rates=rates, options=machine.options(), geom=machine.geometry)
    if control_mode(g.mode).hybrid:
        return BridgeReference(np.asarray(ref.theta), np.asarray(ref.force_ff), np.asarray(ref.coupling), path[:, :3])
    return BridgeReference(np.asarray(ref), platform=path[:, :3])
