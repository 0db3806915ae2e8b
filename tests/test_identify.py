"""``pusupu identify``: a machine's drive-train friction fitted back from the log of its own run.

The log comes from ``pusupu sim --plant mjx --log`` on a machine whose friction differs from the built-in one on every
axis (Coulomb and viscous), under a gain file; ``pusupu identify`` starts from the built-in machine and the same gain
file.  The simulator that wrote the log (the chunked forward pass) and the replay (one rollout) are the same model,
with no noise, so the fit must find the friction to the solver's tolerance: 1e-6 relative is asserted (found: 5e-10 on
the Coulomb values, 6e-8 on the viscous ones for a 1 s window of the arc).
"""

import hashlib
import json
import subprocess
import sys

import numpy as np
import pytest

from pusupu_jax import LoopRates, ParameterError, ServoParams, gains, machine_file, run_log
from pusupu_jax.hybrid import HybridGains
from pusupu_jax.machine_fit import FitField, fit_fields

COULOMB = [28.0, 24.0, 20.0, 16.0, 30.0, 22.0]  # N, against the built-in 20
VISCOUS = [35.0, 60.0, 50.0, 80.0, 40.0, 55.0]  # N s/m, against the built-in 50


def pusupu(*args):
    r = subprocess.run([sys.executable, "-m", "pusupu_jax.cli", *map(str, args)], capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    return r


def test_fit_names_are_fields_or_the_friction_group():
    assert fit_fields("friction") == (FitField.COULOMB, FitField.VISCOUS)
    assert fit_fields("viscous,coulomb,viscous") == (FitField.VISCOUS, FitField.COULOMB)
    with pytest.raises(ParameterError, match="--fit: expected names among friction, coulomb, viscous, got 'mass'"):
        fit_fields("coulomb,mass")


def test_a_file_that_is_not_a_run_log_is_refused_in_one_line(tmp_path):
    bad = tmp_path / "gains.mcap"
    bad.write_text("schema: pusupu-gains\n")
    with pytest.raises(ParameterError, match="expected an MCAP run log"):
        run_log.drive_log(bad)


@pytest.mark.slow
def test_identify_finds_the_friction_of_the_machine_that_ran(tmp_path):
    """0.7 s of a pose table with tilts and reversals, run on the other machine and logged; identified from the
    built-in machine: every Coulomb and viscous value to 1e-6, the residual down by six orders, the machine file
    written with the log's digest, and the plot."""
    true = machine_file.template().replace("  coulomb: 20.0", f"  coulomb: {COULOMB}")
    true = true.replace("  viscous: 50.0", f"  viscous: {VISCOUS}")
    (tmp_path / "true.yaml").write_text(true)
    assert machine_file.load(tmp_path / "true.yaml").drives["coulomb"].tolist() == COULOMB
    builtin = machine_file.Machine.default()
    gains.write(tmp_path / "g.yaml", builtin.servo(ServoParams.table1()), HybridGains(), LoopRates(), mode="imc")
    rows = [(0, 0, 0, 0, 0, 0), (0.1, 0, 0, 0, 0, 0), (0.35, 0.004, 0.002, -0.001, 0.01, -0.01)]
    rows += [(0.6, -0.003, -0.002, 0.001, -0.01, 0.01), (0.7, -0.003, -0.002, 0.001, -0.01, 0.01)]
    path = tmp_path / "path.csv"
    path.write_text("t,x,y,z,a,b\n" + "".join(",".join(map(str, r)) + "\n" for r in rows))
    log = tmp_path / "run.mcap"
    pusupu(
        "sim",
        "--plant",
        "mjx",
        "--machine",
        tmp_path / "true.yaml",
        "--gains",
        tmp_path / "g.yaml",
        "--trajectory",
        path,
        "--json",
        "--log",
        log,
    )
    out, png = tmp_path / "identified.yaml", tmp_path / "fit.png"
    report = json.loads(
        pusupu(
            "identify", log, "--gains", tmp_path / "g.yaml", "--window", 0.7, "--out", out, "--plot", png, "--json"
        ).stdout
    )
    found = {(v["field"], v["axis"]): v for v in report["values"]}
    for field, truth in (("coulomb", COULOMB), ("viscous", VISCOUS)):
        for axis, value in enumerate(truth):
            v = found[(field, axis)]
            assert v["excited"] and v["start"] == {"coulomb": 20.0, "viscous": 50.0}[field]
            assert v["value"] == pytest.approx(value, rel=1e-6), (field, axis)
    assert report["residual_rms_after"] < 1e-6 * report["residual_rms_before"]
    identified = machine_file.load(out)
    np.testing.assert_allclose(identified.drives["coulomb"], COULOMB, rtol=1e-6)
    np.testing.assert_allclose(identified.drives["viscous"], VISCOUS, rtol=1e-6)
    assert hashlib.sha256(log.read_bytes()).hexdigest() in out.read_text()
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
