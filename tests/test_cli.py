"""The ``pusupu`` command, run as a user runs it (a real subprocess, real files); the refusals of bad input that
need no process of their own call its ``main`` in this process (the ``refused`` fixture, tests/conftest.py), and so
do the commands whose output is the point rather than the process (``in_process``: a process of its own costs some
3 s of CPU to start Python and JAX and load its programs), among them the tiny tuning run and the commands that read
its files or resume it (its programs are in this process's memory, and the same command runs as a process of its
own when it is killed and interrupted)."""

import hashlib
import json
import os
import signal
import subprocess
import sys
import time

import numpy as np
import pytest


def pusupu(*args, check=True):
    r = subprocess.run(
        [sys.executable, "-m", "pusupu_jax.cli", *args],
        capture_output=True,
        text=True,
        env=dict(os.environ),
        timeout=600,
    )
    if check:
        assert r.returncode == 0, r.stderr
    return r


@pytest.mark.slow
def test_analyze_json_has_every_loop_of_every_axis(tmp_path, in_process):
    """Also along the arc (``--trajectory``): each slider's carried mass at the arc's poses spans home's, and the
    velocity loop crosses over later with the lighter load on every axis (the same gains push less mass).  With
    ``--coupled``, every axis's loops in the coupled model at home, where the other five axes' velocity loops damp
    each branch through the mechanism: its velocity loop has more phase margin than the single-axis model's (26 deg
    more on the built-in machine, docs/machine.md)."""
    from pusupu_jax import machine_file

    png = tmp_path / "loops.png"
    out = json.loads(in_process("analyze", "--json", "--plot", png, "--trajectory", "arc", "--coupled"))
    coupled = out["coupled"]
    assert coupled["pose"] == list(machine_file.Machine.default().geometry.home) and len(coupled["axes"]) == 6
    for single, both in zip(out["axes"], coupled["axes"]):
        assert set(both) == {"current", "velocity", "position"}
        assert both["velocity"]["phase_margin_deg"] > single["velocity"]["phase_margin_deg"] + 10
    assert len(out["axes"]) == 6
    for axis in out["axes"]:
        for loop in ("current", "velocity", "position"):
            assert set(axis[loop]) == {
                "crossover_hz",
                "phase_margin_deg",
                "gain_margin_db",
                "bandwidth_hz",
                "rise_time_s",
                "settling_time_s",
                "overshoot_pct",
            }
    assert out["axes"][0]["current"]["crossover_hz"] == pytest.approx(244.7, rel=0.005)  # the machine's 54.7 kg
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    along = out["along_path"]
    light, heavy = (np.asarray(along["carried_mass_kg"][k]) for k in ("lightest", "heaviest"))
    home = machine_file.carried_mass(machine_file.Machine.default())
    assert np.all(light <= home) and np.all(home <= heavy) and np.all(heavy - light > 1.0)
    for k in range(6):
        assert along["lightest"][k]["velocity"]["crossover_hz"] > along["heaviest"][k]["velocity"]["crossover_hz"]


def test_sim_step_prints_metrics_and_plots(tmp_path, in_process):
    png = tmp_path / "step.png"
    out = json.loads(
        in_process("sim", "--plant", "axis", "--trajectory", "step", "--json", "--plot", png, "--duration", "0.5")
    )
    assert out["duration_s"] == pytest.approx(0.5)
    assert len(out["rms_error_mm"]) == 6 and 0 < out["rms_error_mm"][0] < 5
    assert out["max_error_mm"][0] == pytest.approx(5.0, rel=1e-3)  # the step itself, at t = 0
    assert png.stat().st_size > 10_000
    table = in_process("sim", "--trajectory", "sine", "--mode", "pid", "--duration", "0.2")
    assert "rms_error_mm" in table and "pid mode" in table


