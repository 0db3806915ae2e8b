"""``pusupu identify``'s inputs: the names of the fields to fit, a file that is not a run log, Kt asked of a log
without currents, and CSV drive tables that do not follow their layout (one that does is read in tests/test_paths.py,
against its MCAP log); fitted values written into a machine file; the solver that keeps a value the data do not
excite at its start, on a linear problem; and one fit of a simulated log end to end, every value of the standard set
(friction, rotor inertia, torque constant, the payload's mass and centre of mass) of a machine it did not start from
(docs/identify.md and benchmarks/bench_identify.py have the full fits: C MuJoCo's logs, with noise)."""

import dataclasses
import subprocess
import sys
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from pusupu_jax import ParameterError, ServoParams, fit_errors, machine_fit, run_log
from pusupu_jax.machine_fit import FitField, fit_fields, least_squares_excited


def test_fit_names_are_fields_or_groups():
    assert fit_fields("friction") == (FitField.COULOMB, FitField.VISCOUS)
    assert fit_fields("viscous,coulomb,viscous") == (FitField.VISCOUS, FitField.COULOMB)
    assert fit_fields("motor,friction,J") == (
        FitField.INERTIA,
        FitField.TORQUE_CONSTANT,
        FitField.COULOMB,
        FitField.VISCOUS,
    )
    assert fit_fields("payload") == (FitField.PAYLOAD_MASS, FitField.PAYLOAD_COM)
    with pytest.raises(
        ParameterError,
        match="--fit: expected names among friction, motor, payload, coulomb, viscous, J, Kt, payload_mass, "
        "payload_com, got 'mass'",
    ):
        fit_fields("coulomb,mass")


def test_fitted_values_go_into_the_machine_file_that_is_written():
    """Drive fields per axis and the payload's mass and centre of mass: read from the machine as the fit's start,
    named one by one, and written back into a machine file that loads with them."""
    import yaml

    from pusupu_jax import machine_file
    from pusupu_jax.machine_file import Machine

    start = Machine.default()
    assert FitField.COULOMB.start(start).tolist() == [20.0] * 6
    assert FitField.PAYLOAD_COM.start(start).tolist() == [0.0] * 3 and FitField.PAYLOAD_MASS.start(start).size == 1
    assert [FitField.VISCOUS.label(5), FitField.PAYLOAD_COM.label(1), FitField.PAYLOAD_MASS.label(0)] == [
        "viscous[6]",
        "payload_com.y",
        "payload_mass",
    ]
    fitted = machine_fit.with_values(
        start,
        {
            FitField.TORQUE_CONSTANT: np.linspace(1.2, 1.45, 6),
            FitField.PAYLOAD_MASS: np.array([4.5]),
            FitField.PAYLOAD_COM: np.array([0.01, -0.02, 0.03]),
        },
    )
    written = machine_file.parse(yaml.safe_load(machine_file.template(fitted)))
    assert written.name == "built-in identified"
    np.testing.assert_allclose(written.drives["Kt"], np.linspace(1.2, 1.45, 6), rtol=1e-12)
    # the back-EMF constant follows the torque constant in the machine file's ratio
    ratio = np.asarray(start.drives["Ke"]) / np.asarray(start.drives["Kt"])
    np.testing.assert_allclose(written.drives["Ke"], ratio * np.linspace(1.2, 1.45, 6), rtol=1e-12)
    np.testing.assert_array_equal(written.drives["coulomb"], start.drives["coulomb"])
    assert written.payload.mass == 4.5 and list(written.payload.com) == [0.01, -0.02, 0.03]


def test_the_standard_errors_go_into_the_uncertainty_section_and_an_unexcited_value_has_none():
    """What ``pusupu identify --out`` writes beside the values (``pusupu tune``'s ``draws`` draw from it): each fitted
    value's standard error in its field's shape, 0 where the logs did not excite the value."""
    import dataclasses

    import yaml

    from pusupu_jax import machine_file
    from pusupu_jax.machine_file import Machine

    values = [machine_fit.FittedValue(FitField.VISCOUS, k, 50.0, 51.0, 0.1 * (k + 1), k != 4) for k in range(6)]
    values += [machine_fit.FittedValue(FitField.PAYLOAD_MASS, 0, 3.0, 5.0, 0.02, True)]
    values += [machine_fit.FittedValue(FitField.PAYLOAD_COM, k, 0.0, 0.01, 0.001 * (k + 1), True) for k in range(3)]
    errors = machine_fit.uncertainty_of(tuple(values))
    matrix = np.eye(len(values))
    matrix[0, 6] = matrix[6, 0] = -0.8  # viscous[1] and the payload's mass
    matrix[4, 5] = matrix[5, 4] = 0.9  # viscous[5], not excited: left out
    correlation = machine_fit.correlation_of(tuple(values), matrix)
    assert correlation is not None and "viscous[5]" not in correlation.values and len(correlation.values) == 9
    machine = dataclasses.replace(Machine.default(), uncertainty=errors, correlation=correlation)
    written = machine_file.parse(yaml.safe_load(machine_file.template(machine)))
    assert written.correlation is not None and written.correlation.values == correlation.values
    np.testing.assert_array_equal(written.correlation.matrix, correlation.matrix)
    assert written.correlation.matrix[0, correlation.values.index("payload_mass")] == -0.8
    np.testing.assert_allclose(written.uncertainty["viscous"], [0.1, 0.2, 0.3, 0.4, 0.0, 0.6], rtol=1e-15)
    assert float(written.uncertainty["payload_mass"]) == 0.02 and set(written.uncertainty) == {
        "viscous",
        "payload_mass",
        "payload_com",
    }
    np.testing.assert_allclose(written.uncertainty["payload_com"], [0.001, 0.002, 0.003], rtol=1e-15)


