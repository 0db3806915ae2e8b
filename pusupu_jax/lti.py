"""Linear time-invariant blocks in JAX: state-space form, discretisation, stepping.

Every filter and controller of the cascade is a continuous transfer function of the
parameters, turned into a state-space block (:func:`tf`), discretised once per
rollout (:func:`c2d`, outside the scan) and stepped inside the scan
(:func:`output`, :func:`update`).  Matrices carry leading batch dimensions (one block
per axis, and more under vmap): ``A (..., n, n)``, ``B (..., n, m)``,
``C (..., p, n)``, ``D (..., p, m)``.

The discretisations are those of python-control's ``sample`` (scipy's
``cont2discrete``): 'zoh' (exact for inputs held over the step) and 'tustin'
(bilinear), so the tests can compare the scan with python-control to rounding error.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import jax
import jax.numpy as jnp
from jax.scipy.linalg import expm


@jax.tree_util.register_dataclass
@dataclass(frozen=True)
class LTI:
    """State-space block ``x' = A x + B u, y = C x + D u`` (continuous or discrete)."""

    A: Any
    B: Any
    C: Any
    D: Any


def tf(num, den) -> LTI:
    """SISO transfer function ``num(s)/den(s)`` in controllable canonical form.

    ``num`` and ``den`` are sequences of coefficient arrays (highest power first, each
    of the batch shape), ``len(num) <= len(den)`` (proper), ``den[0] != 0``.
    """
    n = len(den) - 1
    if len(num) > n + 1:
        raise ValueError(f"tf: expected a proper transfer function, got numerator degree {len(num) - 1} "
                         f"> denominator degree {n}")
    den = [jnp.asarray(c) for c in den]
    batch = jnp.broadcast_shapes(*[jnp.shape(c) for c in den], *[jnp.shape(c) for c in num])
    lead = jnp.broadcast_to(den[0], batch)
    a = [jnp.broadcast_to(c, batch) / lead for c in den[1:]]
    b = [jnp.zeros(batch)] * (n + 1 - len(num)) + [jnp.broadcast_to(jnp.asarray(c), batch) / lead for c in num]
    d = b[0]
    if n == 0:
        empty = jnp.zeros(batch + (0, 0))
        return LTI(empty, jnp.zeros(batch + (0, 1)), jnp.zeros(batch + (1, 0)), d[..., None, None])
    first_row = jnp.stack([-ai for ai in a], axis=-1)[..., None, :]
    shift = jnp.broadcast_to(jnp.eye(n - 1, n), batch + (n - 1, n))
    A = jnp.concatenate([first_row, shift], axis=-2)
    B = jnp.broadcast_to(jnp.eye(n, 1), batch + (n, 1))
    C = jnp.stack([b[i + 1] - d * a[i] for i in range(n)], axis=-1)[..., None, :]
    return LTI(A, B, C, d[..., None, None])


def c2d(sys: LTI, dt: float, method: str) -> LTI:
    """Discretise with step ``dt`` [s]: 'zoh' (matrix exponential) or 'tustin' (bilinear)."""
    A, B, C, D = sys.A, sys.B, sys.C, sys.D
    n, m = A.shape[-1], B.shape[-1]
    if method == "zoh":
        batch = A.shape[:-2]
        top = jnp.concatenate([A, B], axis=-1)
        M = jnp.concatenate([top, jnp.zeros(batch + (m, n + m))], axis=-2) * dt
        E = _batched(expm, M)
        return LTI(E[..., :n, :n], E[..., :n, n:], C, D)
    if method == "tustin":
        eye = jnp.eye(n)
        ima = eye - 0.5 * dt * A
        Ad = jnp.linalg.solve(ima, eye + 0.5 * dt * A)
        Bd = jnp.linalg.solve(ima, dt * B)
        Cd = jnp.swapaxes(jnp.linalg.solve(jnp.swapaxes(ima, -1, -2), jnp.swapaxes(C, -1, -2)), -1, -2)
        Dd = D + 0.5 * (C @ Bd)
        return LTI(Ad, Bd, Cd, Dd)
    raise ValueError(f"c2d: expected method 'zoh' or 'tustin', got {method!r}")


def _batched(fn, M):
    batch = M.shape[:-2]
    flat = M.reshape((-1,) + M.shape[-2:])
    return jax.vmap(fn)(flat).reshape(batch + M.shape[-2:])


def zeros_state(sys: LTI):
    """The zero state of a block, shape ``(..., n)``."""
    return jnp.zeros(sys.A.shape[:-1])


def output(sys: LTI, x, u):
    """``y = C x + D u`` for SISO-per-axis blocks: ``x (..., n)``, ``u (...)`` -> ``y (...)``."""
    return jnp.einsum("...n,...n->...", sys.C[..., 0, :], x) + sys.D[..., 0, 0] * u


def update(sys: LTI, x, u):
    """``x+ = A x + B u`` for an input ``u`` of shape ``(..., m)``."""
    return jnp.einsum("...ij,...j->...i", sys.A, x) + jnp.einsum("...ij,...j->...i", sys.B, u)


def step_siso(sys: LTI, x, u):
    """One step of a SISO block: returns ``(x+, y)``; ``u`` has the batch shape."""
    return update(sys, x, u[..., None]), output(sys, x, u)
