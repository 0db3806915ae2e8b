"""Experiments that reproduce the paper's claims, one command each: ``pusupu experiment NAME [--out DIR] [--json]
[--quick]``.

Every module named in :data:`REGISTRY` has

* ``run(quick: bool = False) -> Result``: the runs, with JSON-able ``metrics`` and arrays for plots (``series``);
  an experiment that compares gains also takes ``gains`` (a gain file of ``pusupu tune``: a path or a loaded
  :class:`~pusupu_jax.gains.GainFile`), ``run(quick=False, gains=None)``: :func:`takes_gains` lists them;
  one that runs on any machine takes ``machine`` (:func:`takes_machine`);
* ``plot(result, out: Path) -> list[Path]``: PNG figures;
* ``table(result) -> str``: a markdown table of the metrics,

so that the CLI, the tests and a notebook call the same code.  :func:`run_experiment` runs one
and writes ``out/NAME.json``, ``out/NAME.md`` and the figures (atomically).  ``quick`` runs a
short version (a few seconds of the paths, fewer seeds) for the test suite.  ``pusupu experiment NAME
--gains FILE`` passes ``gains`` on, and refuses it (exit 2) for an experiment that does not take it.
"""

from __future__ import annotations

import importlib
import inspect
import json
from dataclasses import dataclass, field
from pathlib import Path

from pusupu_jax.files import write_atomic
from pusupu_jax.params import ParameterError

REGISTRY = {  # name: its module in this package
    "arc": "arc",  # Fig. 7: PID, PID + velocity feedforward and 2-DOF IMC on the 200 mm arc
    "p2p": "p2p",  # section 4 and Table 2: PID vs hybrid with seeded kinematic errors
    "hybrid_grid": "hybrid_grid",  # hybrid mode across lambda2, seeded errors: stability
    "timing": "timing",  # timing convergence: every step halved
    "servo": "servo",  # each loop's Bode plot, step and load-torque step, margins; Table 1 vs --gains
    "tuned": "tuned",  # Table 1 vs pusupu tune's gains on arc and p2p in every mode
    "peg_in_hole": "peg_in_hole",  # Fig. 9a: a peg into a chamfered hole off its axis, MJX contact
    "surface_tracking": "surface_tracking",  # Fig. 9b: a tool holding a force on a tilted surface
    "loop_match": "loop_match",  # loop gains of the MJX machine by injection vs the single-axis and coupled models
    "real2sim": "real2sim",  # gains tuned on the identified machine vs the nominal and the true one, through the bridge
}


@dataclass
class Result:
    """What an experiment's ``run`` returns: JSON-able ``metrics`` and plot arrays in ``series``."""

    name: str
    metrics: dict
    series: dict = field(default_factory=dict, repr=False)

    def __repr__(self) -> str:
        """The name and the top-level metrics, each shortened to a line (the arrays of ``series`` left out)."""
        lines = [f"Result {self.name!r}: {len(self.metrics)} metric(s), series {sorted(self.series)}"[:200]]
        lines += [f"  {k}: {_short(v)}" for k, v in list(self.metrics.items())[:MAX_SHOWN]]
        if len(self.metrics) > MAX_SHOWN:
            lines.append(f"  ... {len(self.metrics) - MAX_SHOWN} more in .metrics")
        return "\n".join(lines)

    def _repr_markdown_(self) -> str:
        """The experiment's own markdown table (its module's ``table``), as ``pusupu experiment`` prints it."""
        try:
            return f"**Result {self.name!r}**\n\n" + get(self.name).table(self)
        except Exception:  # noqa: BLE001 (a result its module cannot tabulate, a hand-made one: the text repr)
            return None


MAX_SHOWN = 20  # top-level metrics shown in a Result's repr


def _short(v, width: int = 90) -> str:
    """One short line for a metric: numbers to 4 digits, lists and mappings summarised."""
    if isinstance(v, float):
        text = f"{v:.4g}"
    elif isinstance(v, dict):
        text = "{" + ", ".join(f"{k}: {_short(x, 20)}" for k, x in v.items()) + "}"
    elif isinstance(v, (list, tuple)):
        text = "[" + ", ".join(_short(x, 20) for x in v) + "]"
    else:
        text = repr(v)
    return text if len(text) <= width else text[: width - 4] + " ..."


def get(name: str):
    """The experiment module ``name``."""
    if name not in REGISTRY:
        raise ParameterError(f"experiment: expected one of {sorted(REGISTRY)}, got {name!r}")
    return importlib.import_module(f"{__name__}.{REGISTRY[name]}")


def takes_gains(name: str | None = None):
    """Whether experiment ``name`` takes ``gains`` (its ``run`` has that parameter); without a name, the sorted
    names of those that do."""
    if name is None:
        return sorted(n for n in REGISTRY if takes_gains(n))
    return "gains" in inspect.signature(get(name).run).parameters


def takes_machine(name: str | None = None):
    """Whether experiment ``name`` runs on a given machine (its ``run`` has a ``machine`` parameter); without a name,
    the sorted names of those that do."""
    if name is None:
        return sorted(n for n in REGISTRY if takes_machine(n))
    return "machine" in inspect.signature(get(name).run).parameters


def check_machine(name: str, machine) -> None:
    """ParameterError in one line when a ``machine`` is given to an experiment that does not take one."""
    if machine is not None and not takes_machine(name):
        raise ParameterError(
            f"--machine: only the experiments {', '.join(takes_machine())} run on a machine file, not {name}"
        )


def gain_file(name: str, gains):
    """``gains`` for experiment ``name`` as a :class:`~pusupu_jax.gains.GainFile`: None, a loaded one as it is, or a
    path loaded and checked (:func:`pusupu_jax.gains.load`, 45 deg and 6 dB).  ParameterError in one line for a bad
    file or an experiment that does not take gains."""
    from pusupu_jax import gains as gain_files

    if gains is None:
        return None
    if not takes_gains(name):
        raise ParameterError(f"--gains: only the experiments {', '.join(takes_gains())} take a gain file, not {name}")
    return gains if isinstance(gains, gain_files.GainFile) else gain_files.load(gains)


def run_experiment(name: str, out, quick: bool = False, gains=None, machine=None) -> tuple[Result, list[Path]]:
    """Run experiment ``name``, write ``out/NAME.json``, ``out/NAME.md`` and its figures; returns (result, files).

    ``gains``: a gain file (path or :class:`~pusupu_jax.gains.GainFile`), only for the experiments of
    :func:`takes_gains`; ``machine`` (a :class:`~pusupu_jax.machine_file.Machine`), only for those of
    :func:`takes_machine` (ParameterError otherwise, before any work).
    """
    module = get(name)
    gains = gain_file(name, gains)
    check_machine(name, machine)
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    kwargs = ({} if gains is None else {"gains": gains}) | ({} if machine is None else {"machine": machine})
    result = module.run(quick=quick, **kwargs)
    files = [Path(f) for f in module.plot(result, out)]
    files.append(write_atomic(out / f"{name}.json", json.dumps(result.metrics, indent=2)))
    files.append(write_atomic(out / f"{name}.md", module.table(result) + "\n"))
    return result, files


def pct(new: float, old: float) -> float:
    """Relative change from ``old`` to ``new`` [%] (negative: a reduction)."""
    return (new / old - 1.0) * 100.0
