"""A machine that differs from its machine file (PlantDrives): the plant, the motor and the drive's own feedforward take
the machine's drive values, the host's laws the file's; and machines drawn from an identified machine's standard
errors."""

import dataclasses

import jax
import numpy as np
import pytest

from pusupu_jax import AxisLoad, ServoParams, rollout
from pusupu_jax.machine_draws import DRAWN_DRIVES, draw, plant_drives
from pusupu_jax.machine_file import Correlation, Machine
from pusupu_jax.params import ParameterError
from pusupu_jax.plant import PlantDrives
from pusupu_jax.trajectories import axis_reference

SERVO = ServoParams.table1()
LOAD = AxisLoad.default().replace(inclination=np.full(6, 1.0))  # gravity along the rails: a holding current
REF = axis_reference("sine", duration=0.4) / (float(SERVO.lead[0]) / (2 * np.pi))  # motor angle [rad]
OTHER = {  # a machine unlike Table 1's in every drawn field
    "coulomb": np.asarray(SERVO.coulomb) + 4.0,
    "viscous": np.asarray(SERVO.viscous) * 2.0 + 20.0,
    "J": np.asarray(SERVO.J) * 1.3,
    "Kt": np.asarray(SERVO.Kt) * 1.1,
    "Ke": np.asarray(SERVO.Ke) * 1.1,
}


def _run(servo, params):
    return rollout(servo, params, REF, outer="imc")


def test_a_machine_that_is_what_its_controller_is_told_runs_as_without_drive_values():
    told = {k: np.asarray(getattr(SERVO, k)) for k in OTHER}
    a, b = _run(SERVO, LOAD), _run(SERVO, PlantDrives(LOAD, told))
    np.testing.assert_array_equal(np.asarray(a.theta), np.asarray(b.theta))
    np.testing.assert_array_equal(np.asarray(a.current), np.asarray(b.current))