def test_a_fitted_value_against_a_known_truth():
    """The error, the error relative to the truth (a centre-of-mass coordinate's relative to the truth's distance from
    the platform's centre) and whether 1.96 standard errors cover the truth."""
    import dataclasses

    from pusupu_jax.machine_file import Machine, Payload

    truth = dataclasses.replace(Machine.default(), payload=Payload(5.0, (0.03, 0.0, 0.04), (0.02, 0.02, 0.03)))
    coulomb = machine_fit.FittedValue(FitField.COULOMB, 2, 10.0, 21.0, 0.4, True).against(truth)
    assert (coulomb["true"], coulomb["error"], coulomb["relative_error"]) == (20.0, 1.0, 0.05)
    assert coulomb["covered_95"] is False and coulomb["name"] == "coulomb[3]" and coulomb["value"] == 21.0
    com = machine_fit.FittedValue(FitField.PAYLOAD_COM, 1, 0.0, 0.001, 0.001, True).against(truth)
    assert com["true"] == 0.0 and com["relative_error"] == pytest.approx(0.001 / 0.05) and com["covered_95"] is True


def test_a_window_that_ends_at_speed_is_replayed_as_the_run_it_was():
    """The replay checks and references the whole path its log ran, then keeps the window's periods: cut at a window
    that ends with the machine at speed, the path would be checked as one that stops there at once.  The excitation
    path's first 0.3 s were refused so ("path exceeds the drives: pose 299 (t = 0.299 s): branch 5 motor torque
    16.17 N m"); now its replay covers them, and its reference matches the logged one (checked to 1e-6 rad as the
    replay is built).  Nothing is run: the replay's program is only built."""
    from pusupu_jax import LoopRates
    from pusupu_jax.machine import machine_reference
    from pusupu_jax.machine_file import Machine
    from pusupu_jax.paths import platform_path_from

    machine, servo, rates = Machine.default(), ServoParams.table1(), LoopRates()
    path = platform_path_from("excite", machine.geometry.home, rates)
    theta = np.asarray(machine_reference(machine.servo(servo), path, "imc", rates=rates, geom=machine.geometry))
    n, t = 400, np.arange(400) * rates.dt_position  # the log's samples: the first 0.4 s, one a position period
    zero = np.zeros_like(theta[:n])
    log = run_log.DriveLog(
        "run.mcap", "0" * 64, "bridge", None, "imc", "excite", 1 / rates.dt_position, t, theta[:n], theta[:n],
        zero, zero, zero,
    )  # fmt: skip
    replay = machine_fit._replay(log, machine, servo, None, rates, 0.3, None, None)
    assert replay.t[-1] == pytest.approx(0.3 - rates.dt_position) and len(replay.t) == 300


def test_kt_is_not_fitted_to_a_log_without_currents(tmp_path):
    """Without measured currents the replay's torque does not depend on Kt: asking for it is refused in one line,
    before anything is replayed."""
    from pusupu_jax import drive_table
    from pusupu_jax.machine_file import Machine

    names = drive_table.columns(current=False)
    rows = [",".join(f"{v:g}" for v in [0.001 * (k + 1)] + [0.0] * (len(names) - 1)) for k in range(2)]
    log = drive_table.read(_table(tmp_path / "drive.csv", ",".join(names), rows))
    assert log.current is None
    with pytest.raises(ParameterError, match=r"drive.csv: expected measured currents to fit Kt .*, found torques only"):
        machine_fit.fit([log], Machine.default(), ServoParams.table1(), fields=fit_fields("friction,Kt"))


def _identify(tmp_path, *options: str) -> subprocess.CompletedProcess:
    """``pusupu identify x.mcap --out tmp_path/m.yaml`` with ``options``, as a user runs it."""
    command = [sys.executable, "-m", "pusupu_jax.cli", "identify", "x.mcap", "--out", str(tmp_path / "m.yaml")]
    return subprocess.run(command + list(options), capture_output=True, text=True, timeout=600)


def test_a_mech_step_the_machine_cannot_take_is_refused_in_one_line_before_any_replay(tmp_path):
    """The replay's mechanical step must be a whole number of current-loop ticks dividing the velocity period (50 and
    250 us at the default rates); another is refused by the fit and by ``pusupu identify --mech-step`` (exit 2)."""
    from pusupu_jax.machine_file import Machine

    machine_fit.check_mech_step(5e-5)
    machine_fit.check_mech_step(2.5e-4)
    machine_fit.check_mech_step(None)
    expected = (
        r"expected a whole number of current-loop ticks that divides the velocity period, one of 5e-05, 0.00025 s"
    )
    with pytest.raises(ParameterError, match=r"mech step: " + expected + ", got 0.0001"):
        machine_fit.fit([], Machine.default(), ServoParams.table1(), mech_step=1e-4)
    r = _identify(tmp_path, "--mech-step", "1.5e-4")
    assert r.returncode == 2 and r.stderr.strip().splitlines() == [
        f"pusupu: error: --mech-step: {expected.replace(chr(92), '')}, got 0.00015"
    ], r.stderr
    assert not (tmp_path / "m.yaml").exists()


