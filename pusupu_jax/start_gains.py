"""Start gains for a machine by the paper's method: Table 1's loop design carried over to other drives (host-side).

Table 1 is one design for one motor.  Its ratios carry over; its numbers do not.  For a
machine (:class:`~pusupu_jax.machine_file.Machine`), per axis:

1. **Current PI** (eq. 1-5): ``Ti = L/R`` (the PI zero cancels the armature pole, as Table 1
   does), and ``Ki`` puts the loop's crossover ``w_i = Ki Kn Kcf / L`` at Table 1's fraction of the
   inverter's bandwidth, ``w_i Tn``.  The current filter ``Tcf`` keeps Table 1's ``w_i Tcf``.
2. **Velocity PI** (eq. 6-8): the crossover ``w_v = Kv Kt Kw / J_eff`` keeps Table 1's ratio to the
   current loop's, ``w_v / w_i``; ``Tv`` and the speed filter ``Tw`` keep Table 1's ``w_v Tv`` and
   ``w_v Tw``, so the PI zero and the filter's lag sit where Table 1 puts them relative to the
   crossover and the loop keeps Table 1's phase margin (in this loop model: closed current loop as
   1, rigid load).  ``J_eff = J + m r^2 / eta`` with ``m`` the mass the slider carries
   (:func:`pusupu_jax.machine_file.carried_mass` at home, payload included).
3. **T0** (eq. 9): identified on that machine, velocity steps of the MJX machine at home
   (:func:`pusupu_jax.identify.identify_T0_machine`), with the velocity loop of step 2.
4. **IMC** (eq. 9): ``lambda1`` and ``lambda2`` in Table 1's ratio to ``T0``
   (0.018 / 0.01475 and 0.15 / 0.01475).
5. **PID baselines**: Table 1's PID (``docs/parameters.md``: the nominal IMC loop's crossover)
   on the time scale ``k = T0 / 0.01475 s``: ``Kp / k``, ``Ki / k^2``, ``Kd`` and ``Tf k``.

Each ratio is taken on the built-in machine, so the built-in machine gets back Table 1 in
steps 1, 2 and 5 to rounding.  Step 3 does not give back Table 1's ``T0``: the paper's
``T0`` is the closed velocity loop of its own machine, reproduced by the single-axis model with the
lumped 20 kg design load (:class:`~pusupu_jax.params.AxisLoad`), while the MJX machine's branches carry
their own share of the mechanism and push through it against the other five loops (:func:`derive`
reports the identified value and Table 1's).
Limits (``I_max``, ``V_max``) become the machine's ratings (``I_peak``, ``V_dc`` less Table 1's
margin); the following-error window and time stay Table 1's.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import numpy.typing as npt

from .identify import identify_T0_machine
from .machine_file import Machine, carried_mass
from .params import LoopRates, ServoParams, array_fields
from .plant.axis import screw_ratio

T0_TABLE1 = 0.01475  # s


def _crossovers(servo: ServoParams, mass: npt.ArrayLike) -> tuple[np.ndarray, np.ndarray]:
    """The current and velocity loops' crossovers [rad/s] in the design model of the module docstring."""
    r = np.asarray(screw_ratio(servo))
    j_eff = np.asarray(servo.J) + np.asarray(mass) * r**2 / np.asarray(servo.eta)
    w_i = np.asarray(servo.Ki) * np.asarray(servo.Kn) * np.asarray(servo.Kcf) / np.asarray(servo.L)
    w_v = np.asarray(servo.Kv) * np.asarray(servo.Kt) * np.asarray(servo.Kw) / j_eff
    return w_i, w_v


def derive(
    machine: Machine, rates: LoopRates = LoopRates(), identify: bool = True, shared: bool = True
) -> tuple[ServoParams, dict[str, Any]]:
    """Start gains for ``machine`` (the module docstring's steps) and a report of what was derived (per axis).

    ``identify=False`` leaves ``T0`` (and so the IMC and PID time scales) at Table 1's, skipping the MJX identification.
    ``shared``: every gain the mean of its six derived values (a payload off centre loads the axes unequally, by
    under 1 % on the example user machine), as a tuning of one value for all six axes starts from; False keeps one per
    axis.
    """
    table1, builtin = ServoParams.table1(), Machine.default()
    ref = builtin.servo(table1)
    wi_ref, wv_ref = _crossovers(ref, carried_mass(builtin))
    on = machine.servo(
        table1.replace(
            I_max=np.asarray(machine.drives["I_peak"]),
            V_max=np.asarray(machine.drives["V_dc"]) * (table1.V_max / ref.V_dc),
        )
    )
    mass = carried_mass(machine)
    d = {k: np.asarray(machine.drives[k], dtype=float) for k in machine.drives}
    w_i = wi_ref * ref.Tn / d["Tn"]  # Table 1's w_i Tn
    servo = on.replace(Ti=d["L"] / d["R"], Ki=w_i * d["L"] / (d["Kn"] * table1.Kcf), Tcf=table1.Tcf * wi_ref / w_i)
    _, wv_unit = _crossovers(servo.replace(Kv=np.ones(6)), mass)
    w_v = wv_ref / wi_ref * w_i
    servo = servo.replace(Kv=w_v / wv_unit, Tv=table1.Tv * wv_ref / w_v, Tw=table1.Tw * wv_ref / w_v)
    report: dict[str, Any] = {
        "carried_mass_kg": mass.tolist(),
        "current_crossover_rad_s": w_i.tolist(),
        "velocity_crossover_rad_s": w_v.tolist(),
        "T0_table1_s": T0_TABLE1,
    }
    if identify:
        found = identify_T0_machine(servo, machine.options(), rates=rates, geom=machine.geometry)
        T0 = np.asarray(found["T0"], dtype=float)
        report |= {"T0_identified_s": T0.tolist(), "T0_fit_rms_rad_s": found["fit_rms"]}
    else:
        T0 = np.full(6, T0_TABLE1)
    k = T0 / T0_TABLE1
    servo = servo.replace(
        T0=T0,
        lambda1=table1.lambda1 * k,
        lambda2=table1.lambda2 * k,
        Kp_pid=table1.Kp_pid / k,
        Ki_pid=table1.Ki_pid / k**2,
        Tf_pid=table1.Tf_pid * k,
    )
    if shared:
        servo = servo.replace(
            **{
                f.name: np.full(6, np.mean(getattr(servo, f.name)))
                for f in array_fields(ServoParams)
                if f.metadata["section"] != "plant"
            }
        )
    return machine.servo(servo), report