def test_in_the_position_modes_a_machine_runs_as_if_its_machine_file_had_its_drive_values():
    """No position-mode controller reads friction, ``J``, ``Kt`` or ``Ke``, and the drive's own back-EMF feedforward
    knows its motor: a machine with other values runs as one whose machine file has them (to float64 rounding: the
    same operations in another program).  At rest its motor holds with its own torque constant: 1/1.1 of the
    current for a ``Kt`` 10 % above."""
    a, b = _run(SERVO.replace(**OTHER), LOAD), _run(SERVO, PlantDrives(LOAD, OTHER))
    np.testing.assert_allclose(np.asarray(b.theta), np.asarray(a.theta), rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(np.asarray(b.current), np.asarray(a.current), rtol=1e-10, atol=1e-12)
    hold = np.asarray(_run(SERVO, LOAD).current)[0]
    kt_only = _run(SERVO, PlantDrives(LOAD, {"Kt": OTHER["Kt"]}))
    np.testing.assert_allclose(np.asarray(kt_only.current)[0], hold / 1.1, rtol=1e-12)


def test_the_host_keeps_the_machine_files_values_and_the_drive_takes_its_motors():
    """:func:`loops.on_machine`: the motor's model, torque constant and the drive's back-EMF feedforward from the
    machine; the hybrid force law's current ``r / (eta Kt)`` and ROS's clamp ``V_max / Ke``, which the host computes
    from the machine file, as told."""
    from pusupu_jax import loops
    from pusupu_jax.params import LoopRates

    rates = LoopRates()
    told = loops.discretize(SERVO, rates)
    machine = loops.on_machine(told, SERVO.replace(**OTHER), rates)
    whole = loops.discretize(SERVO.replace(**OTHER), rates)
    np.testing.assert_array_equal(machine.force_current, told.force_current)
    np.testing.assert_array_equal(machine.ros.limit, told.ros.limit)
    np.testing.assert_allclose(machine.Kt, 1.1 * np.asarray(told.Kt), rtol=1e-15)
    np.testing.assert_allclose(machine.emf_gain, 1.1 * np.asarray(told.emf_gain), rtol=1e-15)
    for a, b in zip(jax.tree.leaves(machine.electrical), jax.tree.leaves(whole.electrical)):
        np.testing.assert_array_equal(a, b)
    assert not np.allclose(whole.force_current, told.force_current)


def _identified():
    m = Machine.default()
    return Machine(
        m.name,
        m.geometry,
        m.drives,
        uncertainty={
            "coulomb": np.full(6, 2.0),
            "viscous": np.zeros(6),
            "Kt": np.full(6, 0.05),
            "payload_mass": np.array(0.5),
            "payload_com": np.array([0.01, 0.0, 0.02]),
        },
    )


def test_draws_spread_each_value_by_its_standard_error_and_carry_ke_with_kt():
    """2000 draws: each drawn value's sample mean and spread within 4 sampling errors of the machine's value and
    standard error (Coulomb's 10 N against 2 N: never clipped at 0); values with no or a zero standard error stay."""
    m = _identified()
    drawn = draw(m, 2000, seed=3)
    for name, value, std in (
        ("coulomb", m.drives["coulomb"], 2.0),
        ("Kt", m.drives["Kt"], 0.05),
    ):
        x = np.array([d.drives[name] for d in drawn])  # (2000, 6)
        n = len(x)
        assert np.all(np.abs(x.mean(axis=0) - value) < 4 * std / np.sqrt(n))
        assert np.all(np.abs(x.std(axis=0) / std - 1) < 4 / np.sqrt(2 * n))
    for d in drawn[:5]:
        np.testing.assert_allclose(d.drives["Ke"] / m.drives["Ke"], d.drives["Kt"] / m.drives["Kt"], rtol=1e-14)
        np.testing.assert_array_equal(d.drives["viscous"], m.drives["viscous"])
        np.testing.assert_array_equal(d.drives["J"], m.drives["J"])
        assert d.payload.com[1] == 0.0 and d.uncertainty is None
    masses = np.array([d.payload.mass for d in drawn])
    # normal about 0 kg, clipped at 0: a spread of sigma sqrt(1/2 - 1/(2 pi)), 0.58 sigma
    assert masses.min() == 0.0 and abs(masses.std() - 0.5 * np.sqrt(0.5 - 1 / (2 * np.pi))) < 0.02
    assert [d.name for d in drawn[:2]] == ["built-in draw 1", "built-in draw 2"]


def test_correlated_values_are_drawn_together_and_the_others_as_without_a_correlation():
    """A correlation of 0.9 between ``coulomb[1]`` and ``Kt[2]`` and of -0.5 between ``coulomb[1]`` and the payload's
    mass: over 2000 draws the sample correlations lie within 4 sampling errors of them ((1 - r^2) / sqrt(n)), each
    value keeps its spread, and the values the correlation leaves out are drawn as without it (the same seed)."""
    m = _identified()
    m = dataclasses.replace(
        m,
        uncertainty=m.uncertainty | {"payload_mass": np.array(0.05)},
        payload=dataclasses.replace(m.payload, mass=2.0),  # 40 standard errors from 0: never clipped
        correlation=Correlation(
            ("coulomb[1]", "Kt[2]", "payload_mass"), np.array([[1, 0.9, -0.5], [0.9, 1, -0.45], [-0.5, -0.45, 1]])
        ),
    )
    drawn, plain = draw(m, 2000, seed=5), draw(dataclasses.replace(m, correlation=None), 2000, seed=5)
    x = np.array([[d.drives["coulomb"][0], d.drives["Kt"][1], d.payload.mass] for d in drawn])
    r, n = np.corrcoef(x.T), len(x)
    for (i, j), expected in {(0, 1): 0.9, (0, 2): -0.5, (1, 2): -0.45}.items():
        assert abs(r[i, j] - expected) < 4 * (1 - expected**2) / np.sqrt(n)
    assert np.all(np.abs(x.std(axis=0) / [2.0, 0.05, 0.05] - 1) < 4 / np.sqrt(2 * n))
    for d, p in zip(drawn[:20], plain[:20]):
        np.testing.assert_array_equal(d.drives["coulomb"][1:], p.drives["coulomb"][1:])
        np.testing.assert_array_equal(np.delete(d.drives["Kt"], 1), np.delete(p.drives["Kt"], 1))
        assert d.payload.com == p.payload.com and d.correlation is None
    assert not np.array_equal([d.drives["Kt"][1] for d in drawn[:20]], [p.drives["Kt"][1] for p in plain[:20]])


def test_the_same_seed_draws_the_same_machines_and_a_machine_without_uncertainty_is_refused():
    m = _identified()
    a, b = draw(m, 3, seed=7), draw(m, 3, seed=7)
    for x, y in zip(a, b):
        for k in DRAWN_DRIVES:
            np.testing.assert_array_equal(plant_drives(x)[k], plant_drives(y)[k])
    assert not np.array_equal(a[0].drives["coulomb"], draw(m, 1, seed=8)[0].drives["coulomb"])
    with pytest.raises(ParameterError, match="expected a machine file with an uncertainty section"):
        draw(Machine.default(), 2, seed=0)