def test_a_fit_in_float32_is_refused_before_any_replay():
    """identify's replays and Jacobians need float64; without it (``setup_jax`` not called) the fit says so at once."""
    from pusupu_jax.machine_file import Machine

    machine, gains = Machine.default(), ServoParams.table1()
    with (
        jax.enable_x64(False),
        pytest.raises(
            RuntimeError, match=r"^identify's replays and their Jacobians compute in float64: call pusupu_jax\.runtime"
        ),
    ):
        machine_fit.fit([], machine, gains)


def test_a_file_that_is_not_a_run_log_is_refused_in_one_line(tmp_path):
    bad = tmp_path / "gains.mcap"
    bad.write_text("schema: pusupu-gains\n")
    with pytest.raises(ParameterError, match="expected an MCAP run log"):
        run_log.drive_log(bad)


def _table(path, header, rows, comments="# mode: pid\n# trajectory: arc\n"):
    path.write_text(comments + header + "\n" + "\n".join(rows) + "\n")
    return path


@pytest.mark.parametrize(
    "comments,header,rows,message",
    [
        ("", None, 2, "expected a comment line '# mode: ...'"),
        ("# mode: pid\n# speed: 3\n", None, 2, r"row 2: expected a comment '# key: value' with a key of"),
        (
            "# mode: pid\n",
            "path_time_s,reference_rad_1",
            2,
            r"row 2: expected the header path_time_s, then .* missing reference_rad_2",
        ),
        ("# mode: pid\n", "+extra", 2, "row 2: expected the header .* got 'extra'"),
        ("# mode: pid\n", None, 1, "expected at least 2 samples, got 1"),
        ("# mode: pid\n", None, "nan", r"row 4: torque_nm_6: expected a finite number, got nan"),
        ("# mode: pid\n", None, "back", r"sample 2: path_time_s: expected no less than the sample before \(0.1 s\)"),
        ("# mode: pid\n", None, "short", "row 3: expected 25 values, got 24"),
        ("# mode: pid\n", None, "still", "path_time_s: expected times that advance, got 0.1 s in every sample"),
    ],
)
def test_a_bad_csv_drive_table_is_refused_in_one_line(tmp_path, comments, header, rows, message):
    from pusupu_jax import drive_table

    names = drive_table.columns(current=False)
    line = ",".join(names) + "," + header[1:] if header and header[0] == "+" else header or ",".join(names)
    values = [[0.1 * (k + 1)] + [0.0] * (len(names) - 1) for k in range(2)]
    if rows == 1:
        values = values[:1]
    if rows == "nan":
        values[1][-1] = float("nan")
    if rows == "back":
        values[1][0] = 0.0
        values[0][0] = 0.1
    if rows == "still":
        values[1][0] = values[0][0]
    text = [",".join(f"{v:g}" for v in row) for row in values]
    if rows == "short":
        text[0] = text[0].rsplit(",", 1)[0]
    bad = _table(tmp_path / "drive.csv", line, text, comments)
    with pytest.raises(ParameterError, match=message) as e:
        drive_table.read(bad)
    assert "\n" not in str(e.value)


@pytest.mark.parametrize(
    "comments, options, expected",
    [
        ("# mode: fancy\n# trajectory: arc\n", (), "{log}: mode: expected one of ('imc', 'pid'"),
        ("# mode: pid\n# trajectory: nowhere\n", (), "{log}: trajectory: expected one of ('arc'"),
        ("# mode: pid\n# trajectory: arc\n", ("--trajectory", "nowhere"), "--trajectory: expected one of ('arc'"),
    ],
)
def test_a_log_of_an_unknown_mode_or_path_is_refused_before_any_progress(
    tmp_path, refused, comments, options, expected
):
    """The log's mode and path are checked as it is read: one line naming the log (or --trajectory), and no line of
    progress (the device, the step check) before it."""
    from pusupu_jax import drive_table

    names = drive_table.columns(current=False)
    rows = [",".join(f"{v:g}" for v in [0.001 * k] + [0.0] * (len(names) - 1)) for k in range(3)]
    log = _table(tmp_path / "drive.csv", ",".join(names), rows, comments)
    line = refused("identify", log, "--out", tmp_path / "m.yaml", *options)
    assert line.startswith("pusupu: error: " + expected.format(log=log)), line
    assert not (tmp_path / "m.yaml").exists()


def _linear(A, b, start):
    """``residual_of`` for ``A p - b`` over the values at ``free`` (the others held at ``start``), as ``fit`` builds
    it for the replay."""

    def residual_of(free):
        def residual(p):
            return jnp.asarray(A) @ jnp.asarray(start).at[free].set(p) - jnp.asarray(b)

        return jax.jit(residual), jax.jit(jax.jacfwd(residual))

    return residual_of


