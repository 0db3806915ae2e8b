"""The user's paths: waypoint files and pose tables read and sampled, every fault in one line naming its row or field,
and every path checked against the machine (workspace, motor speeds, motor torques) before anything runs."""

import json
import re
import subprocess
import sys
from pathlib import Path

import jax.numpy as jnp
import numpy as np
import pytest

from pusupu_jax import LoopRates, ParameterError, ServoParams, paths, trajectories
from pusupu_jax.plant import dynamics, kinematics
from pusupu_jax.plant.axis import screw_ratio
from pusupu_jax.plant.geometry import Geometry, GeometryError

G = Geometry.default()
HOME = G.home
RATES = LoopRates()
DT = RATES.dt_position
SERVO = ServoParams.table1()
EXAMPLES = Path(__file__).resolve().parent.parent / "docs" / "examples"
HEAD = "format: pusupu-path\nversion: 1\n"
FAST = HEAD + "waypoints: [{pose: [0.1, 0, 0, 0, 0], speed: 2.0, acceleration: 100}]\n"  # 100 mm at up to 2 m/s


def _file(folder, name, text):
    path = Path(folder) / name
    path.write_text(text)
    return str(path)


def _table(folder, rows, header="t,x,y,z,a,b", name="path.csv"):
    return _file(folder, name, header + "\n" + "".join(",".join(str(v) for v in row) + "\n" for row in rows))


@pytest.mark.parametrize("name", ["waypoints.yaml", "pose_table.csv"])
def test_the_example_files_start_and_end_at_home_and_pass_the_checks(name):
    spec = str(EXAMPLES / name)
    q = paths.platform_path_from(spec, HOME, RATES)
    np.testing.assert_allclose(q[[0, -1]], [HOME, HOME], atol=1e-12)
    assert np.abs(q[:, 3:]).max() > 0.05 and np.abs(q[:, :3] - HOME[:3]).max() <= 0.1  # it tilts, within 100 mm
    assert paths.path_seconds(spec) == pytest.approx(len(q) * DT, abs=10 * DT)
    report = paths.check_path(q, SERVO, DT)
    assert max(report["motor_speed_peak_rad_s"]) < float(SERVO.speed_max[0])
    assert max(report["motor_torque_peak_nm"]) < float(SERVO.Kt[0] * SERVO.I_max[0])


@pytest.mark.parametrize("name", trajectories.PLATFORM_TRAJECTORIES)
def test_every_named_path_fits_the_default_machine(name):
    assert paths.platform_path_from(name, HOME, RATES).shape[1] == 5
    paths.check_path(paths.platform_path_from(name, HOME, RATES), SERVO, DT)


def test_a_segment_takes_the_longest_time_its_limits_need_and_dwells_at_its_arrival(tmp_path):
    """Segment 1: 100 mm and 0.05 rad at 0.05 m/s and 0.01 rad/s: the tilt's 9.375 s (1.875 x 0.05 / 0.01) rules, the
    centre peaks at 1.875 x 0.1 / 9.375 = 0.02 m/s; then 1 s at rest.  Segment 2 takes the file's defaults."""
    spec = _file(
        tmp_path,
        "p.yaml",
        HEAD + "defaults: {speed: 0.025, dwell: 0.5}\nwaypoints:\n"
        "  - {pose: [0.1, 0, 0, 0.05, 0], speed: 0.05, angular_speed: 0.01, dwell: 1.0}\n"
        "  - {pose: [0, 0, 0, 0, 0]}\n",
    )
    q = paths.platform_path_from(spec, HOME, RATES) - HOME
    first = int(round(9.375 / DT)) + 1
    np.testing.assert_allclose(q[first - 1], [0.1, 0, 0, 0.05, 0], atol=1e-15)
    assert np.all(q[first - 1 : first - 1 + int(round(1.0 / DT)) + 1] == q[first - 1])  # the dwell
    speed = np.linalg.norm(np.diff(q[:first, :3], axis=0), axis=1) / DT
    rate = np.linalg.norm(np.diff(q[:first, 3:], axis=0), axis=1) / DT
    assert speed.max() == pytest.approx(0.02, rel=1e-3) and rate.max() == pytest.approx(0.01, rel=1e-3)
    back = trajectories.segment_seconds(
        [[0.1, 0, 0, 0.05, 0], [0] * 5],
        0.025,
        paths.DEFAULTS["acceleration"],
        paths.DEFAULTS["angular_speed"],
        paths.DEFAULTS["angular_acceleration"],
    )[0]
    assert back == pytest.approx(1.875 * 0.1 / 0.025)  # defaults: speed from the file's, the others built in
    assert len(q) == first + int(round(1.0 / DT)) + int(np.ceil(back / DT)) + 1 + int(round(0.5 / DT))
    assert paths.path_seconds(spec) == pytest.approx(9.375 + 1.0 + back + 0.5)


