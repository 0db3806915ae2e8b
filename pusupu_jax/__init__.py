"""pusupu_jax: differentiable servo cascade and plants of the 6PUS-UPU parallel manipulator.

Public API::

    from pusupu_jax import ServoParams, AxisLoad, LoopRates, simulate, rollout
    trace = simulate(ServoParams.table1(), reference_m, mode="imc")
"""

from .runtime import apply_xla_workaround, limit_blas_threads

apply_xla_workaround()  # before JAX's CPU backend starts: see runtime.XLA_CPU_WORKAROUND
limit_blas_threads()  # before numpy loads OpenBLAS: see runtime.BLAS_THREADS

from .params import AxisLoad, LoopRates, ParameterError, ServoParams, validate  # noqa: E402
from .sim import rollout, simulate  # noqa: E402
from .trace import Trace  # noqa: E402

__version__ = "0.1.0"

__all__ = [
    "AxisLoad",
    "LoopRates",
    "ParameterError",
    "ServoParams",
    "Trace",
    "rollout",
    "simulate",
    "validate",
    "__version__",
]