def test_a_value_the_data_do_not_excite_keeps_its_start_and_the_others_are_fitted():
    """Three values, the data see the first and the third only (the second's column is zero): the second keeps its
    start and is reported as not excited; the others are found to the solver's tolerance, with standard errors of
    the data's noise.  With no value excited, every value keeps its start."""
    rng = np.random.default_rng(0)
    A = np.column_stack([rng.normal(size=200), np.zeros(200), rng.normal(size=200)])
    truth, start = np.array([2.0, 5.0, -1.5]), np.array([1.0, 3.0, 0.0])
    b = A @ truth + 1e-3 * rng.normal(size=200)
    low, high = np.full(3, -10.0), np.full(3, 10.0)
    lines = []
    found = least_squares_excited(_linear(A, b, start), start, low, high, lines.append)
    assert found.excited.tolist() == [True, False, True]
    assert found.x[1] == start[1]  # not invented
    np.testing.assert_allclose(found.x[[0, 2]], truth[[0, 2]], atol=5e-4)
    assert np.all(found.std[[0, 2]] < 1e-3)
    assert "identify: 1 value(s) not excited by the logs: fitting the others again" in lines
    none = least_squares_excited(_linear(np.zeros((50, 3)), np.ones(50), start), start, low, high)
    assert not none.excited.any() and none.x.tolist() == start.tolist()


def test_one_gauss_newton_step_from_a_fit_reaches_the_fit_of_a_residual_close_to_it():
    """The step check's move (:func:`machine_fit.gauss_newton_step`): a residual of the same Jacobian but another bias,
    smooth in time (as a finer replay's differs from the replay's), is minimised by the fit's values plus one
    Gauss-Newton step, to rounding; a value the data do not excite (its Jacobian column 0 in the Solution) does not
    move.  Against a change the Jacobian cannot express (white, orthogonal to its columns) the step is 0."""
    rng = np.random.default_rng(1)
    t = np.linspace(0.0, 1.0, 300)
    A = np.column_stack([rng.normal(size=300), np.zeros(300), np.sin(6 * t)])
    start, low, high = np.zeros(3), np.full(3, -10.0), np.full(3, 10.0)
    b = A @ np.array([2.0, 5.0, -1.5]) + 1e-3 * rng.normal(size=300)
    found = least_squares_excited(_linear(A, b, start), start, low, high)
    assert found.excited.tolist() == [True, False, True]
    np.testing.assert_array_equal(found.jacobian[:, 1], 0.0)
    np.testing.assert_allclose(found.jacobian[:, [0, 2]], A[:, [0, 2]], rtol=1e-12)
    bias = 0.05 * np.cos(3 * t) + 0.02 * A[:, 0]  # the finer residual is A x - (b - bias)
    move = machine_fit.gauss_newton_step(found.jacobian, bias)
    other, *_ = np.linalg.lstsq(A[:, [0, 2]], b - bias, rcond=None)
    np.testing.assert_allclose((found.x + move)[[0, 2]], other, rtol=1e-6)
    assert move[1] == 0.0 and abs(move[0] + 0.02) < 5e-3  # mostly the bias's share along the first column
    q, _ = np.linalg.qr(A[:, [0, 2]])
    white = rng.normal(size=300)
    np.testing.assert_allclose(machine_fit.gauss_newton_step(found.jacobian, white - q @ (q.T @ white)), 0, atol=1e-12)


def test_a_step_check_not_finer_than_the_replay_is_refused_in_one_line(tmp_path, refused):
    """``pusupu identify --step-check S``: S must be a step the replay can take, finer than its own (the model's
    0.25 ms, or --mech-step's), or none; another is refused in one line, exit 2, before anything is read (in this
    process: the refusals of --mech-step and --derivatives, in the tests above and below, show a process's one
    line)."""
    machine_fit.check_step_check(5e-5, None)
    for options, expected in (
        (("--step-check", "0.00025"), "--step-check: expected a step finer than the replay's 0.00025 s, got 0.00025 s"),
        (
            ("--mech-step", "0.00005", "--step-check", "0.00005"),
            "--step-check: expected a step finer than the replay's 5e-05 s, got 5e-05 s",
        ),
        (("--step-check", "0.0001"), "--step-check: expected a whole number of current-loop ticks"),
        (("--step-check", "fine"), "--step-check: expected a step in seconds or none, got 'fine'"),
    ):
        line = refused("identify", "x.mcap", "--out", tmp_path / "m.yaml", *options)
        assert line.startswith(f"pusupu: error: {expected}"), line
    assert not (tmp_path / "m.yaml").exists()


def test_the_step_check_is_on_by_default_for_a_robots_logs_and_off_for_the_models_own(tmp_path):
    """``pusupu identify`` without ``--step-check``: a robot's log (a CSV drive table here; a bridge's alike) gets
    the check at one current-loop tick, 50 us; logs that ``pusupu sim`` wrote at the model's step get none, nor
    does a replay that already steps once a tick; one robot log among sim logs turns it on."""
    import dataclasses

    from pusupu_jax import drive_table

    names = drive_table.columns(current=True)
    rows = [",".join(f"{v:g}" for v in [0.001 * (k + 1)] + [0.0] * (len(names) - 1)) for k in range(2)]
    robot = drive_table.read(_table(tmp_path / "drive.csv", ",".join(names), rows))
    sim = dataclasses.replace(robot, source=run_log.SIM_SOURCE)
    assert machine_fit.default_step_check([robot], None).step == 5e-5
    assert machine_fit.default_step_check([robot], 2.5e-4).step == 5e-5
    assert machine_fit.default_step_check([sim, sim], None).step is None
    assert machine_fit.default_step_check([sim, robot], None).step == 5e-5
    assert machine_fit.default_step_check([robot], 5e-5).step is None
    assert "pusupu sim's" in machine_fit.default_step_check([sim], None).why