def test_a_pose_table_is_resampled_by_a_monotone_cubic_through_its_rows(tmp_path):
    """Rows at uneven times, a rest between two equal rows and a sharp move: the samples pass through every row, stay
    within each pair of neighbouring rows (no overshoot; the rest stays a rest), and their speed has no jump."""
    rows = [
        (0, 0, 0, 0, 0, 0),
        (0.3, 0.01, 0, 0, 0.02, 0),
        (0.35, 0.012, 0, 0, 0.02, 0),
        (1.0, 0.012, 0, 0, 0.02, 0),
        (1.2, 0.05, -0.01, 0, 0, 0.03),
        (2.0, 0.05, -0.01, 0, 0, 0.03),
    ]
    spec = _table(tmp_path, rows)
    q = paths.platform_path_from(spec, HOME, RATES) - HOME
    assert len(q) == int(round(2.0 / DT)) + 1
    t = np.arange(len(q)) * DT
    table = np.array(rows)
    for row in table:
        np.testing.assert_allclose(q[int(round(row[0] / DT))], row[1:], atol=1e-12)
    for a, b in zip(table[:-1], table[1:]):
        inside = q[(t >= a[0]) & (t <= b[0])]
        assert np.all(inside >= np.minimum(a[1:], b[1:]) - 1e-15) and np.all(inside <= np.maximum(a[1:], b[1:]) + 1e-15)
    assert np.all(q[(t >= 0.35) & (t <= 1.0)] == q[int(round(0.35 / DT))])  # the rest
    speed = np.diff(q, axis=0) / DT
    assert np.abs(np.diff(speed, axis=0)).max() < 0.01  # m/s or rad/s from one period to the next: no jump
    shuffled = _table(
        tmp_path, [(r[3], r[0], r[5], r[1], r[4], r[2]) for r in rows], header="z,t,b,x,a,y", name="shuffled.csv"
    )
    np.testing.assert_array_equal(paths.platform_path_from(shuffled, HOME, RATES) - HOME, q)  # any column order
    assert paths.path_seconds(spec) == 2.0


WAYPOINT_FAULTS = [
    ("speeed: 1\nwaypoints: [{pose: [0, 0, 0, 0, 0]}]\n", "p.yaml: unknown key 'speeed'"),
    ("waypoints: [{pose: [0, 0, 0, 0, 0]}, {pose: [0, 0, 0, 0, 0], sped: 1}]\n", "waypoints[1]: unknown key 'sped'"),
    ("waypoints: [{speed: 0.1}]\n", "waypoints[0]: missing key 'pose'"),
    (
        "waypoints: [{pose: [0.1, 0, 0, 0, 0], speed: -0.1}]\n",
        r"waypoints[0].speed [m/s]: expected a number > 0, "
        "got -0.1",
    ),
    ("waypoints: [{pose: [0.1, 0, 0, 0, 0], dwell: -1}]\n", "waypoints[0].dwell [s]: expected a number >= 0, got -1"),
    (
        "defaults: {acceleration: 0}\nwaypoints: [{pose: [0.1, 0, 0, 0, 0]}]\n",
        "defaults.acceleration [m/s^2]: expected a number > 0, got 0",
    ),
    ("waypoints: [{pose: [0.1, 0, 0]}]\n", "waypoints[0].pose: expected five numbers [x, y, z, a, b]"),
    ("waypoints: [{pose: [0, 0, '0.1', 0, 0]}]\n", "waypoints[0].pose[2] (z): expected a number, got str '0.1'"),
    ("waypoints: [{pose: [0, 0, 0, .nan, 0]}]\n", "waypoints[0].pose[3] (a): expected a finite number"),
    ("waypoints: [{pose: [0, 0, 0, 0, 2.0]}]\n", "waypoints[0].pose[4] (b): expected a number <= 1.5708, got 2"),
    ("waypoints: []\n", "waypoints: expected a non-empty list"),
]


