"""The contact experiments of Fig. 9 in their quick form: real MJX contact under the cascade, through the CLI; first,
the compliant rollout on the surface scene, which must be the plain one while nothing touches (its two programs are
the quick surface run's, IMC stiff and IMC with force control, which loads them from the persistent cache)."""

import json
import subprocess
import sys

import numpy as np
import pytest

from pusupu_jax.experiments import surface_tracking
from pusupu_jax import LoopRates, ServoParams
from pusupu_jax.machine import Scenario, simulate_scenarios
from pusupu_jax.plant.geometry import Geometry

pytestmark = pytest.mark.slow  # integration: every test here runs commands end to end

TIMEOUT_S = 1800  # s: each run compiles two contact rollouts; 3 min here, allow a machine 2.5x slower and loaded


def test_a_compliant_run_with_nothing_touching_is_the_plain_run():
    """The surface scene at home (the tool 30 mm over the surface), holding still for 0.1 s: no contact force, so
    the admittance stays at zero and the references recomputed from the pose every period are the precomputed
    ones: every recorded signal agrees with the plain run to 1e-12 relative (the inverse kinematics is the same
    closed form, evaluated in the scan instead of before it), the platform's position to 1e-12 m (1e-12 of its
    0.8 m height: its x and y, some 1e-14 m of rounding drift about zero, differed by up to 3.5e-14 m)."""
    options = surface_tracking.options()  # the experiment's scene and solver: 10 mrad tilt, 4 Newton iterations
    path = np.repeat(np.asarray(Geometry.default().home)[None], 100, axis=0)
    ((plain, a),) = simulate_scenarios(ServoParams.table1(), [Scenario(path, options)], mode="imc")
    ((soft, b),) = simulate_scenarios(
        ServoParams.table1(), [Scenario(path, options)], mode="imc", compliance=surface_tracking.ADMITTANCE
    )
    assert np.all(b["contact_force"] == 0.0) and np.all(b["compliance_offset"] == 0.0)
    np.testing.assert_allclose(b["platform"], a["platform"], rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(soft.metrics.branch_force_peak_n, plain.metrics.branch_force_peak_n, rtol=1e-12)
    assert LoopRates().dt_position == 1e-3  # the period the admittance's checks assume here


def _experiment(name, out):
    proc = subprocess.run(
        [sys.executable, "-m", "pusupu_jax.cli", "experiment", name, "--quick", "--out", str(out), "--json"],
        capture_output=True,
        text=True,
        timeout=TIMEOUT_S,
    )
    assert proc.returncode == 0, proc.stderr[-2000:]
    for suffix in (".json", ".md", ".png"):
        assert (out / f"{name}{suffix}").stat().st_size > 0
    return json.loads((out / f"{name}.json").read_text())


@pytest.mark.parametrize("name", ["peg_in_hole", "surface_tracking"])
def test_contact_experiment_quick(name, tmp_path):
    """peg_in_hole: both runs insert (no jam) with contact forces that the scene produced, and the admittance ends
    with a lower lateral force than stiff IMC, which keeps pushing the peg against the wall (quick run: 43 -> 0 N
    here).  surface_tracking: force control holds the normal force closer to its setpoint than stiff position
    control, which holds none (quick run: RMS error 35 -> 18 N here) and stays in contact most of the time."""
    m = _experiment(name, tmp_path)
    runs = m["runs"]
    if name == "peg_in_hole":
        stiff, soft = runs["IMC, stiff"], runs["hybrid + admittance"]
        for r in (stiff, soft):
            assert not r["jammed"] and r["final_depth_mm"] > 0.9 * r["commanded_depth_mm"]
            assert r["peak_lateral_force_n"] > 5.0 and r["peak_axial_force_n"] > 5.0  # N: it did touch
        assert soft["final_lateral_force_n"] < 0.5 * stiff["final_lateral_force_n"]
    else:
        stiff, soft = runs["IMC, stiff"], runs["IMC + force control"]
        assert soft["force_error_rms_n"] < stiff["force_error_rms_n"]
        assert soft["contact_lost_fraction"] < 0.25
        assert abs(soft["normal_force_mean_n"] - m["force_setpoint_n"]) < 0.5 * m["force_setpoint_n"]