@pytest.mark.parametrize("rho, textbook_at_most, counted_within", [(0.0, 1.0, (0.92, 0.98)), (0.98, 0.3, (0.78, 1.0))])
def test_intervals_that_count_the_residuals_correlation_in_time_cover_the_truth(rho, textbook_at_most, counted_within):
    """A linear fit of three values to two logs of 1000 samples each (sines and a square wave, as a path's moves)
    with AR(1) noise of ``rho`` a sample, drawn 200 times: the share of 95 % intervals (1.96 standard errors) that
    cover the truth.  With white noise both kinds cover about 95 % (measured 0.948 textbook, 0.955 counted); with 0.98
    a sample, as a model's error is correlated, the textbook ``s^2 (J^T J)^-1`` covers 0.185 and
    :func:`pusupu_jax.fit_errors.covariance` 0.812 (at 0.9: 0.345 and 0.897; at 0.995: 0.13 and 0.79).  A share of
    600 intervals spreads by about 0.02 from draw to draw.  No error is below the textbook one."""
    from scipy.signal import lfilter

    rng = np.random.default_rng(7)
    t = np.linspace(0, 1, 1000)
    X = np.column_stack(
        [np.sin(2 * np.pi * 1.3 * t), np.cos(2 * np.pi * 0.7 * t), np.sign(np.sin(2 * np.pi * 2.1 * t))]
    )
    X = np.concatenate([X, X[::-1]])  # two logs of the same moves
    truth, n, p = np.array([1.0, -0.5, 0.3]), 2000, 3
    samples, logs = np.arange(n), [1000, 1000]
    textbook = counted = 0
    for _ in range(200):
        noise = np.concatenate([lfilter([np.sqrt(1 - rho**2)], [1, -rho], rng.normal(size=1000)) for _ in logs])
        y = X @ truth + 0.1 * noise
        inverse = np.linalg.inv(X.T @ X)
        fitted = inverse @ X.T @ y
        r = X @ fitted - y  # the residual, as the fit has it (model minus data); J = X
        std = np.sqrt(np.diag(inverse) * (r @ r) / (n - p))
        found = fit_errors.covariance(X, r, samples, logs)
        assert found.bandwidth in fit_errors.bandwidths(1000)
        assert np.all(np.sqrt(np.diag(found.covariance)) >= std * (1 - 1e-9))  # never below the textbook errors
        textbook += np.sum(np.abs(fitted - truth) <= 1.96 * std)
        counted += np.sum(np.abs(fitted - truth) <= 1.96 * np.sqrt(np.diag(found.covariance)))
    assert textbook / 600 <= textbook_at_most
    assert counted_within[0] <= counted / 600 <= counted_within[1], (textbook / 600, counted / 600)


def test_the_fit_gives_the_correlations_of_its_values_from_the_jacobian():
    """On ``A p - b`` the Jacobian is ``A``, so the values' covariance is ``s^2 (A^T A)^-1`` exactly: two columns
    nearly alike give values strongly anti-correlated, a third column apart from them hardly correlated.  An
    unexcited value's row is 0 but for its diagonal, and the report names the strongest pair."""
    rng = np.random.default_rng(1)
    x = rng.normal(size=300)
    A = np.column_stack([x, x + 0.2 * rng.normal(size=300), np.zeros(300), rng.normal(size=300)])
    truth, start = np.array([1.0, 2.0, 3.0, -1.0]), np.zeros(4)
    b = A @ truth + 1e-2 * rng.normal(size=300)
    found = least_squares_excited(_linear(A, b, start), start, np.full(4, -10.0), np.full(4, 10.0))
    kept = [0, 1, 3]
    inverse = np.linalg.inv(A[:, kept].T @ A[:, kept])
    expected = inverse / np.sqrt(np.outer(np.diag(inverse), np.diag(inverse)))
    np.testing.assert_allclose(found.correlation[np.ix_(kept, kept)], expected, atol=1e-9)
    assert found.correlation[0, 1] < -0.97 and abs(found.correlation[0, 3]) < 0.2
    np.testing.assert_array_equal(found.correlation[2], [0.0, 0.0, 1.0, 0.0])
    values = tuple(
        machine_fit.FittedValue(FitField.COULOMB, k, 0.0, float(v), float(e), bool(ok))
        for k, (v, e, ok) in enumerate(zip(found.x, found.std, found.excited))
    )
    strongest = machine_fit.strongest_correlations(values, found.correlation)
    assert [(a, b) for a, b, _ in strongest] == [("coulomb[1]", "coulomb[2]")]


@pytest.mark.parametrize(
    "anchor", [machine_fit.Derivatives.FINITE_DIFFERENCES, machine_fit.Derivatives.MUJOCO_MINIMIZE]
)
def test_the_derivative_free_anchors_find_what_the_exact_jacobian_finds_and_count_their_replays(anchor):
    """The derivative-free anchors (scipy's 2-point differences of the residual, and mujoco.minimize on its own
    forward differences, batched) on the linear problem above: the same values, excitation and standard errors as
    the exact Jacobian (to 1e-6: differences of a linear residual are exact up to rounding), never calling the
    Jacobian, and their residual calls count each difference (one per value at each Jacobian, beyond the solver's
    own evaluations).  The trace of the least residual met never rises, and ends at the fit's."""
    rng = np.random.default_rng(0)
    A = np.column_stack([rng.normal(size=200), np.zeros(200), rng.normal(size=200)])
    truth, start = np.array([2.0, 5.0, -1.5]), np.array([1.0, 3.0, 0.0])
    b = A @ truth + 1e-3 * rng.normal(size=200)
    low, high = np.full(3, -10.0), np.array([10.0, np.inf, np.inf])  # open ends, as a mass has
    exact = least_squares_excited(_linear(A, b, start), start, low, high)
    differences = least_squares_excited(_linear(A, b, start), start, low, high, derivatives=anchor)
    assert differences.excited.tolist() == exact.excited.tolist() == [True, False, True]
    np.testing.assert_allclose(differences.x, exact.x, atol=1e-6)
    np.testing.assert_allclose(differences.std, exact.std, rtol=1e-6, atol=1e-12)
    assert differences.jacobian_s == 0.0 and exact.jacobian_s > 0.0
    assert exact.residual_calls == exact.evaluations
    # the first solve's differences take 3 calls a Jacobian, the refit without the unexcited value 2
    assert differences.residual_calls > differences.evaluations + 2 * differences.jacobians
    assert differences.converged and exact.converged
    for solution in (exact, differences):
        best = [rms for _, rms in solution.trace]
        assert all(b <= a for a, b in zip(best, best[1:]))
        end = np.sqrt(np.mean((A @ solution.x - b) ** 2))
        assert best[-1] <= end * (1 + 1e-6)


