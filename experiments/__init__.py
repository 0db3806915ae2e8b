"""Experiments that reproduce the paper's claims, one command each: ``pusupu experiment NAME [--out DIR] [--json] [--quick]``.

Every module named in :data:`REGISTRY` has

* ``run(quick: bool = False) -> Result``: the runs, with JSON-able ``metrics`` and arrays for plots (``series``);
* ``plot(result, out: Path) -> list[Path]``: PNG figures;
* ``table(result) -> str``: a markdown table of the metrics,

so that the CLI, the tests and a notebook call the same code.  :func:`run_experiment` runs one
and writes ``out/NAME.json``, ``out/NAME.md`` and the figures (atomically).  ``quick`` runs a
short version (a few seconds of the paths, fewer seeds) for the test suite.
"""

from __future__ import annotations

import importlib
import json
from dataclasses import dataclass, field
from pathlib import Path

from pusupu_jax.config import write_atomic
from pusupu_jax.params import ParameterError

REGISTRY = {
    "arc": "experiments.arc",  # Fig. 7: PID, PID + velocity feedforward and 2-DOF IMC on the 200 mm arc
    "p2p": "experiments.p2p",  # section 4 and Table 2: PID vs hybrid with seeded kinematic errors
    "hybrid_grid": "experiments.hybrid_grid",  # hybrid mode across lambda2, seeded errors: stability
    "timing": "experiments.timing",  # timing convergence: every step halved
}


@dataclass
class Result:
    """What an experiment's ``run`` returns: JSON-able ``metrics`` and plot arrays in ``series``."""

    name: str
    metrics: dict
    series: dict = field(default_factory=dict, repr=False)


def get(name: str):
    """The experiment module ``name``."""
    if name not in REGISTRY:
        raise ParameterError(f"experiment: expected one of {sorted(REGISTRY)}, got {name!r}")
    return importlib.import_module(REGISTRY[name])


def run_experiment(name: str, out, quick: bool = False) -> tuple[Result, list[Path]]:
    """Run experiment ``name``, write ``out/NAME.json``, ``out/NAME.md`` and its figures; returns (result, files)."""
    module = get(name)
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    result = module.run(quick=quick)
    files = [Path(f) for f in module.plot(result, out)]
    files.append(write_atomic(out / f"{name}.json", json.dumps(result.metrics, indent=2)))
    files.append(write_atomic(out / f"{name}.md", module.table(result) + "\n"))
    return result, files


def pct(new: float, old: float) -> float:
    """Relative change from ``old`` to ``new`` [%] (negative: a reduction)."""
    return (new / old - 1.0) * 100.0
