"""The velocity loops' time constant ``T0`` identified on the MJX machine (host-side driver, one jitted rollout).

``C2`` (eq. 9) is designed on the position plant ``1/(s (T0 s + 1))``: the closed velocity
loop seen as a first-order lag.  Table 1's ``T0 = 0.01475 s`` belongs to the paper's machine,
and :func:`pusupu_jax.analysis.identify_T0` finds it on the 20 kg single-axis ``AxisLoad``; on
the 6PUS-UPU mechanism each branch carries its own share of the platform, rods and UPU leg,
coupled through the closed chain, and that share changes with the direction of motion.

The test, as a technician runs it on the machine: from rest at a pose (held by the drives,
:func:`pusupu_jax.sim.initial_state`), every branch's velocity loop gets a step of the speed
that one platform motion asks of it (``w_ref = J d v / r`` for a direction ``d`` in pose space,
``J = ds/dq`` of the nominal geometry), so that the branches move together as the mechanism
allows; the measured motor speeds are recorded for ``window`` seconds.  Each branch's ``T0``
is the least-squares first-order fit to its responses over every direction tested
(:func:`pusupu_jax.analysis.fit_first_order`; a direction in which a branch hardly moves
weighs little).  Directions default to ``x`` and ``y``, the plane of the paper's paths.

The test leaves out the drive train's Coulomb friction (its viscous part stays): ``T0`` is the
time constant of the linear loop that C2 models, and a Coulomb force is a constant load that
the velocity PI's slow integral (Table 1's ``Tv`` = 5 s) leaves as an offset over the test, so
that the first-order fit runs to its bound (0.2 s on the built-in machine with 20 N, against
30.8 ms without).
"""

from __future__ import annotations

import functools
from collections.abc import Callable, Sequence
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from .analysis import fit_first_order
from .machine import machine_plant, machine_rates
from .params import LoopRates, ServoParams, validate
from .plant import kinematics
from .plant.axis import screw_ratio
from .plant.geometry import Geometry
from .plant.mjx_plant import MJXPlant
from .plant.model import ModelOptions
from .programs import Program, describe
from .sim import rollout
from .trace import Trace

DIRECTIONS = {"x": (1.0, 0, 0, 0, 0), "y": (0, 1.0, 0, 0, 0), "z": (0, 0, 1.0, 0, 0)}


@functools.lru_cache(maxsize=None)
def _step_tests(plant: MJXPlant, rates: LoopRates) -> Callable[..., Trace]:
    """The step tests' program ``(servo, model, references (D, N, 6)) -> Trace``: the servo parameters and the
    machine's model are arguments, so that every machine of the plant's structure runs one program, kept on disk
    (:class:`~pusupu_jax.programs.Program`): a later process loads it rather than tracing it again."""
    return Program(
        jax.vmap(functools.partial(rollout, plant=plant, rates=rates, outer="velocity"), in_axes=(None, None, 0)),
        lambda: describe(("velocity steps", plant.key(), rates)),
    )


def identify_T0_machine(
    servo: ServoParams,
    options: ModelOptions = ModelOptions(),
    directions: Sequence[str] = ("x", "y"),
    speed: float = 0.01,
    window: float = 0.2,
    rates: LoopRates = LoopRates(),
    geom: Geometry | None = None,
) -> dict[str, Any]:
    """Per-branch ``T0`` [s] from velocity steps of the machine (nominal geometry ``geom``, default
    :meth:`Geometry.default`) at its home pose.

    ``speed`` [m/s]: the platform speed of each step; ``window`` [s]: the length of each test.
    Returns ``{"T0": [6 values], "directions": [...], "t": (N,), "omega": (D, N, 6) rad/s,
    "omega_ref": (D, 6) rad/s, "fit_rms": [6 values] rad/s}``.
    """
    validate(servo)
    servo = servo.replace(coulomb=np.zeros_like(np.asarray(servo.coulomb, dtype=float)))
    unknown = [d for d in directions if d not in DIRECTIONS]
    if unknown or not directions:
        raise ValueError(f"directions: expected some of {sorted(DIRECTIONS)}, got {list(directions)}")
    rates = machine_rates(options, rates)
    geom = Geometry.default() if geom is None else geom
    J = np.asarray(kinematics.jacobian(geom, jnp.asarray(geom.home)))  # (6, 5) m per pose unit
    r = np.asarray(screw_ratio(servo))
    w_ref = np.stack([J @ np.asarray(DIRECTIONS[d]) * speed / r for d in directions])  # (D, 6) rad/s
    n = int(round(window / rates.dt_velocity))
    reference = jnp.asarray(np.repeat(w_ref[:, None, :], n, axis=1))
    plant = machine_plant(ModelOptions())
    trace = _step_tests(plant, rates)(servo, plant.variant(options, geom), reference)
    t, omega = np.asarray(trace.t[0]), np.asarray(trace.omega)
    T0, fit_rms = [], []
    for b in range(6):
        tau = fit_first_order(t, omega[:, :, b], w_ref[:, b])
        T0.append(tau)
        model = w_ref[:, None, b] * (1.0 - np.exp(-t / tau))
        fit_rms.append(float(np.sqrt(np.mean((omega[:, :, b] - model) ** 2))))
    return {"T0": T0, "directions": list(directions), "t": t, "omega": omega, "omega_ref": w_ref, "fit_rms": fit_rms}
