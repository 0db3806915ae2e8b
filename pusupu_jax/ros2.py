"""ROS 2 parameter files for the tuned position loop (host-side): ros2_controllers' ``pid_controller`` and the
joint trajectory controller's ``gains.<joint>`` blocks, in joint units, loadable as they are.

What ROS runs (control_toolbox's ``Pid``, as ``pid_controller`` calls it with
``reference_and_state_interfaces: [position, velocity]``), every controller_manager period ``dt``::

    u   = clamp(p e + I + d (v_ref - v), u_clamp_min, u_clamp_max)      e = s_ref - s
    cmd = feedforward_gain v_ref + u                                     (JTC: ff_velocity_scale)
    I  += dt i e   (after the command, unless conditional integration holds it), clamped to i_clamp

Our controllers map onto that (:func:`ros_gains`):

* ``pid`` and ``pid_ff``: ``p, i, d = Kp_pid, Ki_pid, Kd_pid``, ``feedforward_gain = Kff_pid``
  (pid_ff) or 0.  Dropped: the derivative filter ``Tf_pid``.  ROS takes the velocity error
  instead of differentiating the position.
* ``imc`` and ``hybrid``: ``C2`` (eq. 9) is the PID ``p = (3 l2 + T0)/(3 l2^2)``, ``i = 1/(3 l2^2)``,
  ``d = T0/l2`` behind the filter ``1/((l2/3) s + 1)``.  Dropped: that output filter and the
  prefilter ``C1``, which sets the IMC's tracking (ROS's PID has neither), and in hybrid mode
  branch 6's force control (ROS's PID holds its position like the other five).

Units: the joints are the sliders, position [m] and velocity [m/s]. Our gains map a motor angle
[rad] to a motor speed [rad/s]. Both sides scale by the screw's ``r = lead / 2 pi``, so ``p``
[1/s], ``i`` [1/s^2], ``d`` [1] and the feedforward gain [1] keep their values. The clamps
become the slider speed at which the motor's back-EMF reaches ``V_max``: ``r V_max / Ke`` [m/s].
``pusupu gains check-ros`` simulates exactly this (``sim.rollout(outer='ros_pid')``) on the
machine, beside the full controller, so that the price of running on ROS shows before the robot.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import yaml

from . import files as outputs
from .cascade import MODES, Law, Mode, control_mode
from .inputs import shown
from .params import LoopRates, ParameterError, ServoParams
from .plant.axis import screw_ratio

if TYPE_CHECKING:
    from .machine_file import Machine

ANTIWINDUP = "conditional_integration"  # what our PIs do (integration held while the clamp and the error agree)
JOINTS = tuple(f"slide_{k}" for k in range(1, 7))
PID_CONTROLLER, TRAJECTORY_CONTROLLER = "pusupu_pid_controller", "pusupu_trajectory_controller"
FILES = ("ros2_pid_controller.yaml", "ros2_joint_trajectory_controller.yaml")


def ros_gains(servo: ServoParams, mode: str) -> dict[str, np.ndarray]:
    """``{p, i, d, ff}`` per axis (arrays (6,)) of ROS's PID for the position loop of ``mode``."""
    law = control_mode(mode).law if mode in MODES else None
    if law in (Law.PID, Law.PID_FF):
        ff = np.asarray(servo.Kff_pid, dtype=float) if law == Law.PID_FF else np.zeros(6)
        return {
            "p": np.asarray(servo.Kp_pid, dtype=float),
            "i": np.asarray(servo.Ki_pid, dtype=float),
            "d": np.asarray(servo.Kd_pid, dtype=float),
            "ff": ff,
        }
    if law != Law.IMC:
        raise ParameterError(f"ROS export: expected a mode of imc, pid, pid_ff or hybrid, got {mode!r}")
    l2, T0 = np.asarray(servo.lambda2, dtype=float), np.asarray(servo.T0, dtype=float)
    return {"p": (3 * l2 + T0) / (3 * l2**2), "i": 1 / (3 * l2**2), "d": T0 / l2, "ff": np.zeros(6)}


def as_ros_servo(servo: ServoParams, mode: str) -> ServoParams:
    """``servo`` with its PID fields set to what ROS will run (:func:`ros_gains`), for ``rollout(outer='ros_pid')``."""
    g = ros_gains(servo, mode)
    return servo.replace(Kp_pid=g["p"], Ki_pid=g["i"], Kd_pid=g["d"], Kff_pid=g["ff"])


def speed_clamp(servo: ServoParams) -> np.ndarray:
    """Slider speed [m/s] at which the back-EMF reaches ``V_max``: ROS's output and integral clamps, per axis."""
    return np.asarray(screw_ratio(servo) * servo.V_max / servo.Ke, dtype=float)


def update_rate(rates: LoopRates) -> int:
    """The controller_manager rate [Hz]: the position loop's."""
    hz = 1.0 / rates.dt_position
    if abs(hz - round(hz)) > 1e-6:
        raise ParameterError(
            f"ROS export: the position loop runs at {hz} Hz; controller_manager needs a whole number of Hz"
        )
    return int(round(hz))


def _gains_block(
    servo: ServoParams, mode: str, joints: Sequence[str], ff_key: str
) -> dict[str, dict[str, float | str]]:
    g, clamp = ros_gains(servo, mode), speed_clamp(servo)
    return {
        j: {
            "p": float(g["p"][a]),
            "i": float(g["i"][a]),
            "d": float(g["d"][a]),
            ff_key: float(g["ff"][a]),
            "u_clamp_max": float(clamp[a]),
            "u_clamp_min": -float(clamp[a]),
            "i_clamp_max": float(clamp[a]),
            "i_clamp_min": -float(clamp[a]),
            "antiwindup_strategy": ANTIWINDUP,
        }
        for a, j in enumerate(joints)
    }