@pytest.mark.parametrize("body,message", WAYPOINT_FAULTS)
def test_a_bad_waypoint_file_is_refused_in_one_line_naming_the_field(tmp_path, body, message):
    spec = _file(tmp_path, "p.yaml", HEAD + body)
    for call in (lambda: paths.platform_path_from(spec, HOME, RATES), lambda: paths.path_seconds(spec)):
        with pytest.raises(ParameterError, match=re.escape(message)) as e:
            call()
        assert "\n" not in str(e.value) and str(e.value).startswith(spec)


@pytest.mark.parametrize(
    "text,message",
    [
        ("version: 1\nwaypoints: [{pose: [0, 0, 0, 0, 0]}]\n", "missing key 'format'"),
        (
            "format: pusupu-batch-1\nversion: 1\nwaypoints: [{pose: [0, 0, 0, 0, 0]}]\n",
            "format: expected 'pusupu-path', got 'pusupu-batch-1'",
        ),
        ("format: pusupu-path\nversion: 2\nwaypoints: [{pose: [0, 0, 0, 0, 0]}]\n", "version: expected 1, got 2"),
        ("format: pusupu-path\nversion: true\nwaypoints: [{pose: [0, 0, 0, 0, 0]}]\n", "version: expected 1, got True"),
        ("format: pusupu-path\nversion: 1\nwaypoints: [{pose: [0, 0, 0, 0, 0]}\n", "not valid YAML"),
    ],
)
def test_a_waypoint_file_of_another_format_or_version_is_refused(tmp_path, text, message):
    with pytest.raises(ParameterError, match=re.escape(message)):
        paths.platform_path_from(_file(tmp_path, "p.yml", text), HOME, RATES)


TABLE_FAULTS = [
    ("", "expected a header t,x,y,z,a,b, got an empty file"),
    (
        "t,x,y,z,a\n0,0,0,0,0\n1,0,0,0,0\n",
        "row 1: expected the header t,x,y,z,a,b (the six columns in any order), got 't,x,y,z,a'",
    ),
    ("t,x,y,z,a,c\n0,0,0,0,0,0\n1,0,0,0,0,0\n", "row 1: expected the header t,x,y,z,a,b"),
    ("t,x,y,z,a,b\n", "expected at least two rows of poses under the header, got 0"),
    ("t,x,y,z,a,b\n0,0,0,0,0,0\n", "expected at least two rows of poses under the header, got 1"),
    ("t,x,y,z,a,b\n0,0,0,0,0,0\n1,0,0,0,0\n", "row 3: expected 6 values (t,x,y,z,a,b), got 5"),
    ("t,x,y,z,a,b\n0,0,0,0,0,0\n1,0,nan,0,0,0\n", "row 3, y [m]: expected a finite number, got nan"),
    ("t,x,y,z,a,b\n0,0,0,0,0,0\n1,0,0,abc,0,0\n", "row 3, z: expected a number, got 'abc'"),
    ("t,x,y,z,a,b\n0,0,0,0,0,0\n1,0,0,0,0,inf\n", "row 3, b [rad]: expected a finite number, got inf"),
    (
        "t,x,y,z,a,b\n0,0,0,0,0,0\n0.2,0,0,0,0,0\n\n0.1,0.01,0,0,0,0\n",
        "row 5, t: expected a time after the row before's 0.2 s (times strictly increasing), got 0.1 s",
    ),
    (
        "t,x,y,z,a,b\n0,0,0,0,0,0\n0.1,0,0,0,0,0\n0.1,0.01,0,0,0,0\n",
        "row 4, t: expected a time after the row before's 0.1 s (times strictly increasing), got 0.1 s",
    ),
    (
        "t,x,y,z,a,b\n0,0.01,0,0,0,0\n1,0,0,0,0,0\n",
        "row 2, x: expected 0 (the path starts at home, where the machine "
        "starts: every offset within 1e-06), got 0.01 m",
    ),
    ("t,x,y,z,a,b\n0,0,0,0,0,2e-6\n1,0,0,0,0,0\n", "row 2, b: expected 0"),
    ("t,x,y,z,a,b\n0,0,0,0,0,0\n1,0,0,0,3.0,0\n", "row 3, a [rad]: expected a number <= 1.5708, got 3"),
]


