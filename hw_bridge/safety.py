"""Limits, guards, the feedback watchdog, the following error and the fault log of the bridge (host-side, plain numpy).

Every feedback sample passes :meth:`Safety.check_feedback` and :meth:`Safety.check_following`,
and every command :meth:`Safety.limit_command` before it is sent, so no command outside the
limits ever leaves the bridge: targets are clamped, and a non-finite target is a fault (the
command sent is then the safe one, zero).  A fault latches: the bridge sends CiA 402 quick stop,
then disable voltage.
"""

from __future__ import annotations

import enum
from dataclasses import dataclass, field

import numpy as np

from pusupu_jax.params import command_limits

from .protocol import CSV


@dataclass(frozen=True)
class Limits:
    """Per-axis limits, arrays ``(n_axes,)``, motor side.

    ``position_min``/``position_max`` [rad from home]: the strokes; ``velocity`` [rad/s]: the largest
    speed command; ``torque`` [N m]: the largest torque command (``Kt I_max``); ``following_error``
    [m of slider travel] and ``following_error_time`` [s]: the following-error window and time-out
    (CiA 402 objects 0x6065, 0x6066); ``screw`` [m of slider travel per rad of motor angle]: the
    screw ratio ``lead/2 pi``; ``feedback_margin``: measured speeds and torques beyond ``margin``
    times their limit are faults (a broken encoder or a corrupted packet, not a motion).
    """

    position_min: np.ndarray
    position_max: np.ndarray
    velocity: np.ndarray
    torque: np.ndarray
    following_error: np.ndarray
    following_error_time: np.ndarray
    screw: np.ndarray
    feedback_margin: float = 2.0

    def __post_init__(self):
        for name in (
            "position_min",
            "position_max",
            "velocity",
            "torque",
            "following_error",
            "following_error_time",
            "screw",
        ):
            v = np.asarray(getattr(self, name), dtype=float)
            if v.ndim != 1 or np.isnan(v).any():
                raise ValueError(f"limits.{name}: expected one number per axis, got {v}")
            object.__setattr__(self, name, v)
        if not (
            np.all(self.position_min < self.position_max)
            and np.all(self.velocity > 0)
            and np.all(self.torque > 0)
            and np.all(self.following_error > 0)
            and np.all(self.following_error_time >= 0)
            and np.all(self.screw > 0)
        ):
            raise ValueError(
                "limits: expected position_min < position_max, positive velocity, torque, following-error "
                "and screw values and a following-error time of at least 0"
            )


class FaultKind(enum.StrEnum):
    """What stopped a run: the machine, the drives, the transport or the bridge's own code."""

    FEEDBACK_STALE = "feedback stale"  # no new feedback within the watchdog, or the drives did not come up
    FEEDBACK_INVALID = "feedback invalid"  # NaN or inf, or speed or torque beyond their margin
    POSITION_LIMIT = "position limit"  # an axis outside its stroke
    FOLLOWING_ERROR = "following error"  # an axis beyond its window for longer than its time-out
    COMMAND_INVALID = "command invalid"  # the loops computed a NaN or inf target
    DEADLINE = "deadline"  # consecutive cycles missed their deadline
    DRIVE_FAULT = "drive fault"  # a drive left 'operation enabled', or did not enable
    INTERNAL_ERROR = "internal error"  # an exception of the bridge's own code in a cycle


@dataclass
class Fault:
    cycle: int
    kind: FaultKind
    detail: str

    def line(self) -> str:
        return f"cycle {self.cycle}: {self.kind}: {self.detail}"


