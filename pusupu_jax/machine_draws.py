"""Machines drawn about an identified one from the standard errors its machine file carries (its ``uncertainty``
section, written by ``pusupu identify``): the scenarios of a tune that must hold across what the logs left uncertain
(``pusupu tune``'s ``draws``).

Each value with a standard error is drawn from a normal law about the machine's value with that standard error, held
inside its field's range (:func:`pusupu_jax.machine_fit.value_range`: no negative friction); a drawn ``Kt`` carries
``Ke`` in proportion (:func:`pusupu_jax.machine_fit.drive_values`: both are the motor's flux linkage).  The values are
drawn independently: each keeps its own spread, and the fit's correlations between values are not carried (the file
holds standard errors, not the covariance), so the draws also reach combinations the fit makes unlikely, on the
cautious side for a tune.

A drawn machine is what the robot might be, while its machine file is still the identified one
(:class:`~pusupu_jax.plant.PlantDrives`: a rollout's plant, motors and drives take the drawn drive values; what the
host computes from the machine file, the identified ones).
"""

from __future__ import annotations

import dataclasses

import numpy as np

from .machine_file import UNCERTAINTY_FIELDS, Machine
from .machine_fit import FitField, value_range, with_values
from .params import ParameterError

DRAWN_DRIVES = ("coulomb", "viscous", "J", "Kt", "Ke")  # the drive fields a draw may change (Ke follows Kt)


def draw(machine: Machine, n: int, seed: int) -> list[Machine]:
    """``n`` machines drawn about ``machine`` from its ``uncertainty`` (module docstring), named ``<name> draw k``
    (``k`` from 1), with the generator seeded by ``seed``: the same file and seed draw the same machines.  Values
    without a standard error (or with 0) are the machine's.  Raises ParameterError where the machine has no
    uncertainty section."""
    if machine.uncertainty is None:
        raise ParameterError(
            f"draws: expected a machine file with an uncertainty section (pusupu identify --out writes one), got "
            f"machine {machine.name!r} without one"
        )
    rng = np.random.default_rng(seed)
    out = []
    for k in range(n):
        values = {}
        for name in UNCERTAINTY_FIELDS:  # in a fixed order, whatever the file's
            if name not in machine.uncertainty:
                continue
            field = FitField(name)
            start = field.start(machine)
            low, high = value_range(field)
            spread = np.broadcast_to(machine.uncertainty[name], start.shape)
            values[field] = np.clip(start + spread * rng.standard_normal(start.shape), low, high)
        drawn = with_values(machine, values)
        out.append(dataclasses.replace(drawn, name=f"{machine.name} draw {k + 1}", uncertainty=None))
    return out


def plant_drives(machine: Machine) -> dict[str, np.ndarray]:
    """``machine``'s values of :data:`DRAWN_DRIVES`, ``{field: (6,)}``: what a
    :class:`~pusupu_jax.plant.PlantDrives` of it carries."""
    return {k: np.asarray(machine.drives[k], float).copy() for k in DRAWN_DRIVES}