@pytest.mark.parametrize(
    "args,message",
    [
        (["sim", "--params", "{bad}"], "servo: {Tv: -1}"),
        (["analyze", "--params", "{bad}"], "servo: {Foo: 1}"),
        (["sim", "--trajectory", "bogus"], None),
        (["sim", "--plot", "/no/such/folder/x.png"], None),
        (["analyze", "--params", "/no/such/file.yaml"], None),
        (["batch", "job.yaml", "--ray", "--workers", "1", "--cpus-per-task", "2"], None),
        (["tune", "--config", "{bad}", "--out", "{bad}.out"], "draws: 2\n"),  # the built-in machine: nothing to draw
        # refused once the problem is built, in the folder the run made: no folder left behind
        (["tune", "--config", "{bad}", "--out", "{bad}.out"], "bounds: {lambda2: [0.2, 0.5]}\n"),
    ],
)
def test_bad_input_exits_2_with_one_line(tmp_path, args, message):
    bad = tmp_path / "bad.yaml"
    if message:
        bad.write_text(message)
    r = pusupu(*[a.replace("{bad}", str(bad)) for a in args], check=False)
    assert r.returncode == 2
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("pusupu: error: "), r.stderr
    assert "Traceback" not in r.stderr and r.stdout == ""
    assert not (tmp_path / "bad.yaml.out").exists()


@pytest.mark.parametrize(
    "args",
    [
        ["sim", "--plant", "mjx", "--trajectory", "sine"],
        ["sim", "--plant", "axis", "--trajectory", "arc"],
        ["sim", "--plant", "axis", "--kin-error", "3"],
        ["sim", "--plant", "mjx", "--duration", "2"],
        ["sim", "--plant", "axis", "--mode", "hybrid"],
        ["analyze", "--identify-T0", "--trajectory", "arc"],
        ["analyze", "--identify-T0", "--coupled"],
        ["sim", "--plant", "mjx", "--device", "gpu"],  # no GPU for JAX where the suite runs
        ["tune", "--device", "tpu"],
        ["identify", "run.mcap", "--fit", "mass", "--out", "x.yaml"],
        ["identify", "/no/such/run.mcap", "--out", "x.yaml"],
        ["experiment", "servo", "--out", f"{__file__}/out"],  # under a file: refused before it runs
    ],
)
def test_bad_machine_arguments_exit_2_with_one_line(args, refused):
    refused(*args)


@pytest.mark.slow
def test_sim_mjx_hybrid_takes_its_gains_from_the_params_file_and_reports_the_machine_metrics(tmp_path, in_process):
    """Hybrid mode on the p2p path with kinematic errors; the eq. 14 gains come from the file's hybrid section; the
    machine's metrics per branch, the loop closure and the figure.  In this process: its chunk program is the one
    the tiny tune below runs (a simulation and a tune of one mode share it)."""
    params, png = tmp_path / "params.yaml", tmp_path / "p2p.png"
    params.write_text("hybrid: {m6: 0.5, c6: 4000.0, g: 500.0, form: signed}\n")
    out = json.loads(
        in_process(
            "sim",
            "--plant",
            "mjx",
            "--trajectory",
            "p2p",
            "--mode",
            "hybrid",
            "--kin-error",
            "3",
            "--params",
            str(params),
            "--json",
            "--plot",
            str(png),
        )
    )
    assert out["mode"] == "hybrid" and out["kin_error_seed"] == 3
    assert out["hybrid"]["form"] == "signed" and out["hybrid"]["c6"] == 4000.0
    assert 50.0 < out["hybrid"]["force_ff_peak_n"] < 200.0  # branch 6's share of the ~90 kg machine's weight
    for key in ("branch_rms_error_mm", "motor_torque_peak_nm", "branch_force_peak_n"):
        assert len(out[key]) == 6 and all(v > 0 for v in out[key])
    assert 0 < out["rms_tracking_error_mm"] <= out["max_tracking_error_mm"] < 30
    assert out["loop_closure_residual_max_mm"] < 0.01 * out["rms_tracking_error_mm"]
    assert out["sync_error_rho"] > 0 and out["wall_s"] > 0
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_a_bad_hybrid_section_exits_2_naming_the_gain(tmp_path, refused):
    params = tmp_path / "params.yaml"
    params.write_text("hybrid: {c6: -3.0}\n")
    assert "HybridGains.c6: expected a number from 0 to" in refused(
        "sim", "--plant", "mjx", "--mode", "hybrid", "--params", params
    )


