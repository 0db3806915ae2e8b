"""pusupu_jax: differentiable servo cascade and plants of the 6PUS-UPU parallel manipulator.

Public API::

    from pusupu_jax import ServoParams, AxisLoad, LoopRates, simulate, rollout
    trace = simulate(ServoParams.table1(), reference_m, mode="imc")
"""

from .params import AxisLoad, LoopRates, ParameterError, ServoParams, validate
from .sim import Trace, rollout, simulate

__version__ = "0.1.0"

__all__ = ["AxisLoad", "LoopRates", "ParameterError", "ServoParams", "Trace", "rollout", "simulate",
           "validate", "__version__"]
