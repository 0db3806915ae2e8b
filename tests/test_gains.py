"""Gain files: written for people, read back exactly, every bad input refused with one line, hand edits re-signed."""

import json
import os
import stat

import jsonschema
import numpy as np
import pytest
import yaml

from pusupu_jax import LoopRates, ParameterError, ServoParams, gain_schema, gain_view, gains
from pusupu_jax.hybrid import HybridGains

RATES = LoopRates(n_mech=5)
GOOD = ServoParams.table1().replace(lambda1=np.linspace(0.02, 0.05, 6), lambda2=np.full(6, 0.1))
HYBRID = HybridGains(m6=0.2, c6=1234.5, g=67.8, form="rms")
TUNED = ("lambda1", "lambda2", "c6")


def _write(path, servo=GOOD, hybrid=HYBRID, **kw):
    return gains.write(
        path,
        servo,
        hybrid,
        RATES,
        mode="hybrid",
        tuned=TUNED,
        provenance={"config_hash": "test", "objective_before": 1.0, "objective_after": 0.5},
        **kw,
    )


def test_a_gain_file_reads_back_exactly(tmp_path):
    path = _write(tmp_path / "gains.yaml")
    g = gains.load(path)
    for name, value in vars(GOOD).items():  # the static imc_form included
        assert np.array_equal(np.asarray(getattr(g.servo, name)), np.asarray(value)), name
    assert g.hybrid == HYBRID and g.rates == RATES and g.mode == "hybrid"
    doc = g.document
    position = doc["controller"]["position"]
    assert position["imc_form"] == "full"
    assert position["lambda1"]["value"] == GOOD.lambda1.tolist() and position["lambda1"]["tuned"] is True
    assert position["lambda2"] == {"value": 0.1, "unit": "s", "tuned": True}  # shared by the six axes: written once
    assert "tuned" not in position["T0"] and "plant" not in doc  # the plant is the built-in one, not the file's
    assert doc["controller"]["limits"]["following_error"] == {"value": 0.005, "unit": "m"}
    assert set(doc["stability"]) == {"current", "velocity", "position"}
    assert all(0 < np.max(v["spectral_radius"]) < 1 for v in doc["stability"].values())
    assert doc["controller"]["hybrid"]["c6"]["tuned"] is True and doc["controller"]["hybrid"]["form"] == "rms"
    block = doc["discrete"]["velocity_pi"]
    assert block["sample_period_s"] == RATES.dt_velocity and "current reference" in block["output"]
    assert "I_max" in block["clamp"]
    p = doc["provenance"]
    assert p["package"] == "pusupu_jax" and p["jax_version"] and p["mujoco_version"] and "git_commit" in p
    assert p["tuned_fields"] == sorted(TUNED) and p["config_hash"] == "test"


def test_the_shipped_json_schema_is_current_and_describes_written_files(tmp_path):
    assert gain_schema.SCHEMA_FILE.read_text() == gain_schema.schema_text()
    path = _write(tmp_path / "gains.yaml")
    jsonschema.validate(yaml.safe_load(path.read_text()), json.loads(gain_schema.SCHEMA_FILE.read_text()))


def _rewrite(path, change):
    """Apply ``change`` to the document and sign it again (as a foreign tool, or an attacker, would)."""
    doc = yaml.safe_load(path.read_text())
    doc.pop("checksum")
    change(doc)
    body = yaml.safe_dump(doc, sort_keys=False)
    path.write_text(body + yaml.safe_dump({"checksum": gains._checksum(body)}))


def _set(section, name, value):
    def change(d):
        d["controller"][section][name]["value"] = value

    return change


