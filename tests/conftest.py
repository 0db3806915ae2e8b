"""Shared set-up: float64 and JAX's persistent compilation cache (in .jax_cache/ unless PUSUPU_JAX_CACHE is set)."""

import os
from pathlib import Path

import pytest

from pusupu_jax.runtime import setup_jax

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
