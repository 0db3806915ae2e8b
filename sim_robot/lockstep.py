"""One bridge run against a simulated robot, as a user runs the two commands: ``pusupu sim-robot`` and ``pusupu
bridge``, each its own process, over UDP on loopback, in lock step.

In lock step each bridge cycle waits for the robot's answer to the last command (``--lockstep``), so that no cycle is
skipped on a loaded or non-real-time host and the run is the same whatever the machine's speed: what
``identify``'s benchmark and the real-to-sim experiment measure with.
"""

from __future__ import annotations

import json
import os
import socket
import subprocess
import sys
import tempfile
from pathlib import Path

from pusupu_jax.params import ParameterError

CLI = [sys.executable, "-m", "pusupu_jax.cli"]
LOCKSTEP_S = 0.5  # s, the bridge's wait for each answer: far above a cycle, so a stall is waited out, never a fault
BRIDGE_WATCHDOG = 100  # cycles without fresh feedback before the bridge's safe stop (a stall of the robot is no fault)
DRIVE_WATCHDOG_S = 5.0  # s, the robot's drives' sync watchdog: the same, on the robot's side


def free_udp_url() -> str:
    """``udp://127.0.0.1:PORT`` with a port that was free a moment ago."""
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as probe:
        probe.bind(("127.0.0.1", 0))
        return f"udp://127.0.0.1:{probe.getsockname()[1]}"


def bridge_run(
    gains: Path,
    trajectory: str,
    robot_machine: Path | None = None,
    bridge_machine: Path | None = None,
    seconds: float | None = None,
    fine_steps: int | None = None,
    kin_error: int | None = None,
    log: Path | None = None,
    noise_seed: int | None = None,
    lockstep: bool = True,
) -> dict:
    """``pusupu bridge --gains gains --trajectory trajectory`` (``--machine bridge_machine``, ``--duration seconds``,
    ``--log log``) against ``pusupu sim-robot --gains gains --machine robot_machine`` (``--fine-steps fine_steps``,
    ``--kin-error kin_error``, ``--noise-seed noise_seed``; None: the built-in machine, the model's stepping, no
    kinematic errors, the robot's default seed of its sensors' noise), in lock step (``lockstep=False``: in real
    time, as on a robot, each cycle on its deadline whether the robot answered or not; on a loaded host cycles go late
    and are skipped); returns the bridge's JSON report.  A run that fails, or a robot that does not start, raises
    :class:`~pusupu_jax.params.ParameterError` with the command's last words."""
    url = free_udp_url()
    robot_args = ["sim-robot", "--gains", str(gains), "--listen", url, "--seconds", "3600", "--no-realtime"]
    robot_args += ["--drive-watchdog", f"{DRIVE_WATCHDOG_S:g}"]
    robot_args += [] if robot_machine is None else ["--machine", str(robot_machine)]
    robot_args += [] if fine_steps is None else ["--fine-steps", str(fine_steps)]
    robot_args += [] if kin_error is None else ["--kin-error", str(kin_error)]
    robot_args += [] if noise_seed is None else ["--noise-seed", str(noise_seed)]
    with tempfile.TemporaryFile("w+") as robot_err:  # a file, not a pipe: a talkative robot never blocks on it
        robot = subprocess.Popen(CLI + robot_args, stdout=subprocess.PIPE, stderr=robot_err, text=True, env=os.environ)
        try:
            line = robot.stdout.readline() if robot.stdout else ""
            if "listening" not in line:
                robot.wait(timeout=60)
                robot_err.seek(0)
                raise ParameterError(f"sim-robot did not start: {(robot_err.read() or line).strip()[-500:]}")
            return _bridge(gains, trajectory, url, bridge_machine, seconds, log, lockstep)
        finally:
            robot.terminate()
            robot.wait(timeout=60)


def _bridge(gains, trajectory, url, bridge_machine, seconds, log, lockstep) -> dict:
    """The bridge's run against the robot at ``url``; its JSON report."""
    args = ["bridge", "--gains", str(gains), "--robot", url, "--trajectory", trajectory, "--no-realtime"]
    args += ["--lockstep", f"{LOCKSTEP_S if lockstep else 0:g}", "--watchdog", str(BRIDGE_WATCHDOG), "--json"]
    args += [] if bridge_machine is None else ["--machine", str(bridge_machine)]
    args += [] if seconds is None else ["--duration", f"{seconds:g}"]
    args += [] if log is None else ["--log", str(log)]
    r = subprocess.run(CLI + args, capture_output=True, text=True, env=os.environ)
    if r.returncode != 0:
        raise ParameterError(f"the bridge run failed (exit {r.returncode}): {r.stderr.strip()[-500:]}")
    report: dict = json.loads(r.stdout)
    return report
