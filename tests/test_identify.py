"""``pusupu identify``'s inputs: the names of the fields to fit, and a file that is not a run log.  The fit itself is
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
