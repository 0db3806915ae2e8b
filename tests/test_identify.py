"""``pusupu identify``'s inputs: the names of the fields to fit, a file that is not a run log, and CSV drive tables
that do not follow their layout (one that does is read in tests/test_paths.py, against its MCAP log).  The fit itself is
not run by the suite: from an empty compile cache, its replay and Jacobian compile for minutes on 2 cores
(docs/identify.md has the measured fits)."""

import pytest

from pusupu_jax import ParameterError, run_log
from pusupu_jax.machine_fit import FitField, fit_fields


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
    text = [",".join(f"{v:g}" for v in row) for row in values]
    if rows == "short":
        text[0] = text[0].rsplit(",", 1)[0]
    bad = _table(tmp_path / "drive.csv", line, text, comments)
    with pytest.raises(ParameterError, match=message) as e:
        drive_table.read(bad)
    assert "\n" not in str(e.value)