@pytest.mark.parametrize("text,message", TABLE_FAULTS)
def test_a_bad_pose_table_is_refused_in_one_line_naming_the_row_and_field(tmp_path, text, message):
    spec = _file(tmp_path, "p.csv", text)
    for call in (lambda: paths.platform_path_from(spec, HOME, RATES), lambda: paths.path_seconds(spec)):
        with pytest.raises(ParameterError, match=re.escape(message)) as e:
            call()
        assert "\n" not in str(e.value) and str(e.value).startswith(spec)


@pytest.mark.parametrize("name,what", [("big.csv", "pose table"), ("big.yaml", "path file")])
def test_a_file_over_1_mib_is_refused_before_it_is_read(tmp_path, name, what):
    spec = tmp_path / name
    spec.write_bytes(b"#" * ((1 << 20) + 1))
    with pytest.raises(ParameterError, match=f"expected a {what} of at most 1024 KiB, got a larger file"):
        paths.platform_path_from(str(spec), HOME, RATES)


def test_an_unknown_name_or_kind_of_file_is_refused(tmp_path):
    for spec in ("square", str(tmp_path / "p.txt"), 3):
        with pytest.raises(
            ParameterError,
            match=r"trajectory: expected one of \('arc', 'p2p', 'circle', 'tilt', 'excite'\) or "
            r"a path file \(\.yaml, \.yml, \.csv\)",
        ):
            paths.platform_path_from(spec, HOME, RATES)
    with pytest.raises(ParameterError, match="cannot read path file"):
        paths.platform_path_from(str(tmp_path / "missing.yaml"), HOME, RATES)


def test_a_table_too_long_to_run_is_refused_before_it_is_sampled(tmp_path):
    spec = _table(tmp_path, [(0, 0, 0, 0, 0, 0), (1e7, 0, 0, 0, 0, 0)])
    assert paths.path_seconds(spec) == 1e7
    with pytest.raises(ParameterError, match=r"path\.csv: expected at most 2000 s at these rates"):
        paths.platform_path_from(spec, HOME, RATES)  # 1e10 samples were never allocated


def _first(message):
    k, t = re.search(r"pose (\d+) \(t = ([0-9.e+-]+) s\)", message).groups()
    assert float(t) == pytest.approx(int(k) * DT)
    return int(k)


def test_a_segment_too_fast_for_the_motors_names_its_first_pose_branch_speed_and_limit(tmp_path):
    spec = _file(tmp_path, "fast.yaml", FAST)
    q = paths.platform_path_from(spec, HOME, RATES)
    with pytest.raises(GeometryError) as e:
        paths.check_path(q, SERVO, DT)
    message = str(e.value)
    assert re.fullmatch(
        r"path exceeds the drives: pose \d+ \(t = \S+ s\): branch [1-6] motor speed \S+ rad/s "
        r"\(slider \S+ m/s\), expected at most V_max/Ke = 226\.9 rad/s",
        message,
    ), message
    k, branch = _first(message), int(re.search(r"branch (\d)", message).group(1))
    s = np.asarray(kinematics.inverse_kinematics(G, jnp.asarray(q)))
    motor = np.abs(np.gradient(s, DT, axis=0)) / np.asarray(screw_ratio(SERVO))  # the oracle: central differences
    limit = 300.0 / 1.322  # V_max/Ke: below speed_max, 314.16 rad/s
    assert motor[k, branch - 1] > limit * 0.999 and motor[:k].max() < limit * 1.001  # the first, not the worst
    slow = SERVO.replace(speed_max=np.full(6, 200.0))  # now the rated speed binds, and is named
    with pytest.raises(GeometryError, match=r"expected at most speed_max = 200 rad/s"):
        paths.check_path(q, slow, DT)


