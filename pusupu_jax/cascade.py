"""The servo cascade as per-rate ticks over a typed state: what the simulator scans and the bridge runs.

Plant-free: every tick takes the measurements of its rate and returns its command, so that
:func:`pusupu_jax.sim.rollout` scans exactly these functions against a model and
:mod:`hw_bridge` calls exactly these functions against drives.

* :func:`position_tick`, every position period: motor-angle reference [rad] (or a
  :class:`~pusupu_jax.hybrid.HybridReference` sample) and measured angle [rad] -> velocity
  reference [rad/s]; in hybrid mode also branch 6's current reference [A] from the force law
  (eq. 13-14), ``F_6 r / (eta Kt)``;
* :func:`velocity_tick`, every velocity period: velocity reference and measured speed
  [rad/s] -> current reference [A], clamped to ``+-I_max``; in hybrid mode the force axis's
  current reference is replaced by the force law's, clamped alike;
* :func:`current_tick`, every current period: current reference and measured current [A] ->
  inverter command [V], with the back-EMF feedforward and the ``+-V_max/Kn`` clamp.

A :class:`ControlMode` is the one static answer to "which loops are closed, and what does
the reference hold"; :data:`MODES` maps every :class:`Mode` to its record, and the lists of modes
that each part of the product takes (:data:`POSITION_MODES`, :data:`AXIS_MODES`,
:data:`GAIN_FILE_MODES`, :data:`TUNE_MODES`, :data:`BASELINE_MODES`) are derived from it here,
nowhere else.
"""

from __future__ import annotations

import dataclasses
import enum
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, NamedTuple, cast

import jax
import jax.numpy as jnp

from . import hybrid as hybrid_law
from . import lti, loops
from .loops import Drive, PIState

if TYPE_CHECKING:
    from jax.typing import ArrayLike


class Mode(enum.StrEnum):
    """A control mode's name, as files, reports and the command line spell it."""

    CURRENT = "current"  # the current loop alone
    VELOCITY = "velocity"  # current and velocity loops
    IMC = "imc"  # the 2-DOF IMC position loop on every branch (eq. 9)
    PID = "pid"  # the PID baseline
    PID_FF = "pid_ff"  # the PID with velocity feedforward
    ROS_PID = "ros_pid"  # ros2_controllers' PID, as the ROS 2 export configures it
    HYBRID = "hybrid"  # IMC on branches 1-5, the force law of eq. 13-14 on branch 6


class Loop(enum.StrEnum):
    """A loop of the cascade, innermost first."""

    CURRENT = "current"
    VELOCITY = "velocity"
    POSITION = "position"


class Law(enum.StrEnum):
    """The position controller."""

    IMC = "imc"
    PID = "pid"
    PID_FF = "pid_ff"
    ROS_PID = "ros_pid"


@dataclass(frozen=True)
class ControlMode:
    """Which loops the cascade closes and what its reference holds (static).

    ``closed``: the outermost closed loop; ``law``: the position controller (None below position);
    ``force_axis``: the branch whose current reference comes from the hybrid force law (None: none).
    """

    name: Mode
    closed: Loop
    law: Law | None = None
    force_axis: int | None = None

    @property
    def hybrid(self) -> bool:
        """Branch ``force_axis`` force-controlled; the reference is a :class:`~pusupu_jax.hybrid.HybridReference`."""
        return self.force_axis is not None

    def theta(self, ref: Any) -> Any:
        """The motor-angle reference [rad] of a reference sample (or sequence)."""
        return ref.theta if self.hybrid else ref

    def with_theta(self, ref: Any, theta: jax.Array) -> Any:
        """The reference sample ``ref`` with its motor-angle reference [rad] replaced by ``theta``."""
        return dataclasses.replace(ref, theta=theta) if self.hybrid else theta


