"""The coupled linear model (pusupu_jax.coupled) against python-control's interconnection of the same blocks on the
mechanism's state space, and against the single-axis model where the axes do not couple."""

import control as ct
import numpy as np
import pytest

from pusupu_jax import AxisLoad, ServoParams, analysis, coupled, margins
from pusupu_jax.params import N_AXES
from pusupu_jax.plant.geometry import Geometry

W = np.logspace(0, 4, 9)  # rad/s: from below the position loop's crossover to above the current loop's


def _axis(sys: ct.StateSpace, k: int, rename: dict | None = None) -> ct.StateSpace:
    """``sys`` with every signal of axis ``k`` suffixed ``_k`` (``rename``: signals given other names)."""
    rename = rename or {}

    def label(n: str) -> str:
        return rename.get(n, f"{n}_{k}")

    return ct.ss(
        *ct.ssdata(sys),
        inputs=[label(n) for n in sys.input_labels],
        outputs=[label(n) for n in sys.output_labels],
        name=f"{sys.name}_{k}",
    )


def _mechanism(servo: ServoParams, mech: coupled.Mechanism) -> ct.StateSpace:
    """The mechanism's state space: the platform's coordinates and rates, torques ``tau_k`` in, ``theta_k``, ``w_k``
    out (module docstring of pusupu_jax.coupled), written from its equation of motion."""
    J = np.asarray(mech.jacobian)
    n = J.shape[1]
    r = np.asarray(servo.lead) / (2 * np.pi)
    inertia = mech.inertia + J.T @ np.diag(np.asarray(servo.eta) * np.asarray(servo.J) / r**2) @ J
    minv = np.linalg.inv(inertia)
    A = np.block([[np.zeros((n, n)), np.eye(n)], [np.zeros((n, n)), -minv @ J.T @ np.diag(servo.viscous) @ J]])
    B = np.vstack([np.zeros((n, N_AXES)), minv @ J.T @ np.diag(np.asarray(servo.eta) / r)])
    angles = J / r[:, None]
    C = np.block([[angles, np.zeros_like(angles)], [np.zeros_like(angles), angles]])
    return ct.ss(
        A,
        B,
        C,
        np.zeros((2 * N_AXES, N_AXES)),
        inputs=[f"tau_{k}" for k in range(N_AXES)],
        outputs=[f"theta_{k}" for k in range(N_AXES)] + [f"w_{k}" for k in range(N_AXES)],
        name="mechanism",
    )


def _broken(servo: ServoParams, mech: coupled.Mechanism, axis: int, loop: str) -> ct.StateSpace:
    """python-control's interconnection of the six cascades (pusupu_jax.analysis.blocks, IMC) on the mechanism, axis
    ``axis``'s ``loop`` broken at its controller's output ``y``: the system from the injection to ``y``."""
    controller, injected = {
        "current": ("Gi", "u_pi"),
        "velocity": ("Gv", "i_ref"),
        "velocity_in_position": ("Gv", "i_ref"),
        "position": ("C2", "w_ref"),
    }[loop]
    dropped = {"current": "Gv", "velocity": "C2"}.get(loop)  # the broken axis's own outer loop left open
    parts = [_mechanism(servo, mech)]
    for k in range(N_AXES):
        b = analysis.blocks(servo, AxisLoad.default(), k)
        for name in ("Gxi", "Gcf", "Gi", "EMF", "u", "Kt", "electrical", "Gxv", "Gw", "Gv", "C2"):
            if k == axis and name == dropped:
                continue
            parts.append(_axis(b[name], k, {b[name].output_labels[0]: "y"} if k == axis and name == controller else {}))
        parts += [
            ct.summing_junction(inputs=[f"i_r_{k}", f"-i_f_{k}"], output=f"e_i_{k}"),
            ct.summing_junction(inputs=[f"w_r_{k}", f"-w_f_{k}"], output=f"e_w_{k}"),
            ct.summing_junction(inputs=[f"-theta_{k}"], output=f"e_p_{k}"),
        ]
    return ct.interconnect(parts, inputs=[f"{injected}_{axis}"], outputs=["y"], check_unused=False)


@pytest.fixture(scope="module")
def machine_at_home():
    """The built-in machine at home with Table 1 and a viscous drive train (so that the damping term is in)."""
    servo = ServoParams.table1().replace(viscous=np.full(N_AXES, 50.0))
    geom = Geometry.default()
    return servo, coupled.Mechanism.at(geom, geom.home)


@pytest.mark.parametrize("loop", coupled.LOOPS)
def test_the_coupled_loops_are_python_controls_interconnection_of_the_same_blocks(machine_at_home, loop):
    """Axes 1 and 4 broken in turn, the other five closed: ``L(jw)`` at nine frequencies from the 70-state
    interconnection equals the 5 x 5 impedance solved per frequency to 1e-9 relative (both exact in float64; measured
    2e-14, the slack is for the conditioning of a 70-state system)."""
    servo, mech = machine_at_home
    ours = np.asarray(coupled.loop_gains(servo, mech, W)[loop])
    for axis in (0, 3):
        sys = _broken(servo, mech, axis, loop)
        theirs = -np.squeeze(sys(1j * W))
        np.testing.assert_allclose(ours[axis], theirs, rtol=1e-9)


def test_on_a_mechanism_whose_axes_do_not_couple_it_is_the_single_axis_model():
    """Six sliders each carrying its own mass (a 6-DOF mechanism of diagonal inertia, ``J = 1``): every loop of the
    coupled model equals :func:`pusupu_jax.margins.loop_gains` with those masses, to rounding."""
    servo = ServoParams.table1().replace(viscous=np.linspace(0.0, 80.0, N_AXES))
    masses = np.linspace(20.0, 90.0, N_AXES)
    mech = coupled.Mechanism(inertia=np.diag(masses), jacobian=np.eye(N_AXES))
    ours = coupled.loop_gains(servo, mech, W)
    single = margins.loop_gains(servo, AxisLoad.default().replace(mass=masses), W)
    for loop in ("current", "velocity", "position"):
        np.testing.assert_allclose(np.asarray(ours[loop]), np.asarray(single[loop]), rtol=1e-10)


def test_coupled_margins_read_each_axis_at_its_own_crossings(machine_at_home):
    """:func:`pusupu_jax.coupled.loop_margins` reads each loop at a true gain crossover: python-control's
    interconnection has ``|L| = 1`` there, and the phase margin is its phase plus 180 deg (within (-180, 180]), to
    1e-6 (the crossing is refined by secant steps on the exact response; measured 2e-15 and 1e-13 deg)."""
    servo, mech = machine_at_home
    ours = coupled.loop_margins(servo, mech)
    for loop in coupled.LOOPS:
        for axis in (0, 3):
            w_c = float(ours[loop]["crossover_rad_s"][axis])
            L = -complex(np.squeeze(_broken(servo, mech, axis, loop)(1j * w_c)))
            assert abs(L) == pytest.approx(1.0, abs=1e-6), (loop, axis)
            pm = 180.0 - np.mod(-np.degrees(np.angle(L)), 360.0)
            assert float(ours[loop]["phase_margin_deg"][axis]) == pytest.approx(pm, abs=1e-6), (loop, axis)
