"""Parameter validation, parameter files and batched (vmapped) runs."""

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from pusupu_jax import AxisLoad, LoopRates, ParameterError, ServoParams, simulate, validate
from pusupu_jax.params_file import load_params_file
from pusupu_jax.hybrid import HybridGains
from pusupu_jax.params import stack

POSITIVE = [n for n, f in ServoParams.__dataclass_fields__.items() if f.metadata["kind"] == "positive"]


@settings(max_examples=40, deadline=None)
@given(
    name=st.sampled_from(POSITIVE),
    value=st.sampled_from([0.0, -1.0, -1e-9, math.nan, math.inf]),
    axis=st.integers(0, 5),
)
def test_bad_values_name_the_field_and_axis(table1, name, value, axis):
    v = np.array(getattr(table1, name), dtype=float)
    v[axis] = value
    with pytest.raises(ParameterError, match=rf"ServoParams\.{name}: expected .* at axis {axis}"):
        validate(table1.replace(**{name: v}))


def test_wrong_shapes_and_unknown_keys(table1):
    with pytest.raises(ParameterError, match=r"ServoParams\.Kv: expected shape \(\.\.\., 6\).*got \(5,\)"):
        validate(table1.replace(Kv=np.ones(5)))
    with pytest.raises(ParameterError, match=r"ServoParams\.Tv: expected shape \(6,\) like the other fields"):
        validate(table1.replace(Tv=np.ones((2, 6))))
    with pytest.raises(ParameterError, match="unknown field 'Kx'"):
        ServoParams.from_mapping({"Kx": 1.0})
    with pytest.raises(ParameterError, match="AxisLoad.mass: expected a positive"):
        AxisLoad.from_mapping({"mass": 0})
    with pytest.raises(ParameterError, match=r"eta: expected 0.001 to 1 \[1\] \(an efficiency: at most 1\)"):
        ServoParams.from_mapping({"eta": 1.2})
    with pytest.raises(ParameterError, match="rates.n_mech: expected a divisor"):
        LoopRates(n_velocity=5, n_mech=2)


def test_simulate_rejects_bad_input_before_running(table1):
    with pytest.raises(ParameterError, match="ServoParams.lambda2"):
        simulate(table1.replace(lambda2=-table1.lambda2), np.zeros(10))
    with pytest.raises(ParameterError, match=r"reference: expected slider positions of shape"):
        simulate(table1, np.zeros((10, 5)))
    with pytest.raises(ParameterError, match="reference: expected finite"):
        simulate(table1, np.full(10, np.nan))
    with pytest.raises(ParameterError, match="mode: expected one of"):
        simulate(table1, np.zeros(10), mode="lqr")


def test_parameter_file_round_trip_and_errors(tmp_path):
    good = tmp_path / "p.yaml"
    good.write_text(
        "servo: {lambda1: 0.02, Kv: [0.01, 0.02, 0.03, 0.04, 0.05, 0.06]}\n"
        "load: {mass: 30}\nrates: {f_current: 10000, n_velocity: 4}\nhybrid: {g: 20.0, form: rms}\n"
    )
    servo, load, rates, hybrid = load_params_file(good)
    assert hybrid.g == 20.0 and hybrid.form == "rms" and hybrid.c6 == HybridGains().c6
    assert np.allclose(servo.lambda1, 0.02) and np.allclose(servo.Kv, [0.01, 0.02, 0.03, 0.04, 0.05, 0.06])
    assert np.allclose(load.mass, 30) and rates == LoopRates(f_current=10000.0, n_velocity=4)
    cases = {
        "servo: {Ti: .nan}": "ServoParams.Ti: expected a number, got nan",
        "servo: {Kv: [1, 2]}": r"ServoParams.Kv: expected a number or a list of 6 numbers .*got a list of 2",
        "servo: {Kv: fast}": "ServoParams.Kv: expected a number",
        "gains: {}": "unknown section 'gains'",
        "hybrid: {m6: -1}": "HybridGains.m6: expected a number from 0 to 70000",
        "rates: {f_current: -5}": "rates.f_current: expected a number > 0",
        "servo: {lambda1: [0.1,": "not valid YAML",
        "- 1\n- 2": "expected a mapping",
    }
    for text, message in cases.items():
        bad = tmp_path / "bad.yaml"
        bad.write_text(text)
        with pytest.raises(ParameterError, match=message):
            load_params_file(bad)
    with pytest.raises(ParameterError, match="cannot read"):
        load_params_file(tmp_path / "missing.yaml")


