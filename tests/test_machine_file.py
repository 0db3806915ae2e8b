"""The machine file: the built-in template reads back as the built-in machine, bad files are refused in one line with
exit 2 and nothing written, and a gain file names the machine it was tuned on (the bridge refuses another machine's)."""

import dataclasses
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import yaml

from pusupu_jax import ParameterError, gains, machine_file
from pusupu_jax.hybrid import HybridGains
from pusupu_jax.machine_file import Machine
from pusupu_jax.params import LoopRates, ServoParams
from pusupu_jax.start_gains import derive

EXAMPLE = Path(__file__).parent.parent / "docs" / "examples" / "machine_user.yaml"


def pusupu(*args, timeout=600):
    return subprocess.run(
        [sys.executable, "-m", "pusupu_jax.cli", *map(str, args)], capture_output=True, text=True, timeout=timeout
    )


def test_the_template_is_the_built_in_machine_and_the_digest_ignores_layout():
    text = machine_file.template()
    machine = machine_file.parse(yaml.safe_load(text))
    assert machine_file.digest(machine) == machine_file.digest(Machine.default())
    doc = yaml.safe_load(text)
    doc["drives"]["R"] = [1.3] * 6  # six equal values instead of one: the same machine
    assert machine_file.digest(machine_file.parse(doc)) == machine_file.digest(Machine.default())
    doc["drives"]["R"] = 1.3 * (1 + 1e-9)
    assert machine_file.digest(machine_file.parse(doc)) != machine_file.digest(Machine.default())


def test_the_identification_examples_are_the_built_in_machine_as_built_and_as_designed():
    """docs/examples/machine_as_built.yaml, the robot of the README's identification walk-through and the truth of
    benchmarks/bench_identify.py: the built-in geometry and every drive field the same but the fitted ones (per axis
    friction, rotor inertia, torque constant with the back-EMF constant equal to it), each away from its built-in
    value on at least four axes, and a 5 kg payload off centre.  machine_as_designed.yaml, where both start: the
    built-in machine with a guessed payload, 3 kg at the centre, of the same inertia."""
    built_in = Machine.default()
    as_built = machine_file.load(EXAMPLE.parent / "machine_as_built.yaml")
    same_rest = dataclasses.replace(as_built, name=built_in.name, drives=built_in.drives, payload=built_in.payload)
    assert machine_file.digest(same_rest) == machine_file.digest(built_in)  # geometry and all else the built-in's
    fitted = {"coulomb", "viscous", "J", "Kt", "Ke"}
    for name, value in built_in.drives.items():
        theirs = np.broadcast_to(as_built.drives[name], (6,))
        if name in fitted:
            assert np.sum(~np.isclose(theirs, np.broadcast_to(value, (6,)))) >= 4, name
        else:
            np.testing.assert_array_equal(theirs, np.broadcast_to(value, (6,)), err_msg=name)
    np.testing.assert_array_equal(as_built.drives["Ke"], as_built.drives["Kt"])
    assert as_built.payload.mass == 5.0 and np.linalg.norm(as_built.payload.com) > 0.05
    designed = machine_file.load(EXAMPLE.parent / "machine_as_designed.yaml")  # the walk-through's start
    guess = dataclasses.replace(designed, name=built_in.name, payload=built_in.payload)
    assert machine_file.digest(guess) == machine_file.digest(built_in)
    assert designed.payload.mass == 3.0 and designed.payload.com == (0.0, 0.0, 0.0)
    assert designed.payload.inertia == as_built.payload.inertia  # from CAD: identify does not fit it