def pid_controller_params(
    servo: ServoParams, mode: str, rates: LoopRates, joints: Sequence[str] = JOINTS, name: str = PID_CONTROLLER
) -> dict[str, Any]:
    """A ``pid_controller/PidController`` on the six slider joints, commanding velocity, with its controller_manager."""
    check_joints(joints)
    return {
        "controller_manager": {
            "ros__parameters": {"update_rate": update_rate(rates), name: {"type": "pid_controller/PidController"}}
        },
        name: {
            "ros__parameters": {
                "dof_names": list(joints),
                "command_interface": "velocity",
                "reference_and_state_interfaces": ["position", "velocity"],
                "gains": _gains_block(servo, mode, joints, "feedforward_gain"),
            }
        },
    }


def trajectory_controller_params(
    servo: ServoParams,
    mode: str,
    rates: LoopRates,
    joints: Sequence[str] = JOINTS,
    name: str = TRAJECTORY_CONTROLLER,
) -> dict[str, Any]:
    """A ``joint_trajectory_controller/JointTrajectoryController`` commanding velocity, with the same PIDs."""
    check_joints(joints)
    return {
        "controller_manager": {
            "ros__parameters": {
                "update_rate": update_rate(rates),
                name: {"type": "joint_trajectory_controller/JointTrajectoryController"},
            }
        },
        name: {
            "ros__parameters": {
                "joints": list(joints),
                "command_interfaces": ["velocity"],
                "state_interfaces": ["position", "velocity"],
                "gains": _gains_block(servo, mode, joints, "ff_velocity_scale"),
            }
        },
    }


def check_joints(joints: object, where: str = "ROS joints") -> None:
    """The exporter's rule for joint names: 6 distinct names of letters, digits and ``_`` (ParameterError naming
    ``where`` otherwise)."""
    if (
        not isinstance(joints, (list, tuple))
        or len(joints) != 6
        or len(set(joints)) != 6
        or not all(isinstance(j, str) and j and j.replace("_", "").isalnum() and j.isascii() for j in joints)
    ):
        raise ParameterError(f"{where}: expected 6 distinct names of letters, digits and _, got {shown(joints)}")


def header(mode: str, source: str) -> str:
    """The comment at the top of an exported file: where it comes from, its units, what ROS carries and drops."""
    dropped = (
        "the derivative filter Tf_pid (ROS uses the velocity error instead)"
        if control_mode(mode).law in (Law.PID, Law.PID_FF)
        else "the IMC prefilter C1 (which sets tracking), C2's output filter 1/((lambda2/3) s + 1)"
        + (", and branch 6's force control (hybrid mode): ROS holds its position" if control_mode(mode).hybrid else "")
    )
    return (
        f"# Exported by pusupu_jax from {source}: the tuned {mode} position loop as ROS 2 PIDs.\n"
        "# Joint units: slider position [m], velocity [m/s]; p [1/s], i [1/s^2], d [1], feedforward [1]; clamps\n"
        "# [m/s] (the slider speed at which the back-EMF reaches V_max).\n"
        "# ROS's PID carries: p, i, d on the position and velocity errors, the velocity feedforward, clamps,\n"
        f"# {ANTIWINDUP} anti-windup. It drops: {dropped}.\n"
        "# pusupu gains check-ros shows what that costs on the simulated machine.\n"
    )


def files(
    servo: ServoParams, mode: str, rates: LoopRates, source: str, joints: Sequence[str] = JOINTS
) -> dict[str, str]:
    """``{file name: text}`` of the two parameter files (:data:`FILES`), each with its :func:`header`."""
    params = (
        pid_controller_params(servo, mode, rates, joints),
        trajectory_controller_params(servo, mode, rates, joints),
    )
    return {name: header(mode, source) + yaml.safe_dump(p, sort_keys=False) for name, p in zip(FILES, params)}


def write_files(
    folder: str | os.PathLike[str],
    servo: ServoParams,
    mode: str,
    rates: LoopRates,
    source: str,
    joints: Sequence[str] = JOINTS,
) -> list[Path]:
    """Write the two parameter files (:func:`files`) into ``folder`` (atomically, both or neither)."""
    return outputs.write_files(
        {Path(folder) / name: text for name, text in files(servo, mode, rates, source, joints).items()}
    )


def short_of_floors(servo: ServoParams, mode: str, machine: Machine, floors: tuple[float, float]) -> str | None:
    """What ROS's PID, run with the gains exported from ``servo`` in ``mode`` (:func:`as_ros_servo`), keeps below
    ``floors`` (phase [deg], gain [dB] margin) on ``machine``'s single-axis model: a line naming each such loop's
    least margins over the axes, or None.  A gain file's own controller keeps them where it loads; ROS's drops the
    derivative filter, and in IMC mode the prefilter and C2's output filter."""
    from .gains import margins_report

    margins = margins_report(as_ros_servo(servo, mode), Mode.ROS_PID, machine)
    least = {
        loop: (float(np.min(m["phase_margin_deg"])), float(np.min(m["gain_margin_db"]))) for loop, m in margins.items()
    }
    short = [
        f"its {loop} loop {pm:.1f} deg and {gm:.1f} dB"
        for loop, (pm, gm) in least.items()
        if not (pm >= floors[0] and gm >= floors[1])
    ]
    if not short:
        return None
    return (
        f"ROS's PID with these gains keeps less than {floors[0]:g} deg and {floors[1]:g} dB on machine "
        f"{machine.name!r}: {', '.join(short)} (pusupu gains check-ros compares it with the gain file's controller)"
    )
