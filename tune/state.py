"""The tuner's state: where an optimisation stands, what :mod:`.checkpoint` writes and reads back, and what
:func:`pusupu_jax.tune.optimise.iterate` advances."""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np


@dataclasses.dataclass(frozen=True)
class Evaluation:
    """One evaluation of the objective: ``start`` (from 0), ``iteration`` (0 = the start's own gains), the ``objective``
    (dimensionless) and the point ``z`` evaluated (each tuned field's log-gains: a float or one per axis; None where a
    report leaves the point out)."""

    start: int
    iteration: int
    objective: float
    z: dict[str, Any] | None = None

    def without_point(self) -> Evaluation:
        """The entry as a report keeps it: start, iteration and objective."""
        return dataclasses.replace(self, z=None)

    def to_json(self) -> dict[str, Any]:
        """Plain data, keys in the checkpoint's and ``report.json``'s order; the point only where there is one."""
        d: dict[str, Any] = {"start": self.start, "iteration": self.iteration, "objective": self.objective}
        return d if self.z is None else d | {"z": self.z}

    @classmethod
    def from_json(cls, d: dict[str, Any]) -> Evaluation:
        """The record of :meth:`to_json`'s data (already checked by whoever read it)."""
        return cls(int(d["start"]), int(d["iteration"]), float(d["objective"]), d.get("z"))


@dataclasses.dataclass
class TunerState:
    """Where an optimisation stands: what a checkpoint holds (:mod:`.checkpoint`).

    ``z`` and ``opt``: every member's log-gains and optax state, each leaf with a leading member axis (None between
    two starts of a single problem); ``history``: per member, one :class:`Evaluation` (with its point) per
    evaluation; ``best_value`` ``(M,)`` and ``best_z``: each member's best point so far; ``failed``:
    ``{member: message}`` for members frozen at a non-finite objective or gradient; ``start``: the start being run
    (a single problem's starts run one after another); ``iteration``: the next iteration of that start.
    """

    digest: str
    z: dict | None
    opt: Any
    history: list[list[Evaluation]]
    best_value: np.ndarray
    best_z: dict
    failed: dict = dataclasses.field(default_factory=dict)
    start: int = 0
    iteration: int = 0
    done: bool = False

    @classmethod
    def fresh(cls, digest: str, zb: dict, opt_state) -> "TunerState":
        """The state before the first evaluation of the members ``zb``."""
        members = len(next(iter(zb.values())))
        return cls(
            digest=digest,
            z=zb,
            opt=opt_state,
            history=[[] for _ in range(members)],
            best_value=np.full(members, np.inf),
            best_z={k: np.array(v) for k, v in zb.items()},
        )

    def note(self, values: np.ndarray, zb: dict, starts: list[int], iteration: int) -> None:
        """The history entry of every member that has not failed at this ``iteration``, and its best point."""
        zh = {n: np.asarray(v) for n, v in zb.items()}  # host copies: per-member indexing without device calls
        for m, value in enumerate(values):
            if m in self.failed:
                continue
            self.history[m].append(
                Evaluation(starts[m], iteration, float(value), {n: v[m].tolist() for n, v in zh.items()})
            )
            if value < self.best_value[m]:
                self.best_value[m] = value
                for n, v in zh.items():
                    self.best_z[n][m] = v[m]