def test_sensors_are_optional_and_a_file_without_them_keeps_its_digest():
    """``drives.encoder_counts`` and ``drives.current_noise`` left out are ideal sensors, and the machine's digest
    (which gain files record) is that of a file written before the keys existed; given, each is one value or six,
    and enters the digest."""
    doc = yaml.safe_load(machine_file.template())
    assert "encoder_counts" not in doc["drives"] and machine_file.parse(doc).encoder_counts is None
    assert "current_noise" not in doc["drives"] and machine_file.parse(doc).current_noise is None
    assert machine_file.digest(Machine.default()) == BUILT_IN_DIGEST
    doc["drives"]["encoder_counts"] = 2**20
    twenty_bit = machine_file.parse(doc)
    assert twenty_bit.encoder_counts.tolist() == [2**20] * 6
    assert machine_file.digest(twenty_bit) != BUILT_IN_DIGEST
    doc["drives"]["encoder_counts"] = [2**20] * 6
    assert machine_file.digest(machine_file.parse(doc)) == machine_file.digest(twenty_bit)
    quanta = machine_file.encoder_quanta(twenty_bit, 2.5e-4)
    assert quanta["slider_count_m"][0] == pytest.approx(0.01 / 2**20)  # the 10 mm lead over 2^20 counts
    assert quanta["speed_step_rad_s"][0] == pytest.approx(2 * np.pi / 2**20 / 2.5e-4)
    doc["drives"]["current_noise"] = [0.1, 0.1, 0.1, 0.1, 0.1, 0.2]
    noisy = machine_file.parse(doc)
    assert noisy.current_noise.tolist() == [0.1] * 5 + [0.2] and noisy.current_noise.dtype == float
    assert machine_file.digest(noisy) != machine_file.digest(twenty_bit)
    assert machine_file.parse(yaml.safe_load(machine_file.template(noisy))).current_noise.tolist() == [0.1] * 5 + [0.2]


# the built-in machine's digest as gain files tuned on it record it: it changes only with the machine
BUILT_IN_DIGEST = "203637fd0b107eff7383196032cbe91085c6bd85070b754fbbe25f4b6b0fa4de"


def test_the_uncertainty_section_is_optional_reads_back_and_enters_the_digest():
    """What ``pusupu identify`` writes: the standard errors of the fitted values.  A per-axis one is one number for all
    six axes or six; the payload's mass one number, its centre of mass three.  The template writes the section back
    as read (a file without it keeps its digest)."""
    doc = yaml.safe_load(machine_file.template())
    assert "uncertainty" not in doc and machine_file.parse(doc).uncertainty is None
    doc["uncertainty"] = {"coulomb": 0.5, "Kt": [0.01, 0.02, 0.01, 0.01, 0.01, 0.01], "payload_com": [0.001, 0, 0.002]}
    doc["uncertainty"]["payload_mass"] = 0.05
    m = machine_file.parse(doc)
    np.testing.assert_array_equal(m.uncertainty["coulomb"], np.full(6, 0.5))
    assert m.uncertainty["payload_mass"].shape == () and m.uncertainty["payload_com"].shape == (3,)
    assert machine_file.digest(m) != BUILT_IN_DIGEST
    again = machine_file.parse(yaml.safe_load(machine_file.template(m)))
    assert machine_file.digest(again) == machine_file.digest(m)
    for k, v in m.uncertainty.items():
        np.testing.assert_array_equal(again.uncertainty[k], v)


def test_a_correlation_reads_back_enters_the_digest_and_needs_standard_errors():
    """The ``uncertainty`` section's ``correlation``: labels of values the section gives a standard error, and their
    matrix; the template writes it back as read, and only a file with it has another digest."""
    doc = yaml.safe_load(machine_file.template())
    doc["uncertainty"] = {"coulomb": 0.5, "payload_mass": 0.05}
    without = machine_file.digest(machine_file.parse(doc))
    doc["uncertainty"]["correlation"] = {"values": ["coulomb[2]", "payload_mass"], "matrix": [[1, -0.7], [-0.7, 1]]}
    m = machine_file.parse(doc)
    assert m.correlation is not None and m.correlation.values == ("coulomb[2]", "payload_mass")
    assert machine_file.digest(m) != without
    again = machine_file.parse(yaml.safe_load(machine_file.template(m)))
    assert machine_file.digest(again) == machine_file.digest(m) and again.correlation.values == m.correlation.values
    np.testing.assert_array_equal(again.correlation.matrix, [[1, -0.7], [-0.7, 1]])


def _correlated(values, matrix):
    return lambda d: d.update(
        uncertainty={"coulomb": [0.5, 0.5, 0, 0.5, 0.5, 0.5], "correlation": {"values": values, "matrix": matrix}}
    )


