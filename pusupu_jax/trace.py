"""A rollout's record (:class:`Trace`): every signal of the cascade and the plant at the start of each outer-loop
period, shown as a short per-axis summary rather than its arrays."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Callable

import jax
import numpy as np
import numpy.typing as npt


@jax.tree_util.register_dataclass
@dataclass(frozen=True)
class Trace:
    """A rollout sampled at the start of every outer-loop period; arrays are ``(..., N, n_axes)``.

    ``reference`` and ``command`` are in the outer loop's units: position loops take a
    motor angle [rad] and command a speed [rad/s]; the velocity loop takes [rad/s] and
    commands a current [A]; the current loop takes [A] and commands a voltage [V].
    """

    t: Any  # s, (N,)
    reference: Any
    command: Any
    theta: Any  # motor angle, rad
    omega: Any  # motor speed, rad/s
    position: Any  # slider position, m
    velocity: Any  # slider velocity, m/s
    current: Any  # armature current, A
    torque: Any  # motor torque Kt*I, N m
    current_reference: Any  # A, (..., N, m, n_axes): the current references of the period's m inner periods
    state: Any  # every controller state (a cascade.CascadeState)
    observation: Any  # what the plant's observe() keeps (pytree)

    def __repr__(self) -> str:
        """Duration, shapes, and per axis the slider's range and the peak current and torque (not the arrays)."""
        return _describe_trace(self)

    def _repr_markdown_(self) -> str:
        return _describe_trace(self, markdown=True)


def _describe_trace(tr: Trace, markdown: bool = False) -> str:
    arrays = {k: getattr(tr, k) for k in ("t", "position", "current", "torque")}
    shapes = {k: np.shape(v) for k, v in arrays.items()}
    if any(isinstance(v, jax.core.Tracer) for v in arrays.values()) or len(shapes["position"]) < 2:
        return f"Trace(shapes {shapes})"
    try:
        return _trace_table(tr, shapes, markdown)
    except (TypeError, ValueError, IndexError):  # not arrays of a rollout (a tree_map's product): the shapes only
        return f"Trace(shapes {shapes})"


def _trace_table(tr: Trace, shapes: dict[str, tuple[int, ...]], markdown: bool) -> str:
    from .params import axis_cells, axis_table

    n, axes = shapes["position"][-2:]
    batch = shapes["position"][:-2]
    t = np.asarray(tr.t).reshape(-1, n)[0] if n else np.zeros(0)
    dt = float(t[1] - t[0]) if n > 1 else float("nan")
    title = (
        f"Trace: {n * dt:.4g} s, {n} periods of {dt * 1e3:.4g} ms, {axes} axes"
        + (f", a batch of shape {batch} (lo..hi over the batch)" if batch else "")
        + f"; arrays (..., N, axes) {shapes['position']}, current_reference {np.shape(tr.current_reference)}, "
        "state and observation pytrees"
    )
    if not n:
        return title
    peak: Callable[[npt.ArrayLike], npt.NDArray[Any]] = lambda x: np.abs(np.asarray(x)).max(axis=-2)  # noqa: E731
    position = np.asarray(tr.position) * 1e3
    rows = [
        ("slider min", "mm", axis_cells(position.min(axis=-2))),
        ("slider max", "mm", axis_cells(position.max(axis=-2))),
        ("peak current", "A", axis_cells(peak(tr.current))),
        ("peak torque", "N m", axis_cells(peak(tr.torque))),
    ]
    return axis_table(f"**{title}**" if markdown else title, rows, axes, markdown)