# two 0.1 s windows of a 0.3 s path (the second starts mid-path, from a carry the checkpoint keeps), as
# tests/test_batch.py's jobs: tuning one of them alone there runs the programs this command compiled (persistent
# cache), since a kinematic-error seed or payload only changes their arguments
TINY_TUNE = """\
trajectories: [p2p]
path_s: 0.3
windows: 2
window_s: 0.1
refresh_every: 2
iterations: 6
checkpoint_every: 2
baselines: [pid]
"""


@pytest.fixture(scope="module")
def tuned(tmp_path_factory, in_process):
    """One uninterrupted tiny tuning run (hybrid mode, two 0.1 s windows of the p2p path's first 0.3 s), in this
    process (the tests below run the same command as a process of its own, killed and interrupted, and read its files
    with commands that find its programs in memory): its folder and report."""
    folder = tmp_path_factory.mktemp("tune")
    (folder / "tiny.yaml").write_text(TINY_TUNE)
    return folder, json.loads(in_process("tune", "--config", folder / "tiny.yaml", "--out", folder / "out", "--json"))


@pytest.mark.slow
def test_tune_writes_gains_ros_files_report_and_plots(tuned, in_process):
    import yaml

    from pusupu_jax import gains, ros2

    folder, report = tuned
    out = folder / "out"
    for name in (
        "gains.yaml",
        "ros2_pid_controller.yaml",
        "ros2_joint_trajectory_controller.yaml",
        "report.json",
        "objective.png",
        "path_p2p.png",
        "forces_p2p.png",
        "checkpoint.npz",
    ):
        assert (out / name).stat().st_size > 0, name
    assert not list(out.glob("*.pkl"))
    assert report["tuned_fields"] == ["lambda1", "lambda2", "T0", "Kv", "Tv", "m6", "c6", "g"]
    assert report["objective_after"] <= report["objective_before"]
    assert set(report["before"]["p2p"]) >= {"rms_tracking_error_mm", "branch_force_peak_n"}
    assert set(report["baselines"]["pid"]["p2p"]) >= {"rms_tracking_error_mm", "branch_force_peak_n"}
    assert min(report["margins_after"]["position"]["phase_margin_deg"]) >= 45.0
    # the report names the gain file it describes
    assert report["gains_file"]["sha256"] == hashlib.sha256((out / "gains.yaml").read_bytes()).hexdigest()
    # the ROS files carry the conversion of the tuned controller, in joint units
    g = gains.load(out / "gains.yaml")
    assert g.document["controller"]["position"]["lambda2"]["tuned"] is True
    expected = ros2.ros_gains(g.servo, "hybrid")
    ros = yaml.safe_load((out / "ros2_pid_controller.yaml").read_text())[ros2.PID_CONTROLLER]["ros__parameters"]
    for k, joint in enumerate(ros["dof_names"]):
        assert [ros["gains"][joint][key] for key in "pid"] == [expected[key][k] for key in "pid"]
    # the exported gains drive the other commands
    a = json.loads(in_process("analyze", "--gains", out / "gains.yaml", "--json"))
    assert len(a["axes"]) == 6
    shown = in_process("gains", "show", out / "gains.yaml")
    assert "lambda2" in shown and "yes" in shown
    assert "valid pusupu-gains v4" in in_process("gains", "check", out / "gains.yaml")
    # checked at export with the masses the sliders carry at home and at the extremes of the tuned path, and so again
    loads = g.document["provenance"]["margin_loads_kg"]
    assert list(loads) == ["home", "lightest", "heaviest"]
    assert np.all(np.array(loads["lightest"]) <= loads["home"]) and np.all(np.array(loads["home"]) <= loads["heaviest"])
    # gains check --trajectory: the same check along the whole p2p path (in process: the command is a line around it)
    from pusupu_cli.common import check_along_paths
    from pusupu_jax.machine_file import Machine

    # the report keeps what ROS's PID with these gains keeps against the floors (None: the floors held)
    assert report.get("ros_warning") == ros2.short_of_floors(g.servo, "hybrid", Machine.default(), (45.0, 6.0))
    along = check_along_paths(g, Machine.default(), ["p2p"], (45.0, 6.0), "gains.yaml")
    assert list(along) == ["home", "lightest", "heaviest"]
    assert along["home"].mass.tolist() == loads["home"]
    assert np.all(along["lightest"].mass <= along["home"].mass) and np.all(along["heaviest"].mass >= along["home"].mass)