def test_vmapped_batch_equals_single_runs(table1):
    ref = np.linspace(0, 0.002, 50)
    sets = [table1.replace(Kv=table1.Kv * f, lambda1=table1.lambda1 * f) for f in (0.8, 1.0, 1.3)]
    batch = simulate(stack(sets), ref)
    assert batch.position.shape == (3, 50, 6)
    for k, p in enumerate(sets):
        single = simulate(p, ref)
        np.testing.assert_allclose(batch.position[k], single.position, rtol=1e-10, atol=1e-15)
    assert not np.allclose(batch.position[0], batch.position[2])


def test_large_vmapped_batch_completes():
    """1024 parameter sets vmapped: without runtime.XLA_CPU_WORKAROUND this wedged XLA's CPU thread pool."""
    import subprocess
    import sys

    code = (
        "import numpy as np, jax; from pusupu_jax import ServoParams, simulate; from pusupu_jax.params import stack;"
        "p = ServoParams.table1(); ps = stack([p.replace(Kv=p.Kv * f) for f in np.linspace(0.8, 1.2, 1024)]);"
        "[jax.block_until_ready(simulate(ps, np.zeros(5))) for _ in range(2)]; print('ok')"
    )
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert r.stdout.strip() == "ok", r.stderr[-2000:]


def test_importing_the_package_sets_the_xla_flags_and_keeps_the_users(tmp_path):
    """On import: the thread-pool workaround and the CPU compile flags are added to XLA_FLAGS; a flag the user set
    keeps the user's value; the LLVM flag is left out when a GPU plugin for jax is installed (a package in the
    ``jax_plugins`` namespace, made here as an empty one); ``PUSUPU_XLA_WORKAROUND=0`` leaves XLA_FLAGS alone; with
    a jaxlib of a series the compile flags were not measured on, only the workaround is added (the compile flags'
    checks run where the installed jaxlib is of the measured series, as CI's is); the single-threaded CPU flag only
    when asked for (pusupu bridge, pusupu sim-robot), which also take out the one host device per CPU the import added
    (a count the user set stays)."""
    import os
    import subprocess
    import sys

    from pusupu_jax import runtime

    def flags(extra_env, path=None, then=""):
        env = {k: v for k, v in os.environ.items() if k != "PUSUPU_XLA_WORKAROUND"}
        env.update({"XLA_FLAGS": "--xla_cpu_use_fusion_emitters=true", **extra_env})
        if path:
            env["PYTHONPATH"] = os.pathsep.join([str(path), env.get("PYTHONPATH", "")])
        code = f"import os, pusupu_jax; {then or 'pass'}; print(os.environ['XLA_FLAGS'])"
        r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, timeout=120)
        assert r.returncode == 0, r.stderr[-2000:]
        return r.stdout.split()

    plain = flags({})
    assert plain.count("--xla_cpu_use_fusion_emitters=true") == 1 and "--xla_cpu_use_fusion_emitters=false" not in plain
    assert runtime.XLA_CPU_WORKAROUND in plain
    assert not set(runtime.XLA_CPU_ONE_THREAD) & set(plain)  # for the real-time processes only
    host_devices = f"{runtime.XLA_HOST_DEVICES}={runtime.cpu_count()}"
    assert host_devices in plain
    one_cpu = flags({}, then="pusupu_jax.runtime.apply_xla_workaround(one_thread=True)")
    assert not [f for f in one_cpu if f.startswith(runtime.XLA_HOST_DEVICES)]
    users = flags({"XLA_FLAGS": f"{runtime.XLA_HOST_DEVICES}=3"}, then="pusupu_jax.runtime.apply_xla_workaround(True)")
    assert [f for f in users if f.startswith(runtime.XLA_HOST_DEVICES)] == [f"{runtime.XLA_HOST_DEVICES}=3"]
    if runtime._jaxlib_version().startswith(runtime.XLA_COMPILE_MEASURED_ON):  # the jaxlib installed here (CI's: 0.10)
        assert set(runtime.XLA_LLVM_CPU_ONLY) <= set(plain)
        real_time = flags({}, then="pusupu_jax.runtime.apply_xla_workaround(one_thread=True)")
        assert set(runtime.XLA_CPU_ONE_THREAD) <= set(real_time) and len(real_time) == len(set(real_time))
        (tmp_path / "jax_plugins" / "xla_gpu_stand_in").mkdir(parents=True)
        (tmp_path / "jax_plugins" / "xla_gpu_stand_in" / "__init__.py").write_text("")
        assert not set(runtime.XLA_LLVM_CPU_ONLY) & set(flags({}, tmp_path))
    assert flags({"PUSUPU_XLA_WORKAROUND": "0"}) == ["--xla_cpu_use_fusion_emitters=true"]
    # a jaxlib of another series (its metadata found first on the path): the compile flags, which such a jaxlib may
    # not know (0.11.2 aborts on the fusion-emitter flag), are left out
    other = tmp_path / "other" / "jaxlib-0.11.2.dist-info"
    other.mkdir(parents=True)
    (other / "METADATA").write_text("Metadata-Version: 2.1\nName: jaxlib\nVersion: 0.11.2\n")
    assert flags({}, other.parent) == ["--xla_cpu_use_fusion_emitters=true", host_devices, runtime.XLA_CPU_WORKAROUND]


