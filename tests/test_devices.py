"""Where the work runs: one host device per CPU core, a batch's rows laid over them, and the tuner's gradient the same
to rounding whether its windows are laid over one device or several."""

import jax
import numpy as np
import pytest

from pusupu_jax import devices, runtime
from pusupu_jax.hybrid import HybridGains
from pusupu_jax.params import ServoParams
from pusupu_jax.tune import run
from pusupu_jax.tune.config import TuneConfig

several = pytest.mark.skipif(len(jax.devices()) < 2, reason="one CPU: one host device")


def test_the_package_makes_one_host_device_per_cpu_it_may_run_on():
    assert len(jax.devices("cpu")) == runtime.cpu_count()


@several
def test_rows_are_laid_over_the_most_devices_that_divide_them():
    two = jax.devices()[:2]
    assert devices.row_mesh(12, two).size == 2
    assert devices.row_mesh(7, two) is None  # 7 rows do not split over two devices: one runs them all
    assert devices.row_mesh(12, two[:1]) is None


def test_asking_for_a_gpu_where_there_is_none_is_refused():
    if devices.runtime.gpu_plugin_installed() and devices.gpu_available():
        pytest.skip("this machine has a GPU")
    with pytest.raises(devices.ParameterError, match="--device gpu: expected a GPU"):
        devices.select("gpu", 12)


@several
@pytest.mark.slow
def test_the_gradient_over_windows_laid_over_devices_is_the_gradient_on_one(monkeypatch):
    """The quick configuration's two windows (in IMC mode, whose program is smaller than hybrid's), laid over two
    devices and run on one: value and gradient agree to 1e-12 relative.  Not bit for bit: the gradient's sum over
    the windows is then an all-reduce across devices, in another order than one device's sum."""
    cfg = TuneConfig.quick().replace(path_s=0.4, window_s=0.1, mode="imc", groups=("imc", "velocity"))
    spread = run.Problem(cfg, ServoParams.table1(), HybridGains())
    assert spread.mesh is not None and spread.mesh.size == 2
    monkeypatch.setattr(run.devices, "row_mesh", lambda rows: None)
    alone = run.Problem(cfg, ServoParams.table1(), HybridGains())
    assert alone.mesh is None and alone._value_and_grad is not spread._value_and_grad
    z = spread.z0()
    (v1, _), g1 = spread.value_and_grad(z)
    (v2, _), g2 = alone.value_and_grad(z)
    assert float(v1) == pytest.approx(float(v2), rel=1e-12)
    for k in g1:
        np.testing.assert_allclose(np.asarray(g1[k]), np.asarray(g2[k]), rtol=1e-10, atol=1e-14)
