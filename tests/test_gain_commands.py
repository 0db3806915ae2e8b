"""Every command that reads, runs or exports gains refuses an unstable gain file the same way (one line, exit 2, nothing
written), and version 2 files are read and migrated only on the built-in plant.

The unstable files are forged as a foreign tool would: the values edited, the discrete blocks recomputed and the file
re-signed, so that only the stability check stands between them and a robot.
"""

import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import yaml

from pusupu_jax import LoopRates, ParameterError, gains
from pusupu_jax.hybrid import HybridGains
from pusupu_jax.params import ServoParams

DATA = Path(__file__).parent / "data"
V2_TABLE1 = DATA / "gains_v2_table1.yaml"  # written by the version 2 writer: Table 1, hybrid, the built-in plant
V2_OTHER_PLANT = DATA / "gains_v2_other_plant.yaml"  # the same with Kt and Ke 10 % higher


def pusupu(*args, timeout=600):
    return subprocess.run(
        [sys.executable, "-m", "pusupu_jax.cli", *map(str, args)], capture_output=True, text=True, timeout=timeout
    )


def forge(path: Path, section: str, name: str, value: float) -> Path:
    """``path``'s ``controller.section.name`` set to ``value``, its discrete blocks and checksum made to match."""
    text = path.read_text()
    doc = yaml.safe_load(text)
    doc.pop("checksum")
    doc["controller"][section][name]["value"] = value
    servo = gains.parse(text).servo.replace(**{name: np.full(6, value)})
    doc["discrete"] = gains._discrete(servo, gains.parse(text).rates)
    body = yaml.safe_dump(doc, sort_keys=False, default_flow_style=None, width=110)
    path.write_text(body + yaml.safe_dump({"checksum": gains._checksum(body)}))
    return path


@pytest.fixture(scope="module")
def unstable(tmp_path_factory):
    """A version 3 gain file with Kv = 2 A/(rad/s): in bounds, its velocity loop unstable (a pole of modulus 1.058
    per velocity period at the file's rates)."""
    folder = tmp_path_factory.mktemp("unstable")
    good = gains.write(folder / "good.yaml", ServoParams.table1(), HybridGains(), LoopRates(n_mech=5), mode="hybrid")
    return forge(Path(shutil.copy(good, folder / "unstable.yaml")), "velocity", "Kv", 2.0)


REFUSAL = "the velocity loop of axis 1 is unstable"


def _refused(r):
    lines = r.stderr.strip().splitlines()
    assert r.returncode == 2 and len(lines) == 1 and REFUSAL in lines[0] and "Traceback" not in r.stderr, r.stderr
    return r


def test_check_and_sign_refuse_it_and_leave_the_file(unstable):
    before = unstable.read_bytes()
    _refused(pusupu("gains", "check", unstable))
    _refused(pusupu("gains", "sign", unstable))
    assert unstable.read_bytes() == before


# the other commands in this process (cli.main: the same exit status and line, without starting Python again)


def test_export_ros_writes_nothing(unstable, tmp_path, refused):
    assert REFUSAL in refused("gains", "export-ros", unstable, "--out", tmp_path)
    assert list(tmp_path.iterdir()) == []


def test_export_ros_warns_where_ros_pid_keeps_less_than_the_floors(tmp_path, in_process, capsys):
    """A PID file whose own position loop keeps its margins, with a large derivative gain behind a slow filter
    (``Kd_pid`` 10, ``Tf_pid`` 1 s): ROS's PID takes the derivative on the velocity error without that filter, and its
    position loop keeps some 13 deg and 7.6 dB (``gains check-ros``).  The files are written, as the design of the
    export is (``docs/gains.md``), with one warning line naming that loop."""
    from pusupu_jax import ros2

    servo = ServoParams.table1().replace(Kd_pid=np.full(6, 10.0), Tf_pid=np.full(6, 1.0))
    path = gains.write(tmp_path / "pid.yaml", servo, HybridGains(), LoopRates(n_mech=5), mode="pid")
    out = tmp_path / "ros"
    out.mkdir()
    capsys.readouterr()
    in_process("gains", "export-ros", path, "--out", out)
    err = capsys.readouterr().err.strip().splitlines()
    assert sorted(p.name for p in out.iterdir()) == sorted(ros2.FILES)
    assert len(err) == 1 and err[0].startswith("pusupu: warning: ROS's PID with these gains keeps less than 45 deg")
    assert "its position loop" in err[0], err


def test_sim_refuses_before_simulating(unstable, refused):
    assert REFUSAL in refused("sim", "--gains", unstable, "--json")
    assert refused.stdout == ""


def test_analyze_prints_its_diagnosis_then_refuses(unstable, refused):
    """The analysis of a refused file is what its user needs to see: it is printed, then the exit is 2."""
    assert REFUSAL in refused("analyze", "--gains", unstable)
    assert "velocity" in refused.stdout and "PM deg" in refused.stdout


def test_the_bridge_refuses_before_any_socket(unstable, refused):
    assert REFUSAL in refused("bridge", "--gains", unstable, "--robot", "udp://127.0.0.1:9", "--duration", "1")
    assert "cycle" not in refused.stdout


def test_a_version_2_file_on_the_built_in_plant_is_read_and_migrated(tmp_path, in_process):
    g2 = gains.load(V2_TABLE1)
    assert g2.document["version"] == 2 and g2.mode == "hybrid"
    path = Path(shutil.copy(V2_TABLE1, tmp_path / "gains.yaml"))
    with pytest.raises(ParameterError, match="pusupu gains migrate converts a version 2 file"):
        gains.sign(path)
    in_process("gains", "migrate", path)
    g3 = gains.load(path)
    assert g3.document["version"] == 4 and "plant" not in g3.document
    assert g3.machine["name"] == "built-in"
    assert g3.document["provenance"]["migrated_from_version"] == 2
    for name in ("lambda1", "lambda2", "Kv", "Ki", "Kp_pid", "Kt", "lead"):
        assert np.array_equal(np.asarray(getattr(g3.servo, name)), np.asarray(getattr(g2.servo, name))), name
    assert g3.hybrid == g2.hybrid and g3.rates == g2.rates
    assert float(g3.servo.following_error[0]) == 0.005  # a limit version 2 lacked: the default


def test_a_version_2_file_on_another_plant_is_refused(tmp_path):
    path = Path(shutil.copy(V2_OTHER_PLANT, tmp_path / "gains.yaml"))
    before = path.read_bytes()
    r = pusupu("gains", "migrate", path, "--out", tmp_path / "v4.yaml")
    assert r.returncode == 2 and "plant.Kt: expected the built-in plant's 1.322" in r.stderr, r.stderr
    assert "read only on the built-in plant" in r.stderr and "\n" not in r.stderr.strip()
    assert path.read_bytes() == before and not (tmp_path / "v4.yaml").exists()