def test_a_path_beyond_the_motors_torque_names_its_first_pose_branch_torque_and_limit():
    """Drives that hold 0.264 N m (0.2 A) cannot follow the arc, whose motors peak at 0.276 N m."""
    weak = SERVO.replace(I_max=np.full(6, 0.2))
    q = paths.platform_path_from("arc", HOME, RATES)
    with pytest.raises(GeometryError) as e:
        paths.check_path(q, weak, DT, where="the arc")
    message = str(e.value)
    assert re.fullmatch(
        r"the arc exceeds the drives: pose \d+ \(t = \S+ s\): branch [1-6] motor torque \S+ N m "
        r"\(slider force \S+ N\), expected at most Kt I_max = 0\.2644 N m",
        message,
    ), message
    force, _ = dynamics.inverse_dynamics_forces(weak, q, DT)  # the oracle: the formula of docs/paths.md
    v = np.gradient(np.asarray(kinematics.inverse_kinematics(G, jnp.asarray(q))), DT, axis=0)
    friction = 20.0 * np.tanh(v / 0.001) + 50.0 * v
    torque = np.abs(force + friction) * np.asarray(screw_ratio(weak)) / 0.9
    assert _first(message) == int(np.argmax((torque > 1.322 * 0.2).any(axis=1)))  # the first, not the worst


def test_a_pose_outside_the_workspace_names_the_first_one_out(tmp_path):
    spec = _file(tmp_path, "far.yaml", HEAD + "waypoints: [{pose: [0.6, 0, 0, 0, 0]}]\n")
    q = paths.platform_path_from(spec, HOME, RATES)
    with pytest.raises(
        GeometryError,
        match=r"path leaves the workspace: pose \d+ \(t = \S+ s\) \(x=.*: slider [1-6] "
        r"out of stroke, s = \S+ mm, expected 0\.0 to 500\.0 mm",
    ) as e:
        paths.check_path(q, SERVO, DT)
    k = _first(str(e.value))
    kinematics.check_poses(G, q[:k])  # every pose before it is fine
    poses = np.array([HOME, HOME, HOME + [0, 0, 0.45, 0, 0], HOME + [1.0, 0, 0, 0, 0]])  # out of stroke, unreachable
    with pytest.raises(GeometryError, match=r"^pose 2 \(t = 0\.002 s\) .*slider [1-6] out of stroke"):
        kinematics.check_poses(G, poses, dt=DT)


def test_a_tuning_configuration_takes_path_files_named_from_its_folder(tmp_path):
    from pusupu_jax.tune.config import TuneConfig
    from pusupu_jax.tune.run import check_work, scenario_list

    folder = tmp_path / "conf"
    folder.mkdir()
    (folder / "paths").mkdir()
    table = _table(
        folder / "paths", [(0, 0, 0, 0, 0, 0), (0.5, 0, 0, 0, 0, 0), (2.0, 0.02, 0, 0, 0.02, 0)], name="wiggle.csv"
    )
    config = _file(folder, "tune.yaml", "trajectories: [paths/wiggle.csv, p2p]\npath_s: 1.0\n")
    cfg = TuneConfig.load(config)
    assert cfg.trajectories == (table, "p2p")
    specs = scenario_list(cfg)
    assert [s.name for s in specs] == ["wiggle", "p2p"]
    np.testing.assert_array_equal(specs[0].path(RATES), paths.platform_path_from(table, HOME, RATES)[:1000])
    check_work(cfg)
    before = cfg.digest()
    Path(table).write_text(Path(table).read_text().replace("0.02,0,0,0.02", "0.03,0,0,0.02"))
    assert cfg.digest() != before  # a checkpoint does not resume over an edited path
    for value, message in (
        (["arc", "x/arc.yaml"], "distinct paths, distinctly named"),
        (["arc", "square"], "trajectories[1]: expected one of"),
    ):
        with pytest.raises(ParameterError, match=re.escape(message)):
            cfg.replace(trajectories=value)