def test_the_schema_file_is_generated_from_the_fields():
    shipped = Path(machine_file.__file__).parent / "schemas" / "pusupu-machine.schema.json"
    assert shipped.read_text() == machine_file.schema_text()
    schema = json.loads(shipped.read_text())
    assert set(schema["properties"]["drives"]["required"]) == {f.name for f in machine_file.drive_fields()}


def _edited(tmp_path, edit) -> Path:
    doc = yaml.safe_load(machine_file.template())
    edit(doc)
    path = tmp_path / "machine.yaml"
    path.write_text(yaml.safe_dump(doc))
    return path


BAD = {
    "an unreachable home": (lambda d: d["geometry"].update(home=[0.0, 0.0, 1.6, 0.0, 0.0]), "geometry.home"),
    "a rod too short for the rails": (lambda d: d["geometry"].update(rod_lengths=[0.05] * 6), "unreachable"),
    "a negative mass": (lambda d: d["geometry"].update(platform_mass=-1.0), "geometry.platform_mass"),
    "a zero lead": (lambda d: d["drives"].update(lead=0.0), "drives.lead"),
    "NaN": (lambda d: d["drives"].update(R=float("nan")), "drives.R"),
    "an unknown key": (lambda d: d["drives"].update(Rs=1.0), "unknown field 'Rs'"),
    "a missing section": (lambda d: d.pop("payload"), "missing key 'payload'"),
    "a payload no body can have": (lambda d: d["payload"].update(mass=1.0, inertia=[1.0, 0.1, 0.1]), "payload.inertia"),
    "a drive list of five": (lambda d: d["drives"].update(Kt=[1.0] * 5), "drives.Kt"),
    "an encoder of 100 counts": (lambda d: d["drives"].update(encoder_counts=100), "drives.encoder_counts: expected"),
    "fractional encoder counts": (lambda d: d["drives"].update(encoder_counts=4096.5), "drives.encoder_counts"),
    "an encoder list of five": (lambda d: d["drives"].update(encoder_counts=[4096] * 5), "drives.encoder_counts"),
    "a negative current noise": (lambda d: d["drives"].update(current_noise=-0.1), "drives.current_noise: expected"),
    "a current noise of NaN": (lambda d: d["drives"].update(current_noise=[0.1] * 5 + [float("nan")]), "current_noise"),
    "a negative standard error": (lambda d: d.update(uncertainty={"coulomb": -1.0}), "uncertainty.coulomb: expected"),
    "an uncertainty of a field not fitted": (lambda d: d.update(uncertainty={"R": 0.1}), "unknown field 'R'"),
    "a centre of mass's error of two": (lambda d: d.update(uncertainty={"payload_com": [0.1, 0.1]}), "payload_com"),
    "a correlation of a value without a standard error": (
        _correlated(["coulomb[1]", "Kt[1]"], [[1, 0], [0, 1]]),
        "uncertainty.correlation.values: expected labels of values this section gives a standard error",
    ),
    "a correlation of a value whose standard error is 0": (
        _correlated(["coulomb[1]", "coulomb[3]"], [[1, 0], [0, 1]]),
        "expected values with a standard error above 0, got 'coulomb",
    ),
    "a correlation naming a value twice": (
        _correlated(["coulomb[1]", "coulomb[1]"], [[1, 0.5], [0.5, 1]]),
        "uncertainty.correlation.values: expected each value once",
    ),
    "a correlation matrix of the wrong shape": (
        _correlated(["coulomb[1]", "coulomb[2]"], [[1, 0.5, 0], [0.5, 1, 0]]),
        "uncertainty.correlation.matrix",
    ),
    "an asymmetric correlation": (
        _correlated(["coulomb[1]", "coulomb[2]"], [[1, 0.5], [0.4, 1]]),
        "asymmetry 0.1",
    ),
    "correlations no three values can have": (
        _correlated(["coulomb[1]", "coulomb[2]", "coulomb[4]"], [[1, 0.9, -0.9], [0.9, 1, 0.9], [-0.9, 0.9, 1]]),
        "smallest eigenvalue -0.8",
    ),
    "a correlation of one value": (
        _correlated(["coulomb[1]"], [[1]]),
        "uncertainty.correlation.values: expected a list of two or more value labels",
    ),
    "a correlation without its matrix": (
        lambda d: d.update(uncertainty={"coulomb": 0.5, "correlation": {"values": ["coulomb[1]", "coulomb[2]"]}}),
        "missing key 'matrix'",
    ),
}