MODES = {
    m.name: m
    for m in (
        ControlMode(Mode.CURRENT, Loop.CURRENT),
        ControlMode(Mode.VELOCITY, Loop.VELOCITY),
        ControlMode(Mode.IMC, Loop.POSITION, Law.IMC),
        ControlMode(Mode.PID, Loop.POSITION, Law.PID),
        ControlMode(Mode.PID_FF, Loop.POSITION, Law.PID_FF),
        ControlMode(Mode.ROS_PID, Loop.POSITION, Law.ROS_PID),
        ControlMode(Mode.HYBRID, Loop.POSITION, Law.IMC, hybrid_law.FORCE_AXIS),
    )
}
# the modes that close the position loop: what the MJX machine runs
POSITION_MODES = tuple(name for name, m in MODES.items() if m.closed == Loop.POSITION)
# the single-axis plant's position modes (it has no branch 6 to force-control; ROS's PID is for the export's check)
AXIS_MODES = (Mode.IMC, Mode.PID, Mode.PID_FF)
# what a gain file holds and the bridge runs
GAIN_FILE_MODES = (*AXIS_MODES, Mode.HYBRID)
# what pusupu tune tunes in (ROS's PID is what the export configures, checked by pusupu gains check-ros, not tuned)
TUNE_MODES = tuple(m for m in POSITION_MODES if m != Mode.ROS_PID)
# what a tune runs beside the start and the result as baselines
BASELINE_MODES = (Mode.PID, Mode.PID_FF, Mode.IMC, Mode.ROS_PID)


def control_mode(mode: "str | ControlMode") -> ControlMode:
    """The :class:`ControlMode` named ``mode`` (a mode passes through); ValueError names the known ones."""
    if isinstance(mode, ControlMode):
        return mode
    if mode not in MODES:
        raise ValueError(f"mode: expected one of {tuple(map(str, MODES))}, got {mode!r}")
    return MODES[Mode(mode)]


class CascadeState(NamedTuple):
    """Every controller state of one drive set (arrays ``(..., n_axes, ...)``); None for a loop that is open."""

    current: PIState
    velocity: PIState | None
    position: Any | None  # IMCState, PIDFFState (both PIDs) or RosPIDState
    force: hybrid_law.ForceState | None


def _position_init(
    drive: Drive, mode: ControlMode, theta0: ArrayLike
) -> loops.IMCState | loops.PIDFFState | loops.RosPIDState | None:
    """The position controller at rest at ``theta0`` [rad], zero error: IMC's prefilter holds ``theta0``."""
    if mode.law == Law.IMC:
        return loops.imc_rest(drive.imc, theta0)
    if mode.law in (Law.PID, Law.PID_FF):
        return loops.pid_ff_init(drive.pid, theta0)
    if mode.law == Law.ROS_PID:
        return loops.ros_pid_init(drive.ros, theta0)
    return None


def init(drive: Drive, mode: ControlMode, theta0: ArrayLike = 0.0, force0: ArrayLike = 0.0) -> CascadeState:
    """Every loop state zero but the position controller's, at rest at ``theta0`` [rad] (:func:`rest`); the force
    law's last ``F_6`` at ``force0`` [N]."""
    return CascadeState(
        loops.pi_loop_init(drive.current),
        loops.pi_loop_init(drive.velocity) if mode.closed != Loop.CURRENT else None,
        _position_init(drive, mode, theta0),
        hybrid_law.init(force0) if mode.hybrid else None,
    )


def rest(
    drive: Drive,
    mode: ControlMode,
    current: jax.Array,
    command: jax.Array,
    theta0: ArrayLike = 0.0,
    force0: ArrayLike = 0.0,
) -> CascadeState:
    """The cascade that has held the machine still at ``theta0`` [rad] for a long time.

    ``current`` [A]: the armature currents that hold it; ``command`` [V]: the inverter commands
    that carry them (:func:`pusupu_jax.loops.electrical_rest`); ``force0`` [N]: in hybrid mode
    branch 6's ``F_q`` at t = 0.  Every filter at its steady value, each PI integrator holding its
    output, the position loops at zero error.
    """
    i_ref = current * lti.dc_gain(drive.current.fb_filter) / lti.dc_gain(drive.current.ref_filter)
    zero = jnp.zeros_like(current)
    return CascadeState(
        loops.pi_loop_rest(drive.current, i_ref, current, command),
        loops.pi_loop_rest(drive.velocity, zero, zero, i_ref) if mode.closed != Loop.CURRENT else None,
        _position_init(drive, mode, theta0),
        hybrid_law.init(force0) if mode.hybrid else None,
    )