BAD = {
    "missing key": (lambda d: d.pop("margins"), "missing key 'margins'"),
    "unknown key": (lambda d: d.update(extra=1), "unknown key 'extra'"),
    "wrong unit": (
        lambda d: d["controller"]["position"]["lambda1"].update(unit="ms"),
        "controller.position.lambda1.unit: expected 's', got 'ms'",
    ),
    "unit an int": (lambda d: d["controller"]["position"]["lambda1"].update(unit=1), "unit: expected 's', got 1"),
    "unit a list": (lambda d: d["controller"]["position"]["lambda1"].update(unit=["s"]), "unit: expected 's'"),
    "wrong length": (_set("velocity", "Kv", [0.015] * 5), r"ServoParams.Kv: expected a number or a list of 6"),
    "a quoted number": (_set("velocity", "Kv", "0.015"), "ServoParams.Kv: expected a number, got str"),
    "a boolean": (_set("velocity", "Kv", True), "ServoParams.Kv: expected a number, got bool"),
    "NaN": (
        _set("current", "Ti", [0.00208] * 2 + [float("nan")] + [0.00208] * 3),
        r"ServoParams.Ti\[2\]: expected a number, got nan",
    ),
    "negative time constant": (_set("velocity", "Tv", -5.0), "ServoParams.Tv: expected a positive"),
    "unstable gains": (_set("velocity", "Kv", [0.015] * 5 + [2.0]), "velocity loop of axis 6 is unstable"),
    "too little margin": (_set("position", "lambda2", 0.02), "position loop of axis 1 has .* expected at least 45"),
    "emf_ff beyond the whole back-EMF": (_set("current", "emf_ff", 3.0), r"ServoParams.emf_ff: expected 0 to 1 "),
    "a current limit above the drive's rating": (
        _set("limits", "I_max", 1e6),
        r"ServoParams.I_max: expected 0 to "
        r"I_peak = 10 \[A\]",
    ),
    "a voltage limit above the DC bus": (_set("limits", "V_max", 1e6), r"ServoParams.V_max: expected 0 to V_dc"),
    "a hybrid gain beyond what the machine kept stable": (
        lambda d: d["controller"]["hybrid"]["g"].update(value=1e12),
        r"HybridGains.g: expected a number from 0 to 300000",
    ),
    "loop rates too slow": (
        lambda d: d["rates"].update(n_velocity=100, n_mech=100),
        r"rates: f_current / n_velocity is 200 Hz|position\) is 50 Hz; expected 100",
    ),
    "a plant section (version 2's) in a version 4 file": (lambda d: d.update(plant={}), "unknown key 'plant'"),
    "schema version": (lambda d: d.update(version=5), "version: expected 4"),
    "a version 3 file with a machine key": (lambda d: d.update(version=3), "unknown key 'machine'"),
    "no machine": (lambda d: d.pop("machine"), "missing key 'machine'"),
    "a machine digest that is no sha256": (lambda d: d["machine"].update(digest="abc"), "machine.digest"),
    "version 1 (printed-form era)": (lambda d: d.update(version=1), "version 1 files predate the choice of IMC"),
    "unknown IMC form": (
        lambda d: d["controller"]["position"].update(imc_form="exact"),
        "ServoParams.imc_form: expected one of",
    ),
    "unknown mode": (lambda d: d.update(mode="fuzzy"), "mode: expected one of"),
    "hybrid gain a list": (
        lambda d: d["controller"]["hybrid"]["m6"].update(value=[1, 2, 3]),
        "HybridGains.m6: expected a number, got list",
    ),
    "stale discrete": (lambda d: d["discrete"]["pid"]["D"][0].__setitem__(0, 1.0), "discrete.pid: not the"),
    "rates not a mapping": (lambda d: d.update(rates=5), "rates: expected a mapping"),
    "tuned not a boolean": (
        lambda d: d["controller"]["position"]["lambda1"].update(tuned="yes"),
        "lambda1.tuned: expected true or false",
    ),
}


@pytest.mark.parametrize("case", sorted(BAD))
def test_bad_gain_files_are_refused_with_one_line(tmp_path, case):
    path = _write(tmp_path / "gains.yaml")
    change, message = BAD[case]
    _rewrite(path, change)
    with pytest.raises(ParameterError, match=message) as e:
        gains.load(path)
    assert "\n" not in str(e.value)


def test_stability_is_checked_against_fixed_floors_never_the_files_own(tmp_path):
    """lambda2 = 0.02 s (a position loop under 45 deg), thresholds of -1000 written into the file's provenance and
    margins, checksum recomputed: refused.  An explicit, lower floor is the caller's choice; an unstable loop is
    refused whatever the floors (Kv = 3: a velocity-loop pole outside the unit circle)."""
    path = _write(tmp_path / "gains.yaml")

    def attack(d):
        d["controller"]["position"]["lambda2"]["value"] = 0.02
        d["provenance"].update(pm_min=-1000, gm_min=-1000, floors=[-1000, -1000])
        d["margins"]["position"] = {"phase_margin_deg": 90.0, "gain_margin_db": 60.0}

    _rewrite(path, attack)
    with pytest.raises(ParameterError, match="position loop of axis 1 has .* expected at least 45 deg and 6 dB"):
        gains.load(path)
    with pytest.raises(ParameterError, match="discrete.imc_c1: not the discretisation"):
        gains.load(path, floors=(15.0, 3.0))  # the caller's lower floors pass; the edit's stale blocks are caught next
    _rewrite(path, _set("velocity", "Kv", 3.0))
    with pytest.raises(ParameterError, match="velocity loop of axis 1 is unstable"):
        gains.load(path, floors=(-1000.0, -1000.0))