@pytest.mark.slow
def test_a_killed_tuning_run_resumes_from_its_checkpoint(tuned, tmp_path, in_process):
    """SIGKILL after the first checkpoint, run the same command again (in this process, which has the programs in
    memory): the result equals the uninterrupted run's."""
    folder, report = tuned
    cmd = [
        sys.executable,
        "-m",
        "pusupu_jax.cli",
        "tune",
        "--config",
        str(folder / "tiny.yaml"),
        "--out",
        str(tmp_path / "out"),
        "--json",
    ]
    p = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=dict(os.environ))
    deadline = time.time() + 600
    while not (tmp_path / "out" / "checkpoint.npz").exists() and p.poll() is None and time.time() < deadline:
        time.sleep(0.05)
    p.send_signal(signal.SIGKILL)
    p.communicate()
    assert p.returncode == -signal.SIGKILL, "the run ended before it could be killed"
    assert not (tmp_path / "out" / "gains.yaml").exists()
    resumed = json.loads(in_process(*cmd[3:]))
    assert resumed["result"] == report["result"]
    assert resumed["objective_after"] == report["objective_after"]


def test_ctrl_c_during_a_tune_ends_with_one_line(tuned, tmp_path):
    """Ctrl-C used to end in a KeyboardInterrupt traceback; now one line saying how to resume, and exit status 130."""
    folder, _ = tuned
    cmd = [
        sys.executable,
        "-m",
        "pusupu_jax.cli",
        "tune",
        "--config",
        str(folder / "tiny.yaml"),
        "--out",
        str(tmp_path / "out"),
    ]
    # Ctrl-C as at a terminal: SIGINT's default action in the child, even where this suite runs as a background job
    # of a non-interactive shell, which starts with SIGINT ignored (and Python then installs no KeyboardInterrupt)
    p = subprocess.Popen(
        cmd,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env=dict(os.environ),
        preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL),
    )
    deadline = time.time() + 600
    while not (tmp_path / "out" / ".pusupu.lock").exists() and p.poll() is None and time.time() < deadline:
        time.sleep(0.05)
    p.send_signal(signal.SIGINT)
    _, err = p.communicate(timeout=600)
    assert p.returncode == 130, err
    lines = [line for line in err.splitlines() if line.startswith("pusupu")]
    assert lines == [
        f"pusupu: interrupted (the checkpoint in {tmp_path / 'out'} keeps the run: the same command resumes it)"
    ], err
    assert "Traceback" not in err


@pytest.mark.slow
def test_a_ctrl_c_that_python_drops_in_a_gc_callback_still_ends_with_130():
    """A Ctrl-C landing in a garbage-collector callback (JAX registers one): Python drops its KeyboardInterrupt
    ('Exception ignored in ...'), and the command used to run on to exit 0 (seen once in this suite's Ctrl-C test).
    Here a callback sends SIGINT and lets the handler run inside it; the command finishes and exits 130 with the
    one line of any Ctrl-C, Python's report of the dropped exception left out.  (Before,
    a Ctrl-C during ``analyze`` also ended in an AttributeError: the message read ``args.out``, which it has not.)"""
    code = """
import gc, os, signal, sys
from pusupu_jax.cli import cli
fired = []
def callback(phase, info):
    if phase == "start" and not fired and "control" in sys.modules:  # in the command (python-control loaded)
        fired.append(1)
        os.kill(os.getpid(), signal.SIGINT)
        for _ in range(1000):  # the handler runs here, inside the callback, and its exception is dropped
            pass
gc.callbacks.append(callback)
status = cli.main(["analyze", "--json"])
print("fired", len(fired), file=sys.stderr)
sys.exit(status)
"""
    r = subprocess.run(
        [sys.executable, "-c", code],
        capture_output=True,
        text=True,
        timeout=600,
        preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL),
    )
    assert "fired 1" in r.stderr, r.stderr[-2000:]
    assert r.returncode == 130, r.stderr[-2000:]
    # one line, as for any Ctrl-C: no 'Exception ignored in ...' traceback for the dropped KeyboardInterrupt
    assert [line for line in r.stderr.splitlines() if line.strip()] == ["pusupu: interrupted", "fired 1"], r.stderr