@pytest.mark.parametrize("case", BAD)
def test_a_bad_machine_file_is_refused_in_one_line(tmp_path, case):
    edit, expected = BAD[case]
    with pytest.raises(ParameterError, match=expected.replace("(", r"\(").replace(")", r"\)")) as e:
        machine_file.load(_edited(tmp_path, edit))
    assert "\n" not in str(e.value)


def test_a_file_over_1_mib_is_refused(tmp_path):
    path = tmp_path / "big.yaml"
    path.write_text(machine_file.template() + "#" * (1 << 20))
    with pytest.raises(ParameterError, match="at most 1024 KiB"):
        machine_file.load(path)


@pytest.mark.slow
def test_machine_commands_init_check_and_refusal(tmp_path, in_process, refused):
    """In this process (``cli.main``), but for the refusal of a bad file, which a process of its own shows as one
    line and exit status 2."""
    out = tmp_path / "m.yaml"
    in_process("machine", "init", "--out", out)
    assert machine_file.digest(machine_file.load(out)) == machine_file.digest(Machine.default())
    assert "expected a new file, found one there" in refused("machine", "init", "--out", out)  # never replaced
    assert "expected a new file, found a folder" in refused("machine", "init", "--out", tmp_path)
    # a folder that cannot be: the file's name, not that of the temporary the write would have made
    assert refused("machine", "init", "--out", out / "m.yaml").endswith(f"{out}' is not a folder")
    found = json.loads(in_process("machine", "check", EXAMPLE, "--json"))
    assert found["name"] == "user-1FT7044-lead5" and set(found["workspace"]) == {"home", "arc", "p2p"}
    # twice the carriage mass and 5 kg more on the platform than the built-in machine carries
    builtin = json.loads(in_process("machine", "check", out, "--json"))["carried_mass_kg"]
    assert min(np.subtract(found["carried_mass_kg"], builtin)) > 3.0
    bad = _edited(tmp_path, lambda d: d["drives"].update(lead=0.0))
    r = pusupu("machine", "check", bad)
    assert r.returncode == 2 and r.stderr.count("\n") == 1 and "drives.lead" in r.stderr


def test_a_gain_file_names_its_machine_and_is_checked_on_the_one_given(tmp_path):
    user = machine_file.load(EXAMPLE)
    servo, _ = derive(user, identify=False)
    text = gains.document(servo, HybridGains(), LoopRates(n_mech=5), mode="imc", machine=user)
    g = gains.parse(text, machine=user)
    assert g.machine == machine_file.reference(user) and g.tuned_on(user) and not g.tuned_on(Machine.default())
    assert np.allclose(g.servo.lead, 0.005) and np.allclose(g.servo.coulomb, 95.0)
    # on the built-in machine the same file is checked on its drive: a 31 A clamp on a 10 A drive is refused
    with pytest.raises(ParameterError, match="I_max: expected 0 to I_peak = 10"):
        gains.parse(text)
    with pytest.raises(ParameterError, match="the drive of machine 'user-1FT7044-lead5'"):
        gains.document(ServoParams.table1(), HybridGains(), LoopRates(n_mech=5), mode="imc", machine=user)


@pytest.mark.slow
def test_the_bridge_refuses_gains_tuned_on_another_machine(tmp_path):
    """The built-in machine renamed: the same drives, so only the digest tells the machines apart."""
    other = Machine("twin", Machine.default().geometry, Machine.default().drives)
    path = tmp_path / "gains.yaml"
    path.write_text(
        gains.document(other.servo(ServoParams.table1()), HybridGains(), LoopRates(n_mech=5), mode="imc", machine=other)
    )
    r = pusupu("bridge", "--gains", path, "--robot", "udp://127.0.0.1:5612", "--duration", "1", "--no-realtime")
    assert r.returncode == 2 and "tuned on machine 'twin'" in r.stderr and "--allow-other-machine" in r.stderr
    assert r.stderr.count("\n") == 1