def test_mujoco_minimize_stops_on_a_step_that_cuts_the_cost_by_less_than_ftol():
    """A residual the model cannot bring below 1e4 (its first entry), which two values move by 1e-2 each: the
    gradient is far above mujoco.minimize's gtol, its first step lands on the values (the residual is linear in
    them), and that step cut the cost by about 1e-11 of it, under FTOL, so the solve ends there, said in its
    message, with the step taken, the end's residual replayed once, and the Jacobian of the iteration's start."""
    calls = []

    def residual(p):
        calls.append(p.copy())
        return np.array([1e4, 1e-2 * (p[0] - 3.0), 1e-2 * (p[1] + 1.0)])

    def differences(points):
        return np.stack([residual(p) for p in points])

    solved = machine_fit._mujoco_minimize(
        residual, differences, np.array([1.0, 1.0]), np.array([-10.0, -10.0]), np.array([10.0, 10.0])
    )
    assert "ftol" in solved.message and solved.converged
    np.testing.assert_allclose(solved.x, [3.0, -1.0], atol=1e-6)
    assert solved.cost == pytest.approx(0.5e8, rel=1e-12)
    np.testing.assert_allclose(solved.jac, [[0.0, 0.0], [1e-2, 0.0], [0.0, 1e-2]], atol=1e-8)
    np.testing.assert_allclose(calls[-1], [3.0, -1.0], atol=1e-6)  # the end replayed
    assert solved.jacobians == 1


def test_the_solver_is_chosen_by_name_and_another_is_refused_in_one_line(tmp_path):
    """``pusupu identify --derivatives`` offers each solver of :class:`machine_fit.Derivatives`; another name is
    refused in one line, exit 2, before anything is read."""
    import argparse

    from pusupu_jax.cli.identify import add_parser

    parser = add_parser(argparse.ArgumentParser().add_subparsers())
    action = next(a for a in parser._actions if a.dest == "derivatives")
    assert sorted(action.choices) == sorted(str(d) for d in machine_fit.Derivatives)
    r = _identify(tmp_path, "--derivatives", "newton")
    assert r.returncode == 2 and len(r.stderr.strip().splitlines()) == 1, r.stderr
    assert "--derivatives" in r.stderr and "'newton'" in r.stderr and "mujoco-minimize" in r.stderr
    assert not (tmp_path / "m.yaml").exists()


