"""Gradients of a scalar objective in reverse or forward mode, with one signature (JAX).

``value_and_grad(fun, mode)(x, *args) -> ((value, aux), grad)``, as
``jax.value_and_grad(fun, has_aux=True)``, for ``fun(x, *args) -> (value, aux)`` with ``x`` a
pytree of arrays (the gradient has its structure):

* ``reverse``: ``jax.value_and_grad``.  Its cost does not depend on the number of parameters
  ``n`` (5.7-10x a forward run through the MJX machine, measured; 4.8-8.5x for the MJX steps
  alone), but the backward pass needs the forward pass's intermediates of every step: memory
  grows with the horizon (``rollout(remat=True)`` trades some of it for one more forward pass).
* ``forward``: ``jax.jacfwd``: one tangent per parameter, pushed through the rollout beside
  the primal and vmapped over the ``n`` tangents.  Memory does not grow with the horizon and
  the cost is about ``1 + c n`` forward runs: measured, it beats reverse mode for two
  parameters on the CPU and for up to seven on a GPU at batch 1024, and loses for more.

Both give the same gradient to rounding (tested); ``benchmarks/bench_cosim.py`` measures
their cost against the forward run.
"""

from __future__ import annotations

from typing import Any, Callable

import jax
from jax.flatten_util import ravel_pytree

GRADIENT_MODES = ("reverse", "forward")


def value_and_grad(
    fun: Callable[..., tuple[Any, Any]], mode: str = "reverse"
) -> Callable[..., tuple[tuple[Any, Any], Any]]:
    """``(x, *args) -> ((value, aux), d value / d x)`` for ``fun(x, *args) -> (value, aux)``; not jitted."""
    if mode == "reverse":
        return jax.value_and_grad(fun, has_aux=True)
    if mode != "forward":
        raise ValueError(f"gradient mode: expected one of {GRADIENT_MODES}, got {mode!r}")

    def forward(x: Any, *args: Any) -> tuple[tuple[Any, Any], Any]:
        flat, unravel = ravel_pytree(x)

        def flat_fun(v: jax.Array) -> tuple[Any, tuple[Any, Any]]:
            value, aux = fun(unravel(v), *args)
            return value, (value, aux)

        grad, (value, aux) = jax.jacfwd(flat_fun, has_aux=True)(flat)
        return (value, aux), unravel(grad)

    return forward
