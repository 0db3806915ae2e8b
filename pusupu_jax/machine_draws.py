"""Machines drawn about an identified one from the standard errors its machine file carries (its ``uncertainty``
section, written by ``pusupu identify``): the scenarios of a tune that must hold across what the logs left uncertain
(``pusupu tune``'s ``draws``).

Each value with a standard error is drawn from a normal law about the machine's value with that standard error, held
inside its field's range (:func:`pusupu_jax.machine_fit.value_range`: no negative friction); a drawn ``Kt`` carries
``Ke`` in proportion (:func:`pusupu_jax.machine_fit.drive_values`: both are the motor's flux linkage).  The values the
section's ``correlation`` names (``pusupu identify`` writes the fit's) are drawn jointly, with those correlations: a
combination the logs rule out (more friction with less inertia, where the fit can tell only their sum) is not drawn.
The others are drawn independently; a file without a ``correlation`` draws every value independently, which also
reaches combinations the fit makes unlikely.

A drawn machine is what the robot might be, while its machine file is still the identified one
(:class:`~pusupu_jax.plant.PlantDrives`: a rollout's plant, motors and drives take the drawn drive values; what the
host computes from the machine file, the identified ones).
"""

from __future__ import annotations

import dataclasses

import numpy as np

from .machine_file import UNCERTAINTY_FIELDS, Machine, check_correlation, value_label
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
    fields = [FitField(name) for name in UNCERTAINTY_FIELDS if name in machine.uncertainty]  # a fixed order
    joint, factor = [], None
    if machine.correlation is not None:
        check_correlation(machine.correlation, machine.uncertainty)
        at = {value_label(f, i): (f, i) for f in fields for i in range(f.size)}
        joint = [at[label] for label in machine.correlation.values]
        # z = F n with F F^T = C: F from C's eigenvectors (C may be singular, where Cholesky fails)
        eigenvalues, eigenvectors = np.linalg.eigh(np.asarray(machine.correlation.matrix, float))
        factor = eigenvectors * np.sqrt(np.maximum(eigenvalues, 0.0))
    rng = np.random.default_rng(seed)
    out = []
    for k in range(n):
        z = {f: rng.standard_normal(f.size) for f in fields}  # independent standard normals, field by field
        if factor is not None:
            correlated = factor @ np.array([z[f][i] for f, i in joint])
            for (f, i), v in zip(joint, correlated):
                z[f][i] = v
        values = {}
        for f in fields:
            start = f.start(machine)
            low, high = value_range(f)
            spread = np.broadcast_to(machine.uncertainty[f], start.shape)
            values[f] = np.clip(start + spread * z[f], low, high)
        drawn = with_values(machine, values)
        out.append(dataclasses.replace(drawn, name=f"{machine.name} draw {k + 1}", uncertainty=None, correlation=None))
    return out


def plant_drives(machine: Machine) -> dict[str, np.ndarray]:
    """``machine``'s values of :data:`DRAWN_DRIVES`, ``{field: (6,)}``: what a
    :class:`~pusupu_jax.plant.PlantDrives` of it carries."""
    return {k: np.asarray(machine.drives[k], float).copy() for k in DRAWN_DRIVES}