@pytest.mark.slow
def test_identify_recovers_every_value_of_the_standard_set_of_a_machine_it_did_not_start_from(tmp_path, in_process):
    """The small case of benchmarks/bench_identify.py, end to end: ``pusupu sim --plant mjx --log`` runs Table 1's
    gains (IMC) along the excitation path (2.5 s) on the machine as built (docs/examples/machine_as_built.yaml:
    per axis its own Coulomb and viscous friction, rotor inertia and torque constant, and a 5 kg payload off centre);
    ``pusupu identify --fit friction,motor,payload --step-check 0.00005`` starts from the machine as designed (the
    built-in drives, 3 kg at the platform centre) and fits the 28 values to the log's first 0.5 s.  The fit finds
    each within 1 % of the truth (a centre-of-mass coordinate: of the truth's distance from the platform centre), and
    the residual falls by more than 1000x.  Four truths are the start's (axis 3's friction and Kt, axis 4's J): those
    the fit must leave where they are.  The log is the fitting model's own, without noise: this checks the fit
    and what the path excites, not the model (the benchmark's bridge cases fit logs of C MuJoCo, with noise).  Then
    the step check: the fitted values replayed at 50 us and moved by what the report says, the finer replay's
    residual lowered, the file written with the moved values and the check in its header.  This log is the replay's
    own at 0.25 ms, so the move goes away from its truth, and over half a second far (measured: the values fitted
    within 1e-11 of the truth, relative; residual RMS 0.1403 -> 4.0e-13 in 9 evaluations; moved up to 21 % of
    viscous friction and the payload's mass, 28 % of the centre of mass's distance, for a finer residual 6 % lower,
    docs/identify.md); the moved values' standard errors take in the check's own error, a share of the move."""
    import json

    from pusupu_jax import machine_file
    from pusupu_jax.experiments import real2sim

    examples = Path(__file__).resolve().parent.parent / "docs" / "examples"
    truth = machine_file.load(examples / "machine_as_built.yaml")
    gain_file = real2sim.table1_gain_file(tmp_path)
    sim = ("sim", "--plant", "mjx", "--machine", examples / "machine_as_built.yaml", "--gains", gain_file)
    in_process(*sim, "--trajectory", "excite", "--log", tmp_path / "run.mcap")
    out = tmp_path / "identified.yaml"
    fit = ("--machine", examples / "machine_as_designed.yaml", "--gains", gain_file, "--fit", "friction,motor,payload")
    fit += ("--window", "0.5", "--step-check", "0.00005", "--out", out)
    report = json.loads(in_process("identify", tmp_path / "run.mcap", *fit, "--json"))
    fields = [machine_fit.FitField(v["field"]) for v in report["values"]]
    steps = np.array([v["step_correction"] for v in report["values"]])
    assert len(fields) == 28 and set(fields) == set(machine_fit.FitField)
    assert all(v["excited"] for v in report["values"])
    written = machine_file.load(out)
    for v, field, step in zip(report["values"], fields, steps):
        found = machine_fit.FittedValue(field, v["index"], v["start"], v["value"] - step, v["std_error"], True)
        checked = machine_fit.FittedValue(field, v["index"], v["start"], v["value"], v["std_error"], True)
        assert found.against(truth)["relative_error"] < 0.01, (v["name"], found.against(truth))
        # the check's move away from this log's own step, and not without bound (measured: at most 0.28)
        assert abs(found.against(truth)["error"]) < abs(checked.against(truth)["error"]), v["name"]
        assert checked.against(truth)["relative_error"] < 0.5, (v["name"], checked.against(truth))
        assert field.start(written)[v["index"]] == v["value"], v["name"]  # the file holds the moved values
    assert report["residual_rms_after"] < 1e-3 * report["residual_rms_before"]
    at_fit, moved = report["step_check_rms"]
    assert report["step_check_s"] == 5e-5 and moved < at_fit and report["step_check_moved"] and np.all(steps != 0)
    # the moved values' standard errors hold the check's own error, a share of each move (beside the finer fit's)
    errors = np.array([v["std_error"] for v in report["values"]])
    assert np.all(errors >= machine_fit.STEP_CHECK_ERROR * np.abs(steps) * (1 - 1e-9))
    assert "#   step check at 50 us: that replay's residual RMS" in out.read_text()


@pytest.mark.slow
def test_identify_recovers_the_standard_set_from_a_bridge_log_of_a_finer_robot(tmp_path, in_process):
    """No inverse crime: the log is not the fitting model's.  ``pusupu bridge --log`` runs Table 1's gains along the
    excitation path for 1 s, over UDP on loopback in lock step, against ``pusupu sim-robot --machine
    machine_as_built.yaml --fine-steps 4`` (C MuJoCo, its mechanism stepped four times per current-loop tick, its
    drives' loops in the robot); ``pusupu identify`` fits the 28 values of the standard set to the log's first 0.5 s
    from the machine as designed, with the step check a robot's log gets by default (50 us).  The small case of the
    benchmark's ``bridge_fine4_noise20_step_check`` (its noise-free log of 2 s: every value within 0.75 %).

    Measured on the 2-core CPU: residual RMS 0.144 -> 0.0108, the finer replay's 0.0042 -> 0.0015; Coulomb friction,
    rotor inertia and torque constant within 0.49 % of the truth, viscous friction within 3.4 %, the payload's mass
    2.5 % and its centre of mass 4.5 % of its distance from the platform centre (2.8 mm), all 28 intervals covering
    the truth at 0.16 of their half-width or less.  Half a second excites the viscous friction and the payload less
    than the benchmark's 2 s: the bounds are 1 % for the first three and 6 % for the others, about 1.3x the worst
    measured; every 95 % interval must cover its truth."""
    import json

    from pusupu_jax import machine_file
    from pusupu_jax.experiments import real2sim
    from pusupu_jax.sim_robot.lockstep import bridge_run

    examples = Path(__file__).resolve().parent.parent / "docs" / "examples"
    truth = machine_file.load(examples / "machine_as_built.yaml")
    gain_file = real2sim.table1_gain_file(tmp_path)
    log = tmp_path / "robot.mcap"
    run = bridge_run(gain_file, "excite", examples / "machine_as_built.yaml", seconds=1.0, fine_steps=4, log=log)
    assert run["ended"] == "completed" and not run["faults"], run
    fit = ("--machine", examples / "machine_as_designed.yaml", "--gains", gain_file, "--fit", "friction,motor,payload")
    report = json.loads(in_process("identify", log, *fit, "--window", "0.5", "--out", tmp_path / "m.yaml", "--json"))
    assert report["step_check_s"] == 5e-5 and report["step_check_moved"]  # a robot's log: the check by default
    assert report["residual_rms_after"] < 0.1 * report["residual_rms_before"]
    at_fit, moved = report["step_check_rms"]
    assert moved < 0.5 * at_fit
    tight = {machine_fit.FitField.COULOMB, machine_fit.FitField.INERTIA, machine_fit.FitField.TORQUE_CONSTANT}
    assert len(report["values"]) == 28
    for v in report["values"]:
        field = machine_fit.FitField(v["field"])
        found = machine_fit.FittedValue(field, v["index"], v["start"], v["value"], v["std_error"], v["excited"])
        against = found.against(truth)
        assert v["excited"] and against["covered_95"], (v["name"], against)
        assert against["relative_error"] < (0.01 if field in tight else 0.06), (v["name"], against)