def test_a_batch_scenario_takes_a_path_file_and_fails_alone_when_the_drives_cannot_follow_it(tmp_path):
    from pusupu_jax.tune import jobfile

    _table(
        tmp_path,
        [(0, 0, 0, 0, 0, 0), (0.2, 0, 0, 0, 0, 0), (1.0, 0.01, 0, 0, 0, 0.01), (1.5, 0.01, 0, 0, 0, 0.01)],
        name="gentle.csv",
    )
    _file(tmp_path, "fast.yaml", FAST)
    job = _file(
        tmp_path,
        "job.yaml",
        json.dumps(
            {
                "tune": {"iterations": 1, "windows": 2, "window_s": 0.1},
                "scenarios": [{"trajectory": "gentle.csv"}, {"trajectory": "fast.yaml"}],
            }
        ),
    )
    gentle, fast = jobfile.read(job).jobs
    assert gentle.name == "gentle" and gentle.error is None  # named by its stem, read from the job file's folder
    assert gentle.specs[0].trajectory == str(tmp_path / "gentle.csv")
    assert re.match(
        r"scenarios\[1\] \(fast\): the fast path exceeds the drives: pose \d+ \(t = \S+ s\): branch [1-6] "
        r"motor speed",
        fast.error,
    ), fast.error
    before = gentle.digest()
    (tmp_path / "gentle.csv").write_text((tmp_path / "gentle.csv").read_text() + "2.0,0,0,0,0,0.01\n")
    assert jobfile.read(job).jobs[0].digest() != before  # a done report of the old path is not taken for this one


def test_a_path_cut_while_it_moves_is_refused_with_the_cut_named(tmp_path):
    """``path_s`` cuts a path, and the cut path stops there at once: the excitation path cut at 0.3 s, at speed,
    asks branch 5 for more torque than its drive has, though the whole path passes.  The job file's check and the
    tuner's say so; where the whole path fails as well (the fast path, "cut" beyond its end) they add nothing."""
    from pusupu_jax.hybrid import HybridGains
    from pusupu_jax.tune import jobfile
    from pusupu_jax.tune.config import TuneConfig
    from pusupu_jax.tune.run import Problem

    fast = _file(tmp_path, "fast.yaml", FAST)
    tune = {"iterations": 1, "windows": 2, "window_s": 0.1}
    scenarios = [{"trajectory": "excite", "path_s": 0.3}, {"trajectory": fast, "path_s": 100.0}]
    job = _file(tmp_path, "job.yaml", json.dumps({"tune": tune, "scenarios": scenarios}))
    cut, whole = (j.error for j in jobfile.read(job).jobs)
    note = "(the whole path passes: path_s = 0.3 s cuts it while it moves, and the cut path stops there at once;"
    assert "exceeds the drives: pose 299 (t = 0.299 s): branch 5 motor torque" in cut and note in cut, cut
    assert "exceeds the drives" in whole and "whole path passes" not in whole, whole
    with pytest.raises(ParameterError, match=r"^scenario excite: .*exceeds the drives.*" + re.escape(note)):
        Problem(TuneConfig(trajectories=("excite",), path_s=0.3, **tune), ServoParams.table1(), HybridGains())