def test_edited_and_truncated_files_are_caught_and_a_deliberate_edit_is_re_signed(tmp_path):
    path = _write(tmp_path / "gains.yaml")
    text = path.read_text()
    path.write_text(text.replace("value: 1234.5", "value: 1234.6"))
    with pytest.raises(ParameterError, match="checksum: does not match"):
        gains.load(path)
    gains.sign(path)  # a deliberate, valid edit: re-signed
    g = gains.load(path)
    assert float(g.hybrid.c6) == 1234.6 and g.document["provenance"]["signed_utc"]
    assert g.document["provenance"]["tuned_fields"] == sorted(TUNED)
    signed = path.read_text()
    path.write_text(signed.replace("Kv: {value: 0.015", "Kv: {value: 3.0"))
    with pytest.raises(ParameterError, match="velocity loop of axis 1 is unstable"):
        gains.sign(path)  # an unstable edit is not signed ...
    assert "Kv: {value: 3.0" in path.read_text()  # ... nor the file rewritten
    for cut in (len(text) // 2, text.rfind("checksum:"), len(text) - 10):
        path.write_text(text[:cut])
        with pytest.raises(ParameterError, match="(truncated|checksum|not valid YAML|missing key)"):
            gains.load(path)


def test_unstable_gains_are_never_written_and_the_old_file_survives(tmp_path):
    path = _write(tmp_path / "gains.yaml")
    before = path.read_bytes()
    with pytest.raises(ParameterError, match="velocity loop of axis 1 is unstable"):
        _write(path, servo=GOOD.replace(Kv=np.full(6, 2.0)))
    with pytest.raises(ParameterError, match="servo.Kt: expected the drive of machine 'built-in', 1.322"):
        _write(path, servo=GOOD.replace(Kt=GOOD.Kt / 100))  # gains tuned on another plant
    with pytest.raises(ParameterError, match="ServoParams.lambda2: expected finite"):
        _write(path, servo=GOOD.replace(lambda2=np.full(6, np.nan)))
    assert path.read_bytes() == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["gains.yaml"]  # no temporary left behind


@pytest.mark.parametrize("mask, mode", [(0o022, 0o644), (0o077, 0o600), (0o002, 0o664)])
def test_files_get_the_mode_the_umask_gives(tmp_path, mask, mode):
    """Every file used to be 0600 whatever the umask; an existing 0644 file stayed 0600 after a rewrite."""
    old = os.umask(mask)
    try:
        path = _write(tmp_path / "gains.yaml")
        assert stat.S_IMODE(path.stat().st_mode) == mode
        _write(path)  # rewritten over itself
        assert stat.S_IMODE(path.stat().st_mode) == mode
    finally:
        os.umask(old)


def test_show_and_diff_read_for_people(tmp_path):
    a = gains.load(_write(tmp_path / "a.yaml")).document
    b = gains.load(_write(tmp_path / "b.yaml", hybrid=HYBRID.replace(c6=999.0))).document
    text = gain_view.show(a)
    assert "lambda1" in text and "0.02 0.026 0.032 0.038 0.044 0.05" in text and "yes" in text
    assert "margins   position" in text
    assert gain_view.diff(a, b) == ["hybrid.c6: 1234.5 -> 999.0 N/m"]
    assert gain_view.diff(a, a) == []


BAD_BYTES = {
    "random bytes": bytes(range(256)) * 4,
    "an alias bomb": b"a: &a [x, x]\nb: &b [*a, *a]\nc: &c [*b, *b]\nd: [*c, *c]\n",
    "duplicate keys": b"schema: pusupu-gains\nschema: pusupu-gains\n",
    "mixed key types": b"{1: 2, foo: 3}\n",
    "too large": b"# " + b"x" * (1 << 20) + b"\n",
    "not a mapping": b"- 1\n- 2\n",
}


@pytest.mark.parametrize("case", sorted(BAD_BYTES))
def test_malformed_files_end_in_one_line(tmp_path, case):
    """Never a traceback, never gigabytes."""
    path = tmp_path / "gains.yaml"
    path.write_bytes(BAD_BYTES[case])
    with pytest.raises(ParameterError) as e:
        gains.load(path)
    assert "\n" not in str(e.value) and len(str(e.value)) < 300


def test_a_refused_export_says_so_and_names_the_file_left_in_place(tmp_path):
    """A report and plots used to describe gains that were not in gains.yaml.  Refused gains write
    nothing, and the report's entry names the earlier gains.yaml left as it was (by its sha256)."""
    import hashlib

    from pusupu_jax.tune.config import TuneConfig
    from pusupu_jax.tune.job import export

    cfg = TuneConfig()
    good = export(tmp_path, cfg, GOOD, HYBRID, RATES, TUNED, {})
    assert good.gains_file.sha256 == hashlib.sha256((tmp_path / "gains.yaml").read_bytes()).hexdigest()
    assert {p.split("/")[-1] for p in good.exported} == {
        "gains.yaml",
        "ros2_pid_controller.yaml",
        "ros2_joint_trajectory_controller.yaml",
    }
    before = (tmp_path / "gains.yaml").read_bytes()
    bad = export(tmp_path, cfg, GOOD.replace(Kv=np.full(6, 2.0)), HYBRID, RATES, TUNED, {})
    assert bad.exported == [] and "velocity loop" in bad.error
    assert bad.gains_file.path is None and "velocity loop" in bad.gains_file.not_written
    assert bad.gains_file.left_as_it_was["sha256"] == good.gains_file.sha256
    assert (tmp_path / "gains.yaml").read_bytes() == before


def test_the_loads_a_file_was_tuned_with_are_checked_again_on_every_read(tmp_path):
    """``provenance.margin_loads_kg`` (each slider's mass at the lightest and the heaviest pose along the tuned
    paths) is checked with the margins on writing and on every read, on the machine the file was tuned on.  Table 1's
    position loop keeps 52.1 deg at the built-in machine's 54.7 kg and 39.4 deg at 300 kg: a recorded 300 kg is
    refused when written, and when edited into a written file, naming the load; on another machine the recorded
    masses are not its own and home alone is checked; a malformed record, or a load of another name, is refused in
    one line."""
    from pusupu_jax import machine_file
    from pusupu_jax.machine_file import Machine

    table1, builtin = ServoParams.table1(), Machine.default()
    home = machine_file.axis_load(builtin).mass.tolist()
    recorded = {"home": home, "lightest": [40.0] * 6, "heaviest": [60.0] * 6}
    path = gains.write(tmp_path / "g.yaml", table1, HYBRID, RATES, mode="imc", provenance={"margin_loads_kg": recorded})
    g = gains.load(path)
    loads = gains.tuned_loads(g.document["provenance"], builtin, g.machine)
    assert list(loads) == ["home", "lightest", "heaviest"] and float(loads["heaviest"].mass[0]) == 60.0
    heavy = "expected at least 45 deg and 6 dB \\(with the mass the sliders carry at the heaviest pose along the paths"
    with pytest.raises(ParameterError, match="position loop of axis 1 has 39.4 deg .*" + heavy):
        gains.write(
            tmp_path / "no.yaml",
            table1,
            HYBRID,
            RATES,
            mode="imc",
            provenance={"margin_loads_kg": recorded | {"heaviest": [300.0] * 6}},
        )
    assert not (tmp_path / "no.yaml").exists()
    path.write_text(path.read_text().replace("heaviest: [60.0", "heaviest: [300.0"))
    with pytest.raises(ParameterError, match=heavy):
        gains.load(path)
    other = {"name": "another", "digest": "0" * 64}
    assert list(gains.tuned_loads(g.document["provenance"], builtin, other)) == ["home"]
    for bad in ([1.0, "x"], [0.0] * 6, [50.0] * 5, 50.0):
        with pytest.raises(ParameterError, match="provenance.margin_loads_kg.heaviest: expected 6 masses above 0 kg"):
            gains.tuned_loads({"margin_loads_kg": {"heaviest": bad}}, builtin, g.machine)
    for tuned_on in (g.machine, other):  # a load of no such name: on any machine
        with pytest.raises(ParameterError, match="margin_loads_kg: expected loads named from .*, got 'heavyest'"):
            gains.tuned_loads({"margin_loads_kg": {"heavyest": [60.0] * 6}}, builtin, tuned_on)
