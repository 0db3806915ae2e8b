"""Where the work runs: one host device per CPU core, a batch's rows laid over them, and a GPU refused where there is
none.  That the tuner's gradient is the same to rounding whether its windows are laid over one device or several is
checked in tests/test_batch.py, on a job's own problem, whose program that file compiles already."""

import jax
import pytest

from pusupu_jax import devices, runtime

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


def test_a_gpu_jobs_forward_passes_run_on_the_hosts_cpu_while_its_paths_are_no_more_than_its_cores(monkeypatch):
    """On the CPU every forward pass stays there; where the job computes on a GPU, the host's CPU devices take a
    forward pass of at most one path a device (the GPU a wider one), and the problem's set-up.  (tests/test_batch.py
    runs a job's forward pass so, and checks its start states.)"""
    cpus = jax.devices("cpu")
    assert devices.forward_pass_devices(10 * len(cpus)) == devices.chosen_devices()
    default = jax.config.jax_default_device
    with devices.set_up_device():
        assert jax.config.jax_default_device == default

    class Gpu:
        platform = "gpu"

    gpu = Gpu()
    monkeypatch.setattr(devices, "chosen_devices", lambda: [gpu])
    assert devices.forward_pass_devices(1) == devices.forward_pass_devices(len(cpus)) == cpus
    assert devices.forward_pass_devices(len(cpus) + 1) == [gpu]
    # so does the problem's set-up: what it computes under set_up_device lands on the host's first CPU device
    with devices.set_up_device():
        assert jax.config.jax_default_device == cpus[0]
