"""Linear time-invariant blocks in JAX: state-space form, discretisation, stepping.

Every filter and controller of the cascade is a continuous state-space block of the
parameters (:func:`ss`, :func:`series`), discretised once per rollout (:func:`c2d`, outside
the scan) and stepped inside the scan (:func:`output`, :func:`update`).  Matrices carry leading batch dimensions (one
block
per axis, and more under vmap): ``A (..., n, n)``, ``B (..., n, m)``,
``C (..., p, n)``, ``D (..., p, m)``.

The discretisations are those of python-control's ``sample`` (scipy's
``cont2discrete``): 'zoh' (exact for inputs held over the step) and 'tustin'
(bilinear), so the tests can compare the scan with python-control to rounding error.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import jax
import jax.numpy as jnp
from jax.scipy.linalg import expm
from jax.typing import ArrayLike


@jax.tree_util.register_dataclass
@dataclass(frozen=True)
class LTI:
    """State-space block ``x' = A x + B u, y = C x + D u`` (continuous or discrete)."""

    A: Any
    B: Any
    C: Any
    D: Any


def _stack2(rows: Sequence[Sequence[jax.Array]]) -> jax.Array:
    """A ``(..., r, c)`` matrix from nested lists of arrays of one batch shape."""
    return jnp.stack([jnp.stack(row, axis=-1) for row in rows], axis=-2)


def ss(
    A: Sequence[Sequence[ArrayLike]],
    B: Sequence[Sequence[ArrayLike]],
    C: Sequence[Sequence[ArrayLike]],
    D: Sequence[Sequence[ArrayLike]],
) -> LTI:
    """A SISO block from nested lists of per-axis coefficient arrays (``A`` n x n, ``B`` n x 1, ``C`` 1 x n, ``D`` 1 x
    1).

    The blocks of the cascade are written in realisations whose states hold physical values
    that do not depend on the gains (a low-pass state holds the filtered input, an integrator
    holds its output term), so that a state carried over a change of gains means the same:
    a change of gains moves the output only in proportion to the change, and a run restarted from
    another run's state with other gains continues smoothly.
    """
    batch = jnp.broadcast_shapes(*[jnp.shape(x) for row in (*A, *B, *C, *D) for x in row])

    def mat(rows: Sequence[Sequence[ArrayLike]]) -> jax.Array:
        return _stack2([[jnp.broadcast_to(jnp.asarray(x, dtype=float), batch) for x in row] for row in rows])

    return LTI(mat(A), mat(B), mat(C), mat(D))


def series(*blocks: LTI) -> LTI:
    """``blocks[-1]( ... blocks[1](blocks[0](u)))``: SISO blocks in series, states concatenated in order."""
    out = blocks[0]
    for b in blocks[1:]:
        n1, n2 = out.A.shape[-1], b.A.shape[-1]
        batch = out.A.shape[:-2]
        top = jnp.concatenate([out.A, jnp.zeros(batch + (n1, n2))], axis=-1)
        bottom = jnp.concatenate([b.B @ out.C, b.A], axis=-1)
        out = LTI(
            jnp.concatenate([top, bottom], axis=-2),
            jnp.concatenate([out.B, b.B @ out.D], axis=-2),
            jnp.concatenate([b.D @ out.C, b.C], axis=-1),
            b.D @ out.D,
        )
    return out


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


def _batched(fn: Callable[[jax.Array], jax.Array], M: jax.Array) -> jax.Array:
    batch = M.shape[:-2]
    flat = M.reshape((-1,) + M.shape[-2:])
    return jax.vmap(fn)(flat).reshape(batch + M.shape[-2:])


def zeros_state(sys: LTI) -> jax.Array:
    """The zero state of a block, shape ``(..., n)``."""
    return jnp.zeros(sys.A.shape[:-1])


def dc_state(sys: LTI, u: ArrayLike) -> jax.Array:
    """The fixed point ``x = A x + B u`` of a discrete block without an integrator, for a constant input ``u (...,
    m)``."""
    n = sys.A.shape[-1]
    x: jax.Array = jnp.linalg.solve(jnp.eye(n) - sys.A, jnp.einsum("...ij,...j->...i", sys.B, u)[..., None])[..., 0]
    return x


def dc_gain(sys: LTI) -> jax.Array:
    """Steady output per unit constant input of a discrete SISO block without an integrator, shape ``(...)``."""
    one = jnp.ones(sys.A.shape[:-2] + (1,))
    return output(sys, dc_state(sys, one), one[..., 0])


def integrator_state(sys: LTI, y: ArrayLike) -> jax.Array:
    """A state of a discrete SISO block with an integrator (``A = 1``) that outputs ``y`` with a zero input.

    With a zero input every state is a fixed point; this is the one of least norm.
    """
    c: jax.Array = sys.C[..., 0, :]
    return c * (y / jnp.sum(c * c, axis=-1))[..., None]


def output(sys: LTI, x: ArrayLike, u: ArrayLike) -> jax.Array:
    """``y = C x + D u`` for SISO-per-axis blocks: ``x (..., n)``, ``u (...)`` -> ``y (...)``."""
    y: jax.Array = jnp.einsum("...n,...n->...", sys.C[..., 0, :], x) + sys.D[..., 0, 0] * u
    return y


def update(sys: LTI, x: ArrayLike, u: ArrayLike) -> jax.Array:
    """``x+ = A x + B u`` for an input ``u`` of shape ``(..., m)``."""
    return jnp.einsum("...ij,...j->...i", sys.A, x) + jnp.einsum("...ij,...j->...i", sys.B, u)


def step_siso(sys: LTI, x: ArrayLike, u: jax.Array) -> tuple[jax.Array, jax.Array]:
    """One step of a SISO block: returns ``(x+, y)``; ``u`` has the batch shape."""
    return update(sys, x, u[..., None]), output(sys, x, u)
