"""``pusupu identify``'s inputs: the names of the fields to fit, and a file that is not a run log.  The fit itself
runs on the log of ``tests/test_paths.py``'s pose table (``test_identify_finds_the_friction_of_the_machine_that_ran``:
it shares that run)."""

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
