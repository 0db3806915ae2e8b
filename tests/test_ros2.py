"""The ROS 2 export: files that satisfy ros2_controllers' own parameter definitions, the conversion of the tuned
controllers (checked against python-control), and the simulated ROS loop against control_toolbox's algorithm."""

import json
from pathlib import Path

import control as ct
import numpy as np
import pytest
import yaml

from pusupu_jax import AxisLoad, LoopRates, ParameterError, ServoParams, rollout, ros2
from pusupu_jax import analysis as an
from pusupu_jax.plant.axis import screw_ratio

DEFINITIONS = json.loads((Path(__file__).parent / "data" / "ros2_controllers_parameters.json").read_text())
SERVO = ServoParams.table1().replace(lambda2=np.full(6, 0.06), T0=np.full(6, 0.03))
RATES = LoopRates(n_mech=5)
TYPES = {"double": float, "bool": bool, "string": str, "string_array": list, "int": int}


def _check(params: dict, definition: dict, joints_key: str):
    """Every key is a parameter of the controller, of its type, within its validations; every gain likewise."""
    for key, value in params.items():
        if key == "gains":
            continue
        spec = definition["parameters"][key]  # KeyError: not a parameter of the controller
        assert isinstance(value, TYPES[spec["type"]]), (key, value)
        if spec["type"] == "string_array":
            assert all(isinstance(v, str) for v in value)
        if spec.get("not_empty"):
            assert value, key
        if "subset_of" in spec:
            assert set(value) <= set(spec["subset_of"]), key
        if "size_lt" in spec:
            assert len(value) < spec["size_lt"], key
    for key, spec in definition["parameters"].items():
        if spec.get("not_empty"):
            assert key in params, f"required parameter {key} missing"
    assert sorted(params["gains"]) == sorted(params[joints_key])
    for joint, g in params["gains"].items():
        for key, value in g.items():
            spec = definition["gains"][key]
            assert isinstance(value, TYPES[spec["type"]]), (joint, key, value)
            if "one_of" in spec:
                assert value in spec["one_of"], (key, value)


@pytest.mark.parametrize("mode", ["hybrid", "imc", "pid", "pid_ff"])
def test_exported_files_load_as_ros2_controllers_defines_them(tmp_path, mode):
    files = ros2.write_files(tmp_path, SERVO, mode, RATES, source="test", joints=ros2.JOINTS)
    pid = yaml.safe_load(files[0].read_text())
    jtc = yaml.safe_load(files[1].read_text())
    assert files[0].read_text().startswith("# Exported by pusupu_jax")
    for doc, name, kind, joints_key in (
        (pid, ros2.PID_CONTROLLER, "pid_controller", "dof_names"),
        (jtc, ros2.TRAJECTORY_CONTROLLER, "joint_trajectory_controller", "joints"),
    ):
        manager = doc["controller_manager"]["ros__parameters"]
        assert manager["update_rate"] == 1000 and manager[name]["type"].startswith(kind)
        _check(doc[name]["ros__parameters"], DEFINITIONS[kind], joints_key)
    g = pid[ros2.PID_CONTROLLER]["ros__parameters"]["gains"]["slide_1"]
    expected = ros2.ros_gains(SERVO, mode)
    assert g["p"] == expected["p"][0] and g["i"] == expected["i"][0] and g["d"] == expected["d"][0]
    assert g["feedforward_gain"] == (1.0 if mode == "pid_ff" else 0.0)
    r = float(screw_ratio(SERVO)[0])
    assert g["u_clamp_max"] == pytest.approx(r * 300.0 / 1.322)  # joint units: m/s


def test_joint_names_are_configurable_and_checked(tmp_path):
    names = tuple(f"leg{k}_slider" for k in range(6))
    doc = ros2.pid_controller_params(SERVO, "pid", RATES, names)
    assert doc[ros2.PID_CONTROLLER]["ros__parameters"]["dof_names"] == list(names)
    with pytest.raises(ParameterError, match="expected 6 distinct names"):
        ros2.pid_controller_params(SERVO, "pid", RATES, names[:5] + names[:1])


@pytest.mark.parametrize("lambda2, T0", [(0.15, 0.01475), (0.06, 0.03), (0.03, 0.07)])
def test_c2_is_the_exported_pid_behind_its_output_filter(lambda2, T0):
    """C2 (python-control, from eq. 9) = (p + i/s + d s)/((l2/3) s + 1) with the exported p, i, d, to 1e-9 over
    1e-2..1e5 rad/s: the only thing ROS drops from C2 is that filter."""
    servo = ServoParams.table1().replace(lambda2=np.full(6, lambda2), T0=np.full(6, T0))
    g = ros2.ros_gains(servo, "imc")
    s = ct.tf("s")
    pid_form = (g["p"][0] + g["i"][0] / s + g["d"][0] * s) / (lambda2 / 3 * s + 1)
    c2 = an.blocks(servo, AxisLoad.default())["C2"]
    w = 1j * np.logspace(-2, 5, 300)
    np.testing.assert_allclose(pid_form(w), c2(w), rtol=1e-9)


def test_the_simulated_ros_loop_is_control_toolbox_s_pid():
    """rollout(outer='ros_pid') against control_toolbox's Pid::compute_command written out in Python, fed the same
    measurements: a 20 mm step (the output and the integral clamp, conditional integration holds), then a ramp."""
    servo = SERVO.replace(
        Kp_pid=np.full(6, 40.0), Ki_pid=np.full(6, 200.0), Kd_pid=np.full(6, 0.05), Kff_pid=np.full(6, 0.8)
    )
    r = float(screw_ratio(servo)[0])
    t = np.arange(400) * RATES.dt_position
    ref = (0.02 + 0.02 * np.clip(t - 0.2, 0, None)) / r  # motor angle [rad]
    trace = rollout(servo, AxisLoad.default(), np.repeat(ref[:, None], 6, axis=1), outer="ros_pid")
    p, i, d, ff = 40.0, 200.0, 0.05, 0.8
    limit, dt = 300.0 / 1.322, RATES.dt_position
    integral, previous, expected = 0.0, 0.0, []
    theta, omega = np.asarray(trace.theta)[:, 0], np.asarray(trace.omega)[:, 0]
    for k in range(len(t)):
        v_ref = (ref[k] - previous) / dt
        e = ref[k] - theta[k]
        unsat = p * e + integral + d * (v_ref - omega[k])
        u = min(max(unsat, -limit), limit)
        if not (unsat != u and e * unsat > 0):  # conditional integration
            integral += dt * i * e
        integral = min(max(integral, -limit), limit)
        expected.append(ff * v_ref + u)
        previous = ref[k]
    got = np.asarray(trace.command)[:, 0]
    np.testing.assert_allclose(got, expected, rtol=1e-12, atol=1e-9)
    assert np.sum(np.abs(got - ff * np.diff(ref, prepend=0.0) / dt) >= limit - 1e-9) > 3  # the clamp was reached