def _timed_log(timing, samples=8):
    """A log of the first ``samples`` of eight samples along the excitation path whose ``timing`` is given."""
    rows = np.array([0, 1, 2, 4, 5, 8, 9, 10])[:samples]
    zero = np.zeros((len(rows), 6))
    return run_log.DriveLog(
        "run.mcap", "0" * 64, "bridge", None, "imc", "excite", 1000.0, rows * 1e-3, zero, zero, zero, zero, zero,
        timing=timing,
    )  # fmt: skip


def test_a_bridge_logs_commands_are_replayed_as_the_robot_ran_them():
    """The replay of a bridge log over UDP follows its cycles as the log says they went.  Commands 10-18 of rows
    -1 (the takeover ramp's last) to 9: the robot found commands 13 and 14 waiting and ran 14; the bridge skipped
    the cycles of rows 5 and 6; command 16 was computed from the packet of the period before the last (feedback
    103, the answer to 14, when 15 had run).  The replay's steps are the path's commands: rows 0-4 and 7-9, 13 not
    run, 16 reading encoders one period old; each sample is the start of the step after the command it answers (the
    answer to the takeover's last command, the replay's start).  A last command no sample answers is replayed as run
    (no sample depends on it).  Without timing, and where several commands share a row (CST axes), every row in
    turn."""
    sequence = np.arange(10, 19)
    timing = run_log.BridgeTiming(
        path_time=np.array([-1, 0, 1, 2, 3, 4, 7, 8, 9]) * 1e-3,
        sequence=sequence,
        feedback=np.array([0, 100, 101, 102, 102, 103, 103, 105, 106]),
        sample_sequence=np.arange(100, 108),
        sample_ack=np.array([10, 11, 12, 14, 15, 16, 17, 18]),
    )
    log = _timed_log(timing)
    row = np.rint(log.path_time * 1e3).astype(int)
    steps = machine_fit.bridge_commands(log, row, 1e-3, 10)
    assert steps.timed
    assert steps.rows.tolist() == [0, 1, 2, 3, 4, 7, 8, 9]
    assert steps.taken.tolist() == [True, True, False, True, True, True, True, True]
    assert steps.age.tolist() == [0, 0, 0, 0, 0, 1, 0, 0]
    assert steps.index.tolist() == [0, 1, 2, 4, 5, 6, 7, 8]
    assert steps.counts() == {"commands": 8, "not_run": 1, "older_feedback": 1, "rows_stepped_over": 2}
    assert machine_fit.bridge_commands(log, row, 1e-3, 5).rows.tolist() == [0, 1, 2, 3, 4]  # the window's commands
    unanswered = dataclasses.replace(timing, sample_sequence=np.arange(100, 107), sample_ack=timing.sample_ack[:-1])
    last = machine_fit.bridge_commands(_timed_log(unanswered, 7), row[:-1], 1e-3, 10)
    assert last.rows.tolist() == steps.rows.tolist() and last.taken.tolist() == steps.taken.tolist()
    for plain in (
        dataclasses.replace(log, timing=None),
        _timed_log(dataclasses.replace(timing, path_time=timing.path_time // 2e-3 * 1e-3)),
    ):
        every = machine_fit.bridge_commands(plain, row, 1e-3, 10)
        assert not every.timed and every.rows.tolist() == list(range(10)) and every.index.tolist() == row.tolist()
        assert every.counts() is None


def test_a_commanded_reference_runs_the_robots_periods_and_reads_the_encoders_the_bridge_had():
    """:class:`~pusupu_jax.sim.Commanded` on the single-axis plant, 40 position periods of a cosine: every command
    run, on the present encoders, is the plain rollout to the bit.  A command not run leaves the machine, the drives
    and their loops where they were (the next step starts where it started) while the position loop steps; one that
    reads the encoders a period old computes another command than on the present ones, and the commands before it are
    the same."""
    from pusupu_jax import AxisLoad
    from pusupu_jax.sim import Commanded, rollout

    n = 40
    ref = jnp.asarray(np.repeat((2.0 * (1 - np.cos(np.linspace(0, np.pi, n))))[:, None], 6, axis=1))
    run = jax.jit(lambda r: rollout(ServoParams.table1(), AxisLoad.default(), r, outer="imc"))
    plain = run(ref)
    taken, age = np.ones(n, bool), np.zeros(n, np.int32)
    same = run(Commanded(ref, jnp.asarray(taken), jnp.asarray(age)))
    for a, b in zip(jax.tree.leaves(plain), jax.tree.leaves(same)):
        assert np.array_equal(a, b)
    taken[20], age[30] = False, 1
    timed = run(Commanded(ref, jnp.asarray(taken), jnp.asarray(age)))
    for field in ("theta", "omega", "current"):
        x = np.asarray(getattr(timed, field))
        assert np.array_equal(x[21], x[20]) and not np.array_equal(x[20], x[19])  # no period under command 20
    s = jax.tree.leaves(timed.state.position)
    assert any(not np.array_equal(np.asarray(x)[21], np.asarray(x)[20]) for x in s)  # its position loop stepped
    stale = np.asarray(timed.command)[30]
    again = np.asarray(
        run(Commanded(ref, jnp.asarray(taken), jnp.asarray(np.where(np.arange(n) == 30, 0, age)))).command
    )
    assert not np.allclose(stale, again[30])
    assert np.array_equal(np.asarray(timed.command)[:30], again[:30])
