"""Shared set-up: float64, JAX's persistent compilation cache (in .jax_cache/ unless PUSUPU_JAX_CACHE is set), and
XLA's backend (LLVM) optimisation level 0 for every program the suite compiles, in this process and in the commands
it runs.

The suite compiles some hundred MJX programs from an empty cache, and compiling is most of its time. At level 0 the
same programs (XLA's own passes unchanged, LLVM's optimisation off) compile faster, and the suite's short runs
hardly feel the slower code; on the 2-core CPU, from an empty cache: a gradient check through the cosimulation 70 ->
55 s, the quick arc experiment 64 -> 53 s; the whole suite, a clean clone as CI runs it, 41 min 21 s at level 3
against 36 min 35 s at 0 (75 against 65 min of CPU). The suite passes at both levels. A user's programs keep XLA's
default (3); to run the suite at it, set ``XLA_FLAGS=--xla_backend_optimization_level=3`` (a level set there is
kept)."""

import os

if "--xla_backend_optimization_level" not in os.environ.get("XLA_FLAGS", ""):  # before JAX starts its backend
    os.environ["XLA_FLAGS"] = f"{os.environ.get('XLA_FLAGS', '')} --xla_backend_optimization_level=0".strip()

from pathlib import Path  # noqa: E402

import pytest  # noqa: E402

from pusupu_jax.runtime import setup_jax  # noqa: E402

CACHE = setup_jax(os.environ.get("PUSUPU_JAX_CACHE") or Path(__file__).resolve().parent.parent / ".jax_cache")
os.environ["PUSUPU_JAX_CACHE"] = str(CACHE)  # the CLI subprocesses share it


@pytest.fixture(scope="session")
def table1():
    from pusupu_jax import ServoParams

    return ServoParams.table1()


@pytest.fixture(scope="session")
def linear_load():
    """The default single-axis load (mass, no gravity along a level rail): linear."""
    from pusupu_jax import AxisLoad

    return AxisLoad.default()


@pytest.fixture(scope="session")
def table1_linear():
    """Table 1 without the drive train's Coulomb friction: the plant is then linear, so python-control models it
    exactly."""
    import numpy as np

    from pusupu_jax import ServoParams

    return ServoParams.table1().replace(coulomb=np.zeros(6))