def test_the_sim_command_refuses_a_path_the_drives_cannot_follow_in_one_line(tmp_path):
    spec = _file(tmp_path, "fast.yaml", FAST)
    r = subprocess.run(
        [sys.executable, "-m", "pusupu_jax.cli", "sim", "--plant", "mjx", "--trajectory", spec],
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert r.returncode == 2 and r.stdout == "", r.stderr
    (line,) = r.stderr.strip().splitlines()
    assert re.match(
        r"pusupu: error: --trajectory \S+fast\.yaml exceeds the drives: pose \d+ \(t = \S+ s\): "
        r"branch [1-6] motor speed",
        line,
    ), line


@pytest.fixture(scope="module")
def pose_table_run(tmp_path_factory):
    """``(spec, log, result)`` of ``pusupu sim`` on a second of a table with tilts, in PID mode, logged to MCAP."""
    tmp_path = tmp_path_factory.mktemp("pose_table")
    spec = _table(
        tmp_path,
        [(0, 0, 0, 0, 0, 0), (0.2, 0, 0, 0, 0, 0), (0.7, 0.005, 0, -0.002, 0.01, 0), (1.0, 0.005, 0, -0.002, 0.01, 0)],
        name="nudge.csv",
    )
    r = subprocess.run(
        [
            sys.executable,
            "-m",
            "pusupu_jax.cli",
            "sim",
            "--plant",
            "mjx",
            "--trajectory",
            spec,
            "--mode",
            "pid",
            "--json",
            "--log",
            tmp_path / "sim.mcap",
        ],
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert r.returncode == 0, r.stderr
    return spec, tmp_path / "sim.mcap", json.loads(r.stdout)


def test_the_sim_command_runs_a_pose_table_on_the_machine(pose_table_run):
    """A second of a table with tilts, end to end in PID mode (the compiled program of every PID run on the machine,
    from the persistent cache when test_cli ran before), logged to MCAP: read back with the mcap package's reader,
    one message per position period on each channel, with its schema, whose error is the run's RMS error."""
    spec, log, out = pose_table_run
    assert out["trajectory"] == spec and out["duration_s"] == pytest.approx(1.0 + DT)
    assert 0 < out["rms_tracking_error_mm"] <= out["max_tracking_error_mm"] < 5
    assert all(0 < v < 13.22 for v in out["motor_torque_peak_nm"])
    from pusupu_jax import run_log

    topics, metadata = run_log.read(log)
    assert set(topics) == {"/sim/platform", "/sim/branch", "/sim/drive"} and metadata["mode"] == "pid"
    drive = [m for _, m in topics["/sim/drive"][1]]
    assert np.abs([m["torque_nm"] for m in drive]).max(axis=0) == pytest.approx(out["motor_torque_peak_nm"], rel=1e-12)
    kt = np.array([m["torque_nm"] for m in drive]) / np.array([m["current_a"] for m in drive])
    assert np.nanmax(np.abs(kt - np.nanmedian(kt, axis=0))) < 1e-9  # torque = Kt x current, the same Kt throughout
    schema, messages = topics["/sim/platform"]
    assert set(schema["required"]) == {"reference_m", "platform_m", "error_mm"}
    assert len(messages) == len(topics["/sim/branch"][1]) == round(out["duration_s"] / DT)
    times = [t for t, _ in messages]
    assert times == sorted(times) and (times[1] - times[0]) == pytest.approx(DT * 1e9, abs=1)
    rms = np.sqrt(np.mean([m["error_mm"] ** 2 for _, m in messages]))
    assert rms == pytest.approx(out["rms_tracking_error_mm"], rel=1e-9)


def test_a_csv_drive_table_of_the_run_reads_as_its_mcap_log(pose_table_run, tmp_path):
    """The pose-table run's drive samples written out in the documented CSV layout (columns shuffled, at 17
    significant digits) read back as the same DriveLog as its MCAP log: every array to the last bit, mode and path
    from the comment lines, the rate from the samples' step (one position period: 1 kHz)."""
    from pusupu_jax import drive_table, run_log

    spec, log, _ = pose_table_run
    mcap = run_log.drive_log(log)
    names = drive_table.columns()
    order = list(reversed(names))
    arrays = {"path_time_s": mcap.path_time[:, None]}
    for group, values in (
        ("reference_rad", mcap.reference),
        ("position_rad", mcap.position),
        ("velocity_rad_s", mcap.velocity),
        ("torque_nm", mcap.torque),
        ("current_a", mcap.current),
    ):
        arrays |= {f"{group}_{k + 1}": values[:, k : k + 1] for k in range(6)}
    table = np.hstack([arrays[c] for c in order])
    csv = tmp_path / "drive.csv"
    csv.write_text(
        f"# mode: pid\n# trajectory: {spec}\n"
        + ",".join(order)
        + "\n"
        + "\n".join(",".join(f"{v:.17g}" for v in row) for row in table)
        + "\n"
    )
    got = drive_table.read(csv)
    assert (got.mode, got.trajectory, got.gain_checksum) == ("pid", str(spec), None)
    assert got.rate_hz == pytest.approx(1.0 / DT)
    for name in ("path_time", "reference", "position", "velocity", "torque", "current"):
        np.testing.assert_array_equal(getattr(got, name), getattr(mcap, name), err_msg=name)