def position_tick(
    drive: Drive,
    mode: ControlMode,
    s: CascadeState,
    ref: Any,
    theta: jax.Array,
    omega: jax.Array,
    hybrid: hybrid_law.HybridGains | None = None,
) -> tuple[CascadeState, jax.Array, jax.Array | None]:
    """One position period: ``(state, w_ref [rad/s], i_force [A] or None)``.

    ``ref``: motor-angle references [rad] ``(n_axes,)``, or in hybrid mode one
    :class:`~pusupu_jax.hybrid.HybridReference` sample; ``theta``, ``omega``: the encoders [rad, rad/s];
    ``hybrid``: the :class:`~pusupu_jax.hybrid.HybridGains` in hybrid mode.  ``i_force``: branch
    ``mode.force_axis``'s current reference ``F_6 r / (eta Kt)`` (unclamped; :func:`velocity_tick` clamps).
    """
    theta_ref = mode.theta(ref)
    position = s.position
    assert position is not None  # a mode that closes the position loop carries its controller's state
    sp: loops.IMCState | loops.PIDFFState | loops.RosPIDState
    if mode.law == Law.IMC:
        sp, w_ref = loops.imc_step(drive.imc, position, theta_ref, theta)
    elif mode.law in (Law.PID, Law.PID_FF):  # the PID baseline: PID + velocity feedforward at Kff = 0
        velocity_ff = drive.velocity_ff if mode.law == Law.PID_FF else 0.0
        sp, w_ref = loops.pid_ff_step(drive.pid, velocity_ff, position, theta_ref, theta)
    else:
        sp, w_ref = loops.ros_pid_step(drive.ros, position, theta_ref, theta, omega)
    if not mode.hybrid:
        return s._replace(position=sp), w_ref, None
    assert s.force is not None  # and hybrid mode its force law's
    sf, force = hybrid_law.step(
        cast(hybrid_law.HybridGains, hybrid),  # hybrid mode passes its gains
        s.force,
        (theta_ref - theta) * drive.screw,
        ref.coupling,
        ref.force_ff,
        drive.dt_position,
    )
    k = mode.force_axis
    return s._replace(position=sp, force=sf), w_ref, force * drive.force_current[..., k]


def velocity_tick(
    drive: Drive,
    mode: ControlMode,
    s: CascadeState,
    w_ref: jax.Array,
    omega: jax.Array,
    i_force: jax.Array | None = None,
) -> tuple[CascadeState, jax.Array]:
    """One velocity period: ``(state, i_ref [A])``, clamped to ``+-I_max``; ``i_force`` replaces the force axis's."""
    assert s.velocity is not None  # a mode that closes the velocity loop carries its state
    sv, i_ref = loops.pi_loop_step(drive.velocity, s.velocity, w_ref, omega)
    if i_force is not None:
        k = mode.force_axis
        limit = drive.velocity.limit[..., k]
        i_ref = i_ref.at[..., k].set(jnp.clip(i_force, -limit, limit))
    return s._replace(velocity=sv), i_ref


def current_tick(
    drive: Drive, s: CascadeState, i_ref: jax.Array, current: jax.Array, omega: jax.Array
) -> tuple[CascadeState, jax.Array]:
    """One current period: ``(state, u [V])`` from the reference and the measured current [A] and speed [rad/s]."""
    sc, u = loops.pi_loop_step(drive.current, s.current, i_ref, current, drive.emf_gain * omega)
    return s._replace(current=sc), u