def test_importing_the_package_first_gives_numpy_one_blas_thread_and_keeps_the_users_count():
    """``import pusupu_jax`` before numpy sets OpenBLAS to one thread (runtime.BLAS_THREADS: its spinning threads cost
    `pusupu identify` 5x its time beside two busy processes); a count the user set stays.  Where numpy's wheel bundles
    scipy-openblas, the library itself is asked how many threads it runs (else the environment is checked alone)."""
    import os
    import subprocess
    import sys

    from pusupu_jax import runtime

    code = """
import ctypes, glob, os, pusupu_jax, numpy
found = glob.glob(os.path.join(os.path.dirname(numpy.__file__), os.pardir, "numpy.libs", "*scipy_openblas64*"))
ask = getattr(ctypes.CDLL(found[0]), "scipy_openblas_get_num_threads64_", None) if found else None
print(os.environ[pusupu_jax.runtime.BLAS_THREADS], ask() if ask else "")
"""

    def threads(extra_env):
        env = {k: v for k, v in os.environ.items() if k != runtime.BLAS_THREADS} | extra_env
        r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, timeout=120)
        assert r.returncode == 0, r.stderr[-2000:]
        return r.stdout.split()

    ours = threads({})
    assert ours[0] == "1" and ours[1:] in ([], ["1"])
    users = threads({runtime.BLAS_THREADS: "2"})
    assert users[0] == "2" and users[1:] in ([], [str(min(2, runtime.cpu_count()))])


def test_importing_the_packages_makes_no_jax_array():
    """No module makes a JAX array on import (fresh interpreter, float64 off as JAX starts).  Such an array takes
    the float width in force on import: margins' frequency grid was float32 in every process that imported the
    package before enabling float64 (the CLI, Ray's workers), so their programs differed from this suite's."""
    import json
    import os
    import subprocess
    import sys

    code = """
import importlib, json, pkgutil
import jax
names = []
for package in ("pusupu_jax", "pusupu_jax.tune", "pusupu_jax.hw_bridge", "pusupu_jax.sim_robot",
                "pusupu_jax.experiments", "pusupu_jax.cli"):
    root = importlib.import_module(package)
    names += [package] + [m.name for m in pkgutil.walk_packages(root.__path__, package + ".")
                          if not m.name.endswith("__main__")]
named = []
for name in names:
    module = importlib.import_module(name)
    named += [f"{name}.{k}" for k, v in vars(module).items() if isinstance(v, jax.Array)]
print(json.dumps({"modules": names, "named": named, "live": len(jax.live_arrays()), "x64": jax.config.jax_enable_x64}))
"""
    env = {k: v for k, v in os.environ.items() if k != "JAX_ENABLE_X64"}
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=600, env=env)
    assert r.returncode == 0, r.stderr[-2000:]
    out = json.loads(r.stdout.strip().splitlines()[-1])
    assert {
        "pusupu_jax.margins",
        "pusupu_jax.plant.mjx_plant",
        "pusupu_jax.tune.batch",
        "pusupu_jax.hw_bridge.loop",
    } <= set(out["modules"])
    assert out["named"] == [] and out["live"] == 0 and out["x64"] is False, out
