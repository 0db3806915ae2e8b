"""What the two contact experiments (Fig. 9: ``peg_in_hole``, ``surface_tracking``) share: the runs and the tool.

Each run is the machine in real MJX contact under the cascade, Table 1 gains, with or without
the admittance of :mod:`pusupu_jax.compliance` around the position loops.  The contact force is
what the scene exerts on the tool (an ideal wrist sensor: :meth:`MJXPlant.contact_force`);
nothing is scripted.  Two settings of MuJoCo's solver differ from the tuner's machine, both
measured on the surface scene (``IMC + force control``, quick path):

* four Newton iterations instead of the one that keeps gradients cheap: with one, a contact
  that appears mid-step came out of the solve at 113 kN; twelve give the same run as four to
  every printed digit;
* the elliptic friction cone instead of the pyramidal: with the pyramidal cone a sliding tool
  chatters, its normal force alternating between zero and twice its mean from one period to
  the next (on an earlier quick path, a 30 mm sweep: 41 % of the periods off the surface,
  against 4 % with the elliptic cone).  The elliptic cone reduces the chatter; it does not
  remove it (``docs/compliance.md``).
"""

from __future__ import annotations

import dataclasses

import matplotlib.pyplot as plt
import numpy as np

from pusupu_jax import LoopRates, ServoParams
from pusupu_jax.machine import Scenario, simulate_scenarios

SOLVER = dict(solver_iterations=4, cone="elliptic")  # ModelOptions of the contact scenes (above)


def run_modes(path, options, runs: dict, *, rates: LoopRates = LoopRates(), force_setpoint=None) -> tuple[dict, dict]:
    """Run ``path`` on the machine built with ``options`` once per entry of ``runs``, ``label: (mode,
    admittance gains or None)``; returns ``(runs, arrays)`` keyed by label (each run a
    :class:`~pusupu_jax.machine.MachineRun`)."""
    results, arrays = {}, {}
    for label, (mode, gains) in runs.items():
        ((result, a),) = simulate_scenarios(
            ServoParams.table1(),
            [Scenario(path, options)],
            mode=mode,
            rates=rates,
            compliance=gains,
            force_setpoint=force_setpoint if gains else None,
        )
        results[label], arrays[label] = result, a
    return results, arrays


def tool_point(arrays: dict, below: float) -> np.ndarray:
    """World position [m] of the point ``below`` [m] under the platform centre on its axis, ``(N, 3)``."""
    return arrays["platform"] + np.asarray(arrays["platform_mat"])[:, :, 2] * -below


def halved(options, rates: LoopRates = LoopRates()):
    """``options`` and ``rates`` with every step halved (as the ``timing`` experiment halves them)."""
    return dataclasses.replace(options, timestep=options.timestep / 2), rates.finer(2)


def force_figure(result_series: dict, title: str, below: str, ylabel: str):
    """Per run, the contact force components against time, and under them ``arrays[below]`` [m] in mm
    (``ylabel``) with its zero marked."""
    fig, axes = plt.subplots(2, len(result_series), figsize=(5.5 * len(result_series), 7.2), squeeze=False, sharex=True)
    for col, (label, a) in enumerate(result_series.items()):
        ax = axes[0, col]
        for k, name in enumerate("xyz"):
            ax.plot(a["t"], np.asarray(a["contact_force"])[:, k], lw=0.8, label=f"F{name}")
        ax.set_title(label, fontsize=9)
        ax.set_ylabel("contact force on the tool [N]")
        ax.grid(True, alpha=0.3)
        ax.legend(fontsize=7)
        ax = axes[1, col]
        ax.plot(a["t"], np.asarray(a[below]) * 1e3, lw=1)
        ax.axhline(0.0, color="k", lw=0.6)
        ax.set_ylabel(ylabel)
        ax.set_xlabel("time [s]")
        ax.grid(True, alpha=0.3)
    fig.suptitle(title)
    fig.tight_layout()
    return fig
