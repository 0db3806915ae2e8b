"""A user's machine end to end, from the README's commands (the quick tuning configuration): the machine file and a
pose table with tilts are checked, tuned on, exported with the machine's name, checked on that machine and run by the
bridge against the simulated robot built from the same file; the built-in machine refuses the gains.  (A batch job
file that names the machine is read in tests/test_batch.py; its end-to-end run is left to the command line, to keep
the suite's time.)"""

import json
import subprocess
import sys
from pathlib import Path

import pytest

pytestmark = pytest.mark.slow  # integration: every test here runs commands end to end

EXAMPLES = Path(__file__).parent.parent / "docs" / "examples"
MACHINE, PATH = EXAMPLES / "machine_user.yaml", EXAMPLES / "pose_table.csv"


def pusupu(*args, timeout=900):
    return subprocess.run(
        [sys.executable, "-m", "pusupu_jax.cli", *map(str, args)], capture_output=True, text=True, timeout=timeout
    )


def test_a_users_machine_end_to_end(tmp_path, in_process, refused):
    """The quick configuration in its own mode, hybrid, on the shape of tests/test_cli.py's tiny tune (two 0.1 s
    windows), whose traced gradient it loads: the machine's drives and the derived start gains are the program's
    arguments.  Three iterations on windows kept for all three (``refresh_every: 10``) at a learning rate of 0.01:
    J went 1.1000 -> 1.1035 -> 1.0965 and ended at 1.0957 (2-core CPU).  The windows cover 0.2 s of the 2 s path:
    along the whole of it the platform's RMS error moved 1.853 -> 1.903 mm; a smoke run of every step, not a tuning
    (the README's walk-through tunes).  The bridge runs the hybrid file's cycle, 4 kHz, for 1 s in lock step."""
    in_process("machine", "check", MACHINE, "--trajectory", PATH)  # the checks run in this process; the rest in its own
    config = tmp_path / "quick.yaml"
    config.write_text(
        f"trajectories: [{PATH}]\nwindows: 2\nwindow_s: 0.1\niterations: 3\nlearning_rate: 0.01\n"
        "refresh_every: 10\ncheckpoint_every: 10\n"
    )
    out = tmp_path / "out"
    r = pusupu("tune", "--machine", MACHINE, "--quick", "--config", config, "--out", out, "--json")
    assert r.returncode == 0, r.stderr
    report = json.loads(r.stdout)
    assert report["machine"]["name"] == "user-1FT7044-lead5"
    start = report["start_gains"]
    assert start["source"] == "derived" and len(start["T0_identified_s"]) == 6
    assert report["start"]["T0"] != [0.01475] * 6  # T0 identified on this machine, not Table 1's
    assert report["objective_after"] < report["objective_before"]
    gain_file = out / "gains.yaml"
    assert "tuned on machine 'user-1FT7044-lead5'" in in_process("gains", "check", gain_file, "--machine", MACHINE)
    # on the built-in machine: its 10 A drive, the user's 31 A clamp
    assert "I_max: expected 0 to I_peak = 10" in refused("gains", "check", gain_file)
    robot = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "pusupu_jax.cli",
            "sim-robot",
            "--gains",
            gain_file,
            "--machine",
            MACHINE,
            "--listen",
            "udp://127.0.0.1:5611",
            "--seconds",
            "120",
            "--no-realtime",
            "--drive-watchdog",  # the bridge's cycles wait on the robot in lock step: a stall of either is no fault
            "2",
        ],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        # the robot compiles its programs before it opens its port, and says so: on a loaded machine that took
        # longer than the bridge waits for the drives to come up
        assert "listening" in robot.stdout.readline(), robot.stderr.read()
        r = pusupu(
            "bridge",
            "--gains",
            gain_file,
            "--machine",
            MACHINE,
            "--robot",
            "udp://127.0.0.1:5611",
            "--trajectory",
            PATH,
            "--duration",
            "1",
            "--no-realtime",
            # this run is about the machine file, and the suite's other workers and the robot share two cores with
            # it: in real time a 6 ms stall of the robot tripped the watchdog once, and 4 late cycles in a row the
            # deadline check once; in lock step each cycle waits for the robot's answer and a late one delays the rest
            "--lockstep",
            "0.5",
            "--json",
        )
        assert r.returncode == 0, r.stderr
        run = json.loads(r.stdout)
        assert run["faults"] == [] and run["cycles"] > 0
    finally:
        robot.terminate()
        robot.wait(timeout=60)