@dataclass
class Safety:
    """Guards on one bridge run; ``faults`` logs every fault with its cycle, the first one latches the safe stop."""

    limits: Limits
    watchdog_cycles: int = 5  # feedback older than this many cycles stops the machine
    faults: list = field(default_factory=list)

    def __post_init__(self):
        lim, m = self.limits, self.limits.feedback_margin
        # the bounds of (position, velocity, torque) side by side: one comparison passes a good sample (NaN fails it)
        self._low = np.concatenate([lim.position_min, -m * lim.velocity, -m * lim.torque])
        self._high = np.concatenate([lim.position_max, m * lim.velocity, m * lim.torque])
        self._bound = {}  # drive modes (bytes) -> the command bound of each axis
        self._window = lim.following_error / lim.screw  # rad of motor angle
        self._beyond_since = np.full(len(lim.screw), np.inf)  # s: since when each axis is beyond its window (inf: not)

    @property
    def tripped(self) -> bool:
        return bool(self.faults)

    def fault(self, cycle: int, kind: FaultKind, detail: str) -> None:
        self.faults.append(Fault(cycle, kind, detail))

    def check_feedback(self, cycle: int, age: int, position, velocity, torque) -> bool:
        """True when the sample may drive the loops: fresh (``age`` cycles old at most the watchdog), finite, in
        range."""
        lim = self.limits
        if age > self.watchdog_cycles:
            self.fault(
                cycle, FaultKind.FEEDBACK_STALE, f"no new feedback for {age} cycles (watchdog {self.watchdog_cycles})"
            )
            return False
        values = np.concatenate((position, velocity, torque))
        inside = (values >= self._low) & (values <= self._high)
        if inside.all():
            return True
        # a fault: name it (NaN is outside every bound, so it is looked for first)
        n = len(position)
        if not np.isfinite(values).all():
            self.fault(cycle, FaultKind.FEEDBACK_INVALID, "NaN or inf in the measured position, velocity or torque")
        elif not inside[n:].all():
            self.fault(
                cycle,
                FaultKind.FEEDBACK_INVALID,
                f"measured speed or torque beyond {lim.feedback_margin} times its limit",
            )
        else:
            k = int(np.argmin(inside[:n]))  # the first axis outside its stroke
            self.fault(
                cycle,
                FaultKind.POSITION_LIMIT,
                f"axis {k + 1} at {position[k]:.4g} rad, outside "
                f"[{lim.position_min[k]:.4g}, {lim.position_max[k]:.4g}]",
            )
        return False

    def check_following(self, cycle: int, t: float, reference, position) -> bool:
        """True unless an axis's position error ``reference - position`` [rad of motor angle] has stayed beyond its
        following-error window for longer than its time-out (CiA 402 0x6065, 0x6066); ``t`` [s]: the cycle's time in
        the run.  Called once per cycle of a run, whose first call starts it."""
        lim = self.limits
        error = reference - position
        beyond = np.abs(error) > self._window
        self._beyond_since = np.where(beyond, np.minimum(self._beyond_since, t), np.inf)
        late = t - self._beyond_since > lim.following_error_time
        if not late.any():
            return True
        k = int(np.argmax(late))
        self.fault(
            cycle,
            FaultKind.FOLLOWING_ERROR,
            f"axis {k + 1} {error[k] * lim.screw[k] * 1e3:.3g} mm of slider travel "
            f"from its reference, beyond its {lim.following_error[k] * 1e3:.3g} mm "
            f"window for {(t - self._beyond_since[k]) * 1e3:.0f} ms (time-out "
            f"{lim.following_error_time[k] * 1e3:.0f} ms)",
        )
        return False

    def limit_command(self, cycle: int, modes, target) -> np.ndarray:
        """``target`` clamped to the velocity (CSV) or torque (CST) limit of each axis; all zero if any is not
        finite."""
        if not np.isfinite(target).all():
            self.fault(cycle, FaultKind.COMMAND_INVALID, "the loops computed a NaN or inf target")
            return np.zeros_like(target)
        modes = np.asarray(modes)
        bound = self._bound.get(modes.tobytes())
        if bound is None:
            bound = self._bound[modes.tobytes()] = np.where(modes == CSV, self.limits.velocity, self.limits.torque)
        return np.minimum(np.maximum(target, -bound), bound)


def limits_for(servo, geom=None):
    """The bridge's limits on the geometry ``geom`` (default: the built-in one): strokes from home, V_max/Ke, Kt I_max,
    the following-error window and time-out (host-side)."""
    import jax.numpy as jnp

    from pusupu_jax.plant import kinematics
    from pusupu_jax.plant.geometry import Geometry

    geom = Geometry.default() if geom is None else geom
    r = np.asarray(servo.lead, dtype=float) / (2 * np.pi)
    s_home = np.asarray(kinematics.inverse_kinematics(geom, jnp.asarray(geom.home)))
    return Limits(
        (np.asarray(geom.stroke_min) - s_home) / r,
        (np.asarray(geom.stroke_max) - s_home) / r,
        *command_limits(servo),
        np.asarray(servo.following_error, dtype=float),
        np.asarray(servo.following_error_time, dtype=float),
        r,
    )