def test_a_bad_gain_file_exits_2_with_one_line(tuned, tmp_path, refused):
    folder, _ = tuned
    bad = tmp_path / "gains.yaml"
    bad.write_text((folder / "out" / "gains.yaml").read_text().replace("version: 4", "version: 7"))
    for command in (["analyze"], ["sim"], ["gains", "show"], ["gains", "check"]):
        args = [*command, str(bad)] if command[0] == "gains" else [*command, "--gains", str(bad)]
        assert "version: expected 4" in refused(*args)


@pytest.mark.slow
def test_gains_check_ros_prints_both_controllers(tuned, in_process):
    folder, _ = tuned
    out = json.loads(
        in_process(
            "gains", "check-ros", folder / "out" / "gains.yaml", "--trajectory", "p2p", "--seconds", 0.3, "--json"
        )
    )
    for who in ("pusupu", "ros"):
        assert out["paths"]["p2p"][who]["rms_tracking_error_mm"] > 0
        assert out["position_margins"][who]["phase_margin_deg"] > 0
    assert out["ros_gains"]["d"][0] > 0


def test_a_foreign_checkpoint_is_refused_without_running(tmp_path, refused):
    """A crafted checkpoint.pkl in --out used to run its code.  Now nothing reads a pickle."""
    out = tmp_path / "out"
    out.mkdir()
    marker = tmp_path / "pwned"
    payload = f"cos\nsystem\n(S'touch {marker}'\ntR.".encode()  # a pickle that runs a shell command
    (out / "checkpoint.pkl").write_bytes(payload)
    assert "never read" in refused("tune", "--quick", "--out", out)
    (out / "checkpoint.pkl").unlink()
    (out / "checkpoint.npz").write_bytes(payload)  # the same bytes where the checkpoint is now kept
    assert "not a pusupu checkpoint" in refused("tune", "--quick", "--out", out, alone=False)
    assert not marker.exists()


def test_a_second_run_into_a_busy_folder_is_refused(tmp_path):
    """Two runs into one --out used to both say they wrote gains.yaml; now the second names the holder."""
    from pusupu_jax.tune.job import OutputLock

    out = tmp_path / "out"
    out.mkdir()
    lock = OutputLock(out)
    try:
        r = pusupu("tune", "--quick", "--fresh", "--out", str(out), check=False)
    finally:
        lock.release()
    assert r.returncode == 2 and f"pid {os.getpid()}" in r.stderr and "in use" in r.stderr, r.stderr


@pytest.mark.parametrize(
    "args, message",
    [
        (["tune", "--out", ""], "--out: expected a folder, got an empty name"),
        (["tune", "--quick", "--out", "{file}/sub"], "--out: cannot write"),
        (["tune", "--quick", "--out", "{file}"], "--out: expected a folder, got the file"),
        (["tune", "--config", "{config}"], "c.yaml: tune config pm_min: expected a finite number"),
        (["tune", "--config", "{missing_path}"], "p.yaml: tune config trajectories[0]: "),
        (["sim", "--plot", "{dir}"], "--plot: expected the path of a PNG, SVG or PDF file, got the folder"),
        (["sim", "--plot", ""], "--plot: expected the path of a PNG, SVG or PDF file, got an empty name"),
        (["sim", "--plot", "x.txt"], "--plot: expected a name ending .png, .svg or .pdf, got 'x.txt'"),
        (["sim", "--plot", ".png"], "--plot: expected a name ending .png, .svg or .pdf, got '.png'"),
        (["sim", "--plant", "mjx", "--log", "x.txt"], "--log: expected a name ending .mcap, got 'x.txt'"),
        (["sim", "--duration", "1e4"], "trajectory duration: expected at most 2000 s"),
        (["sim", "--params", "{rates}"], "rates: f_current is 1e+12 Hz; expected 1000 to 100000 Hz"),
        (["sim", "--plant", "mjx", "--kin-error", "-1"], "expected a non-negative integer seed"),
        (["sim", "--params", "{binary}"], "expected a UTF-8 text"),
        (["sim", "--params", "{bomb}"], "anchors are not accepted"),
        (["sim", "--params", "{mixed}"], "expected string keys"),
        (["sim", "--params", "{quoted}"], "ServoParams.Kv: expected a number, got str"),
        (["sim", "--params", "{duplicate}"], "duplicate key 'servo'"),
        (["sim", "--params", "{zero}"], "ServoParams: expected a mapping of fields, got int 0"),
        (
            ["sim", "--plant", "mjx", "--mode", "hybrid", "--params", "{hybrid_list}"],
            "HybridGains.m6: expected a number",
        ),
    ],
)
def test_every_probe_input_ends_in_one_line_and_exit_2(tmp_path, refused, args, message):
    """A reliability probe: inputs that ended in tracebacks, hangs or silent acceptance, each one line now,
    before any compile."""
    files = {
        "file": ("f.txt", b"x"),
        "dir": ("d", None),
        "config": ("c.yaml", b"pm_min: .nan\n"),
        "missing_path": ("p.yaml", b"trajectories: [nosuch.csv]\n"),
        "rates": ("r.yaml", b"rates: {f_current: 1.0e+12}\n"),
        "binary": ("b.yaml", bytes(range(256))),
        "bomb": ("bomb.yaml", b"a: &a [x, x]\nb: &b [*a, *a]\nservo: [*b, *b]\n"),
        "mixed": ("m.yaml", b"{1: 2, foo: 3}\n"),
        "quoted": ("q.yaml", b"servo: {Kv: '0.015'}\n"),
        "duplicate": ("dup.yaml", b"servo: {Kv: 0.01}\nservo: {Kv: 0.02}\n"),
        "zero": ("z.yaml", b"servo: 0\n"),
        "hybrid_list": ("h.yaml", b"hybrid: {m6: [1, 2, 3]}\n"),
    }
    paths = {}
    for key, (name, data) in files.items():
        paths[key] = tmp_path / name
        if data is None:
            paths[key].mkdir()
        else:
            paths[key].write_bytes(data)
    assert message in refused(*[a.format(**paths) if "{" in a else a for a in args])


def test_version_and_python_m():
    from pusupu_jax import __version__

    assert pusupu("--version").stdout.strip() == f"pusupu {__version__}"
    r = subprocess.run(
        [sys.executable, "-m", "pusupu_jax.cli", "--version"], capture_output=True, text=True, timeout=120
    )
    assert r.returncode == 0 and r.stdout.strip() == f"pusupu {__version__}"


def test_a_write_that_fails_midway_keeps_the_old_file_and_ends_in_one_line(tmp_path):
    """A full disk gave an ENOSPC traceback.  The process may write at most 4 kB per file
    (RLIMIT_FSIZE; the write fails with EFBIG where a full disk gives ENOSPC, through the same code).  Re-signing a
    gain file must end with one line and exit 2, the old file intact and no temporary left behind.  The command
    starts from an empty compilation cache, whose entries it then cannot write either: the warnings of JAX and of
    pusupu_jax.programs for each of them (some forty lines here) must not reach the user."""
    from pusupu_jax import LoopRates, ServoParams, gains
    from pusupu_jax.hybrid import HybridGains

    (tmp_path / "out").mkdir()
    path = gains.write(
        tmp_path / "out" / "gains.yaml", ServoParams.table1(), HybridGains(), LoopRates(n_mech=5), mode="imc"
    )
    before = path.read_bytes()
    limited = (
        "import resource, runpy, signal, sys; signal.signal(signal.SIGXFSZ, signal.SIG_IGN); "
        "resource.setrlimit(resource.RLIMIT_FSIZE, (4096, 4096)); "
        f"sys.argv = ['pusupu', 'gains', 'sign', {str(path)!r}]; "
        "runpy.run_module('pusupu_jax.cli', run_name='__main__')"
    )
    r = subprocess.run(
        [sys.executable, "-c", limited],
        capture_output=True,
        text=True,
        env=dict(os.environ, PUSUPU_JAX_CACHE=str(tmp_path / "cache")),
        timeout=300,
    )
    assert r.returncode == 2 and len(r.stderr.strip().splitlines()) == 1, r.stderr
    assert "File too large" in r.stderr
    assert path.read_bytes() == before and sorted(p.name for p in path.parent.iterdir()) == ["gains.yaml"]
