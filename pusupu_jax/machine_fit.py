"""Fitting the machine's drive fields (friction, rotor inertia, torque constant) to run logs (host-side driver of a
differentiable replay).

A log (:func:`pusupu_jax.run_log.drive_log`: ``pusupu sim --plant mjx --log`` or ``pusupu bridge --log``) holds, per
sample, the motor angle each axis followed, and the angle, speed, torque and (protocol version 2) current its drive
measured.  :func:`fit` replays the logged path through the simulated closed loop (the cascade with the gains the log
ran with, on the MJX machine of the machine file), from rest at the path's start, and fits chosen drive fields of the
machine file (:class:`FitField`) so that the replay's motor efforts and angles match the logged ones: a nonlinear
least-squares problem whose residual is

    r = [(e_sim - e_log) / s_e, (theta_sim - theta_log) / s_theta]   over every logged sample and axis,

``e`` the log's :class:`Channel`: the measured current [A] where the log has it (what a drive measures: the torque it
reports is the current times its own idea of Kt), else the torque [N m]; ``s_e`` the RMS of the logged efforts of
that channel and ``s_theta`` the RMS of the logged tracking error (so both count alike).  ``Kt`` needs currents: with
torques only, the replay's torque does not depend on it.  Its scale is fixed by the loads the machine file knows
absolutely, chiefly gravity on the sliders and the mechanism's masses; ``J``, by the accelerations along the path.

*Closed-loop replay, not open-loop.*  The logged run was closed loop: replaying the logged torques into the open-loop
machine drifts away from the logged motion within a fraction of a second (an unstable double integrator per axis), so
its residual stops measuring the parameters.  The replayed closed loop stays on the path, and the effort its
controller needs to get there carries the friction (Coulomb and viscous), the inertia and the torque constant of the
logged machine.

*Solver.*  scipy's trust-region reflective least squares (``scipy.optimize.least_squares(method='trf')``), each
value held inside its field's range (:func:`pusupu_jax.params.bounds`: no negative friction), over two jitted
programs, the residual and its Jacobian (``jax.jacfwd``: forward mode, one tangent per fitted value, exact).  An
optimistix Levenberg-Marquardt traces the whole solve, both programs inside its loop, into one program: on the
2-core CPU (beside another job) its compile for a 1 s window had not ended after 8 minutes, where the two programs
here compile in about 35 s.  With scipy's finite differences of the residual instead (:class:`Derivatives`), a fit
of 28 values took 3.1x to 5.6x more replays and had not converged at 50 evaluations (``docs/benchmarks.md``).

*Standard errors* come from the Jacobian and the residual at the optimum, with the residual's correlation in time
counted (:mod:`pusupu_jax.fit_errors`: a model's error errs alike over many samples in a row).  A value the logs do
not excite (its Jacobian column below ``1e-8`` of the largest, or a standard error above half its size) is not
invented: it keeps the machine file's value, is reported as not excited, and the others are fitted again without
it.
"""

from __future__ import annotations

import dataclasses
import enum
import time
from typing import Any, Callable, cast

import jax
import jax.numpy as jnp
import numpy as np

from . import devices, fit_errors
from .cascade import control_mode
from .hybrid import HybridGains, HybridReference
from .machine import MACHINE_MODES, machine_plant, machine_rates, machine_reference
from .machine_file import Correlation, Machine, value_label
from .params import N_AXES, LoopRates, ParameterError, ServoParams, bounds
from .paths import check_spec, platform_path_from
from .plant.model import ModelOptions
from .run_log import SIM_SOURCE, DriveLog
from .runtime import require_x64
from .sim import AGES, Commanded, rollout


class FitField(enum.StrEnum):
    """A field of the machine file that :func:`fit` can fit: a drive field (one value per axis) or the payload's."""

    COULOMB = "coulomb"  # Coulomb friction at the slider [N]
    VISCOUS = "viscous"  # viscous friction at the slider [N s/m]
    INERTIA = "J"  # the motor's rotor inertia [kg m^2]
    TORQUE_CONSTANT = "Kt"  # the motor's torque constant [N m/A], Ke with it (:func:`drive_values`): needs currents
    PAYLOAD_MASS = "payload_mass"  # the payload's mass [kg]
    PAYLOAD_COM = "payload_com"  # the payload's centre of mass (x, y, z) in the platform frame [m]

    @property
    def drive(self) -> bool:
        """A drive field: one value per axis, in ``Machine.drives``."""
        return self not in (FitField.PAYLOAD_MASS, FitField.PAYLOAD_COM)

    @property
    def size(self) -> int:
        """How many values the field has: one per axis, one mass, three coordinates."""
        return N_AXES if self.drive else 3 if self is FitField.PAYLOAD_COM else 1

    def label(self, index: int) -> str:
        """One value's name: ``coulomb[3]`` (axis 3, from 1), ``payload_com.x``, ``payload_mass``
        (:func:`pusupu_jax.machine_file.value_label`)."""
        return value_label(self, index)

    def start(self, machine: Machine) -> np.ndarray:
        """The field's values in ``machine`` ``(size,)``: where the fit starts."""
        if self.drive:
            return np.broadcast_to(np.asarray(machine.drives[self], float), (N_AXES,)).copy()
        if self is FitField.PAYLOAD_COM:
            return np.asarray(machine.payload.com, float).copy()
        return np.array([machine.payload.mass], float)


FIT_GROUPS = {  # names of several fields at once (``--fit``)
    "friction": (FitField.COULOMB, FitField.VISCOUS),
    "motor": (FitField.INERTIA, FitField.TORQUE_CONSTANT),
    "payload": (FitField.PAYLOAD_MASS, FitField.PAYLOAD_COM),
}
UNITS = {
    FitField.COULOMB: "N",
    FitField.VISCOUS: "N*s/m",
    FitField.INERTIA: "kg*m^2",
    FitField.TORQUE_CONSTANT: "N*m/A",
    FitField.PAYLOAD_MASS: "kg",
    FitField.PAYLOAD_COM: "m",
}
SCALES = {  # a fitted value's scale where its start is 0
    FitField.COULOMB: 10.0,
    FitField.VISCOUS: 50.0,
    FitField.INERTIA: 1e-4,
    FitField.TORQUE_CONSTANT: 1.0,
    FitField.PAYLOAD_MASS: 1.0,
    FitField.PAYLOAD_COM: 0.05,
}


def value_range(field: FitField) -> tuple[float, float]:
    """The range a fitted value is held in: a drive field's (:func:`pusupu_jax.params.bounds`, its numeric ends),
    a mass from 0 up, a centre of mass anywhere."""
    if field is FitField.PAYLOAD_MASS:
        return 0.0, np.inf
    if field is FitField.PAYLOAD_COM:
        return -np.inf, np.inf
    b = bounds(next(f for f in dataclasses.fields(ServoParams) if f.name == field))
    if b is None:
        return -np.inf, np.inf
    return float(b[0]), float(b[1]) if isinstance(b[1], (int, float)) else np.inf


def drive_values(values: dict[FitField, Any], Kt: Any, Ke: Any) -> dict[str, Any]:
    """The drive fields of ``values`` by name, with the back-EMF constant carried by the torque constant: a fitted
    ``Kt`` sets ``Ke = Ke * Kt_fitted / Kt`` (``Kt``, ``Ke``: the machine file's, per axis [N m/A], [V s/rad]).  Both
    are the motor's flux linkage, in a ratio its datasheet's conventions fix.  Left at the machine file's value, the
    back-EMF of a true ``Kt`` 10 % away held a noise-free fit's residual at 2.2e-6 and its viscous friction 5 % off;
    with the true machine's ``Ke`` the same fit ended at 1e-12, every value within 3e-9 (docs/identify.md)."""
    drive = {str(f): v for f, v in values.items() if f.drive}
    if FitField.TORQUE_CONSTANT in values:
        drive["Ke"] = Ke * values[FitField.TORQUE_CONSTANT] / Kt
    return drive


def with_values(machine: Machine, values: dict[FitField, np.ndarray]) -> Machine:
    """``machine`` with the fields of ``values`` set (each ``(field.size,)``; ``Ke`` follows ``Kt``,
    :func:`drive_values`), named ``<name> identified``."""
    payload = machine.payload
    if FitField.PAYLOAD_MASS in values:
        payload = dataclasses.replace(payload, mass=float(values[FitField.PAYLOAD_MASS][0]))
    if FitField.PAYLOAD_COM in values:
        x, y, z = (float(c) for c in values[FitField.PAYLOAD_COM])
        payload = dataclasses.replace(payload, com=(x, y, z))
    as_arrays = {f: np.asarray(v, float) for f, v in values.items()}
    drives = drive_values(as_arrays, np.asarray(machine.drives["Kt"], float), np.asarray(machine.drives["Ke"], float))
    return dataclasses.replace(
        machine, name=f"{machine.name} identified", drives=machine.drives | drives, payload=payload
    )


def uncertainty_of(values: tuple[FittedValue, ...]) -> dict[str, np.ndarray]:
    """The identified machine file's ``uncertainty`` section (:data:`pusupu_jax.machine_file.UNCERTAINTY_FIELDS`):
    each fitted field's standard errors, in its unit, 0 for a value the logs did not excite (the machine file's value,
    kept: nothing to draw it from)."""
    out: dict[str, np.ndarray] = {}
    for v in values:
        errors = out.setdefault(str(v.field), np.zeros(v.field.size))
        errors[v.index] = v.std_error if v.excited else 0.0
    return {k: e.reshape(()) if k == FitField.PAYLOAD_MASS else e for k, e in out.items()}


def correlation_of(values: tuple[FittedValue, ...], matrix: np.ndarray) -> Correlation | None:
    """The ``uncertainty`` section's correlations (:class:`pusupu_jax.machine_file.Correlation`) between the values
    with a standard error above 0 (the excited ones), from ``matrix``, the fit's correlations between all ``values``
    in their order; None where fewer than two have one."""
    kept = [k for k, v in enumerate(values) if v.excited and v.std_error > 0]
    if len(kept) < 2:
        return None
    return Correlation(tuple(values[k].name for k in kept), np.asarray(matrix, float)[np.ix_(kept, kept)])


def strongest_correlations(
    values: tuple[FittedValue, ...], correlation: Any, least: float = 0.5, most: int = 5
) -> list[tuple[str, str, float]]:
    """Up to ``most`` pairs of ``values`` whose ``correlation`` (``(n, n)``, in their order) is at least ``least`` in
    size, the strongest first: ``(name, name, correlation)``, what the logs tell apart only in combination."""
    C = np.asarray(correlation, float)
    pairs = [
        (values[i].name, values[j].name, float(C[i, j]))
        for i in range(len(values))
        for j in range(i + 1, len(values))
        if abs(C[i, j]) >= least
    ]
    return sorted(pairs, key=lambda p: -abs(p[2]))[:most]


class Channel(enum.StrEnum):
    """What a log's drive effort is compared as: the measured current where the log has it, else the torque."""

    CURRENT = "current"  # A: what a drive measures; the torque a drive reports is its own Kt times it
    TORQUE = "torque"  # N m


class Derivatives(enum.StrEnum):
    """How the solver gets the residual's Jacobian."""

    EXACT = "exact"  # jax.jacfwd through the replay: one program, forward mode, one tangent per fitted value
    # scipy's 2-point differences of the residual: one more replay per fitted value at each Jacobian, and no
    # derivative through the model (a derivative-free anchor of benchmarks/bench_identify.py)
    FINITE_DIFFERENCES = "finite-differences"
    # MuJoCo's own solver, mujoco.minimize.least_squares (Gauss-Newton with a Levenberg-Marquardt regulariser and box
    # bounds, as mujoco.sysid uses it) on its forward differences of the residual, the perturbed replays of each
    # Jacobian run as one batch (jax.vmap): the other anchor
    MUJOCO_MINIMIZE = "mujoco-minimize"


WINDOW_S = 2.0  # [s] the replay of each log: the excitation path's motion (1.99 s) from rest
UNEXCITED_COLUMN = 1e-8  # a Jacobian column this small against the largest: the logs do not excite the value
UNEXCITED_ERROR = 0.5  # a standard error above this fraction of the value (or of its scale): not identified
COM_SCALE_M = 1e-3  # [m] the least distance a centre of mass's error is taken relative to (FittedValue.against)
# the residual evaluations one solve may take: a value the logs barely determine lets the solver crawl along a flat
# valley for thousands of them (a payload's centre of mass on a level path: 33 evaluations of 30 s each, the residual
# still falling by 3e-4 of itself per step); it stops here instead, and the standard errors show what is loose
MAX_EVALUATIONS = 50
# the solvers stop when a step cuts the cost (half the sum of squared residuals) by less than this fraction of it, or
# moves the values by less than XTOL of their size (scipy's ftol and xtol; mujoco.minimize has no ftol of its own, so
# _mujoco_minimize applies it after each iteration)
FTOL = 1e-9
XTOL = 1e-9
# the step check's own error, as a share of its move, added to the moved values' standard errors: the move takes the
# values from the replay's step h to a finer one, and a first-order step's bias, c h, leaves a quarter of the move from
# 250 to 50 us between 50 us and continuous time (Richardson); half is taken, for what is not first order.  Over
# twenty noisy copies of a bridge log, a quarter left three rotor inertias covered in 50-60 % of the seeds, half
# covered every value in at least 85 %; over twenty further copies, every value but one rotor inertia (75 %), whose
# bias left is larger than its move (docs/identify.md)
STEP_CHECK_ERROR = 0.5
OPEN_END = 1e6  # mujoco.minimize's bounds must be finite: an open end at this many times the value's scale


def fit_fields(text: str) -> tuple[FitField, ...]:
    """``--fit``'s comma-separated names (fields, or a group of :data:`FIT_GROUPS`) as fields, in order, once each."""
    out: list[FitField] = []
    for name in (n.strip() for n in text.split(",")):
        try:
            group = FIT_GROUPS.get(name) or (FitField(name),)
        except ValueError:
            known = ", ".join([*FIT_GROUPS, *(str(f) for f in FitField)])
            raise ParameterError(f"--fit: expected names among {known}, got {name!r}") from None
        out += [f for f in group if f not in out]
    return tuple(out)


@dataclasses.dataclass(frozen=True)
class FittedValue:
    """One value of one field (``index``: the axis of a drive field, the coordinate of the payload's centre of mass,
    both from 0): where the fit started, where it ended, its standard error (in the field's unit), and whether the
    logs excited it (if not, ``value`` is ``start``); ``step_correction``, what the step check moved it by (``value``
    less the fit's value at the replay's step; 0 without a step check: :func:`fit`)."""

    field: FitField
    index: int
    start: float
    value: float
    std_error: float
    excited: bool
    step_correction: float = 0.0

    @property
    def name(self) -> str:
        """``coulomb[3]`` (axis 3, from 1), ``payload_com.x``, ``payload_mass``."""
        return self.field.label(self.index)

    def as_dict(self) -> dict[str, Any]:
        return {
            "field": str(self.field),
            "index": self.index,
            "name": self.name,
            "unit": UNITS[self.field],
            "start": self.start,
            "value": self.value,
            "std_error": self.std_error,
            "excited": self.excited,
            "step_correction": self.step_correction,
        }

    def against(self, truth: Machine) -> dict[str, Any]:
        """:meth:`as_dict` with the ``truth``'s value of the same field and index (a machine whose values are known:
        a simulated robot's), the error, the error relative to the truth (a centre-of-mass coordinate's to the
        truth's distance from the platform's centre, at least :data:`COM_SCALE_M`; None for a truth of 0) and
        whether the 95 % interval (1.96 standard errors) covers the truth."""
        true = float(self.field.start(truth)[self.index])
        scale = (
            max(float(np.linalg.norm(truth.payload.com)), COM_SCALE_M) if self.field is FitField.PAYLOAD_COM else true
        )
        return self.as_dict() | {
            "true": true,
            "error": self.value - true,
            "relative_error": abs(self.value - true) / abs(scale) if scale else None,
            "covered_95": bool(abs(self.value - true) <= 1.96 * self.std_error),
        }


@dataclasses.dataclass(frozen=True)
class FitReport:
    """What :func:`fit` found: every fitted value, the residual's RMS before and after (at the replay's step, after:
    at the values the solver found, before a step check's move), the samples and the window,
    the replay's mechanical step [s], the solver's work (``converged``: False where it stopped at
    :data:`MAX_EVALUATIONS`; ``derivatives``: the Jacobian it took; ``residual_calls``: every replay of the residual,
    finite differences included; ``residual_s``, ``jacobian_s``: seconds in the residual's and the Jacobian's calls,
    compiles left out; ``trace``: after each residual call, those seconds so far and the least residual RMS met so
    far), the correlations between the values (``correlation``, in their order: the covariance from the Jacobian at
    the optimum over the standard errors; an unexcited value's row 0 but for its 1 on the diagonal), the samples over
    which the standard errors counted the residual's correlation in time (``error_bandwidth``:
    :func:`pusupu_jax.fit_errors.covariance`), the logs (path, SHA-256, what wrote them, and for a bridge log over
    UDP what its timing changed in the replay: :meth:`Commands.counts`), and with a step check (:func:`fit`) its step
    [s] and the finer replay's residual RMS at the values fitted at the replay's step and at the values moved
    (``step_check_rms``), and the seconds it took, its compile included (``step_check_wall_s``)."""

    values: tuple[FittedValue, ...]
    correlation: tuple[tuple[float, ...], ...]
    residual_rms_before: float
    residual_rms_after: float
    samples: int
    window_s: float
    mech_step_s: float
    evaluations: int
    jacobians: int
    derivatives: Derivatives
    residual_calls: int
    residual_s: float
    jacobian_s: float
    trace: tuple[tuple[float, float], ...]
    solver_message: str
    converged: bool
    wall_s: float
    logs: tuple[dict[str, Any], ...]
    error_bandwidth: int = 0
    step_check_s: float | None = None
    step_check_rms: tuple[float, float] | None = None
    step_check_wall_s: float = 0.0

    def as_dict(self) -> dict[str, Any]:
        values = [v.as_dict() for v in self.values]
        return dataclasses.asdict(self) | {
            "values": values,
            "derivatives": str(self.derivatives),
            "step_check_moved": self.step_check_moved,
        }

    @property
    def step_check_moved(self) -> bool:
        """Whether a step check moved the values: its move lowered the finer replay's residual."""
        return self.step_check_rms is not None and self.step_check_rms[1] < self.step_check_rms[0]

    def unexcited(self) -> list[FittedValue]:
        return [v for v in self.values if not v.excited]


@dataclasses.dataclass(frozen=True)
class Replay:
    """One log's replay: the jitted ``run(values) -> (effort, theta)`` (``values``: ``{field: (field.size,)}``) at
    the logged samples ``(n, n_axes)``, the
    effort in the log's ``channel`` (current [A] where the log has it, else torque [N m]), and the logged ``effort``
    and ``position`` there; ``t`` [s] along the path; ``steps``, what the replay runs (:func:`bridge_commands`)."""

    run: Callable[[dict[FitField, jax.Array]], tuple[jax.Array, jax.Array]]
    channel: Channel
    effort: np.ndarray
    position: np.ndarray
    reference: np.ndarray
    t: np.ndarray
    steps: Commands


def check_log(log: DriveLog, trajectory: str | None = None, given_as: str = "trajectory") -> str:
    """The path spec that ``log`` is replayed along (``trajectory``, else the log's own), after checking the log's
    mode and that spec; :class:`ParameterError` naming the log, or ``given_as`` for a ``trajectory`` given (the
    command's ``--trajectory``), otherwise.  Cheap: called on every log before any work, and again by the replay."""
    if log.mode not in MACHINE_MODES:
        raise ParameterError(f"{log.path}: mode: expected one of {tuple(map(str, MACHINE_MODES))}, got {log.mode!r}")
    if trajectory:
        return check_spec(trajectory, given_as)
    if not log.trajectory:
        raise ParameterError(
            f"{log.path}: expected the path it ran (a '# trajectory:' line or --trajectory), found none"
        )
    return check_spec(log.trajectory, f"{log.path}: trajectory")


def _replay(
    log: DriveLog,
    machine: Machine,
    gains: ServoParams,
    hybrid: HybridGains | None,
    rates: LoopRates,
    window_s: float,
    trajectory: str | None,
    mech_step: float | None,
) -> Replay:
    """The closed-loop replay of ``log``'s first ``window_s`` seconds on ``machine`` under ``gains``, checked against
    the log: its mode, rate and reference; the MJX machine stepped every ``mech_step`` [s] (None: the model's).
    Where the machine has encoders (``encoder_counts``), its drives take their speed from their counts, as the
    mean over each velocity period (:func:`pusupu_jax.sim.pieces`' ``counted_speed``; at the model's step the same
    speed): the replay at a finer step then sees what such drives see."""
    spec = check_log(log, trajectory)
    options = machine.options(None if mech_step is None else ModelOptions(timestep=mech_step))
    rates = machine_rates(options, rates)
    path = platform_path_from(spec, machine.geometry.home, rates)
    n = min(int(round(window_s / rates.dt_position)), len(path))
    row = np.rint(log.path_time / rates.dt_position).astype(int)  # the position period of each sample's reference
    steps = bridge_commands(log, row, rates.dt_position, n)
    keep = (steps.index >= 0) & (steps.index < len(steps.rows))
    if keep.sum() < 2:
        raise ParameterError(
            f"{log.path}: expected samples in the first {window_s:g} s of the path, found fewer than 2"
        )
    index = steps.index[keep]
    servo = machine.servo(gains)
    # the whole path checked and referenced, as the run it was, then the rows its commands took: cut at the window's
    # end, it would be checked as a path that stops there at once (a window ending at speed refused as beyond the
    # drives)
    whole = machine_reference(servo, path, log.mode, options=options, rates=rates, geom=machine.geometry)
    reference = jax.tree.map(lambda x: x[steps.rows], whole)
    if steps.timed:
        reference = Commanded(reference, jnp.asarray(steps.taken), jnp.asarray(steps.age))
    theta_ref = np.asarray(cast(HybridReference, whole).theta if control_mode(log.mode).hybrid else whole)[row[keep]]
    off = float(np.abs(theta_ref - log.reference[keep]).max())
    if off > 1e-6:
        raise ParameterError(
            f"{log.path}: expected the reference of the path {spec!r} on this machine, found one {off:.3g} rad "
            "away (another path, geometry or rate: give --trajectory or --machine)"
        )
    nominal = dataclasses.replace(
        options, kin_error_seed=None, payload=0.0, payload_com=(0.0, 0.0, 0.0), payload_inertia=(0.0, 0.0, 0.0)
    )
    plant = machine_plant(nominal)
    model = plant.variant(options, machine.geometry)
    mode, hybrid = log.mode, hybrid if control_mode(log.mode).hybrid else None
    channel = Channel.TORQUE if log.current is None else Channel.CURRENT

    payload = plant.mj_model.body("payload").id  # welded to the platform at its centre of mass (plant.model)
    counted = machine.encoder_counts is not None  # its drives take their speed from the encoders' counts

    @jax.jit
    def run(values: dict[FitField, jax.Array]) -> tuple[jax.Array, jax.Array]:
        fitted = model
        if FitField.PAYLOAD_MASS in values or FitField.PAYLOAD_COM in values:  # and what MuJoCo derives from them
            mass, pos = model.body_mass, model.body_pos
            if FitField.PAYLOAD_MASS in values:
                mass = mass.at[payload].set(values[FitField.PAYLOAD_MASS][0])
            if FitField.PAYLOAD_COM in values:
                pos = pos.at[payload].set(values[FitField.PAYLOAD_COM])
            fitted = plant.with_masses(model, mass, pos)
        trace = rollout(
            servo.replace(**drive_values(values, servo.Kt, servo.Ke)),
            fitted,
            reference,
            plant=plant,
            rates=rates,
            outer=mode,
            hybrid=hybrid,
            counted_speed=counted,
        )
        effort = trace.current if channel is Channel.CURRENT else trace.torque
        return effort[index], trace.theta[index]

    logged = log.current if log.current is not None else log.torque
    return Replay(
        run, channel, logged[keep], log.position[keep], log.reference[keep], row[keep] * rates.dt_position, steps
    )


@dataclasses.dataclass(frozen=True)
class Commands:
    """What a replay runs of a log, in a window: per step ``(m,)`` the path's reference row (``rows``), whether the
    robot ran a period under it (``taken``) and how many of its periods old the encoders were that the position loop
    read (``age``), with the replay's sample of each logged sample (``index``: the step whose start it is; outside
    ``[0, m)`` where no step of the window answers it).  ``timed``: the steps are a bridge's commands
    (:func:`bridge_commands`), not every row in turn."""

    rows: np.ndarray
    taken: np.ndarray
    age: np.ndarray
    index: np.ndarray
    timed: bool

    def counts(self) -> dict[str, int] | None:
        """What the timing changed, for the report: the commands replayed, those the robot did not run, those
        computed from older encoders, the rows stepped over (skipped cycles); None for every row in turn."""
        if not self.timed:
            return None
        return {
            "commands": len(self.rows),
            "not_run": int((~self.taken).sum()),
            "older_feedback": int((self.age > 0).sum()),
            "rows_stepped_over": int(self.rows[-1] + 1 - len(self.rows)) if len(self.rows) else 0,
        }


def bridge_commands(log: DriveLog, row: np.ndarray, dt: float, n: int) -> Commands:
    """The steps of a replay of ``log`` in a window of ``n`` position periods of ``dt`` [s] (``row``: the path's row
    of each logged sample's reference).

    A simulation's log takes every row in turn: step ``i`` is row ``i``, and a sample of row ``p`` is the start of
    step ``p``.  A bridge's run does not always go so.  A cycle the bridge skipped on a late wake-up
    (:class:`~pusupu_jax.hw_bridge.runner.CycleRunner`) sent no command: the next command's row steps over it.  A
    robot that found two commands waiting ran one period, under the newer; the bridge's position loop had stepped
    on both.  And a command computed before the last period's feedback came was computed from older encoders.  A
    bridge log over UDP says all of it (``log.timing``: every command with its row and the feedback it answered,
    every feedback packet with the command the robot ran); the replay's steps are then the commands from the path's
    first row, each with whether the robot ran it and the age of its feedback (:class:`~pusupu_jax.sim.Commanded`,
    an age past ``AGES - 1`` taken as that), and a sample is the start of the step after the command it answers.
    Logs without timing, and runs with several commands a row (CST axes: the bridge cycles at the velocity loop's
    rate), take every row in turn."""
    every = Commands(np.arange(n), np.ones(n, bool), np.zeros(n, np.int32), row, False)
    timing = log.timing
    given = None if timing is None else np.rint(timing.path_time / dt).astype(int)
    if timing is None or given is None or (np.diff(given) == 0).any() or not (given >= 0).any():
        return every
    first = int(np.argmax(given >= 0))  # the path's first command (before it: the takeover ramp's)
    sequence = timing.sequence[first:]
    taken = np.isin(sequence, timing.sample_ack)
    before = np.concatenate([[0], np.cumsum(taken)[:-1]])  # the periods the robot ran before each command
    # each sample: the command it answers among the path's, and the robot's periods to it (0: before the path's)
    at = np.searchsorted(sequence, timing.sample_ack)
    answers = (at < len(sequence)) & (sequence[np.minimum(at, len(sequence) - 1)] == timing.sample_ack)
    periods = np.where(answers, before[np.minimum(at, len(sequence) - 1)] + 1, 0)
    # each command: the periods to the feedback it was computed from, as the sample of that packet says
    k = np.searchsorted(timing.sample_sequence, timing.feedback[first:])
    found = (k < len(periods)) & (timing.sample_sequence[np.minimum(k, len(periods) - 1)] == timing.feedback[first:])
    age = np.clip(before - np.where(found, periods[np.minimum(k, len(periods) - 1)], 0), 0, AGES - 1)
    # the commands of the window's rows, to the one after the last a sample answers, whose start that sample is
    # (after it, whether the robot ran them is not in the log, and no sample needs them)
    last = int(np.flatnonzero(taken)[-1]) if taken.any() else -2
    m = min(int(np.searchsorted(given[first:], n)), last + 2)
    taken = taken | (np.arange(len(taken)) > last)  # that one: taken as run (nothing in the window depends on it)
    # a sample answering the command before the path's first (the takeover ramp's last) is the replay's start
    start = (timing.sample_ack == timing.sequence[first - 1]) if first > 0 else np.zeros(len(at), bool)
    index = np.where(answers, at + 1, np.where(start, 0, -1))
    return Commands(given[first:][:m], taken[:m], age[:m].astype(np.int32), index, True)


@dataclasses.dataclass(frozen=True)
class Solution:
    """What :func:`least_squares_excited` found: the values ``x`` (the unexcited ones at their start), their standard
    errors, their correlations (``correlation`` ``(n, n)``: an unexcited value's row 0 but for its diagonal), which
    were excited, the residual at the start, the solver's last message and whether it converged, and
    over every solve the residual and Jacobian evaluations, the residual calls (each replay: a batch of differences
    counts its width), the seconds in the residual's and the Jacobian's calls, and ``trace``: after each residual
    call, the seconds of calls so far and the least residual RMS met so far; ``bandwidth``, the samples over which
    the standard errors counted the residual's correlation (:func:`pusupu_jax.fit_errors.covariance`; 0 without
    ``samples``); ``jacobian`` ``(n, p)``, the residual's Jacobian at ``x`` in the excited values' columns (the
    others 0)."""

    x: np.ndarray
    std: np.ndarray
    correlation: np.ndarray
    excited: np.ndarray
    residual_before: np.ndarray
    message: str
    converged: bool
    evaluations: int
    jacobians: int
    residual_calls: int
    residual_s: float
    jacobian_s: float
    trace: tuple[tuple[float, float], ...]
    bandwidth: int
    jacobian: np.ndarray


@dataclasses.dataclass(frozen=True)
class _Solved:
    """One solve's end: the values (the free ones), the Jacobian and the residual there, the solver's evaluations of
    the residual and of the Jacobian, its message and whether it converged; its cost, half the sum of squared
    residuals, from the residual."""

    x: np.ndarray
    jac: np.ndarray
    residual: np.ndarray
    evaluations: int
    jacobians: int
    message: str
    converged: bool

    @property
    def cost(self) -> float:
        """Half the sum of squared residuals."""
        return 0.5 * float(self.residual @ self.residual)


def value_errors(
    J: np.ndarray,
    r: np.ndarray,
    samples: tuple[np.ndarray, list[int]] | None,
    added_variance: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray, int]:
    """The standard errors and the correlations of a least-squares fit's values at its optimum, and the bandwidth
    they took: ``J`` ``(n, p)`` the residual's Jacobian there, ``r`` ``(n,)`` the residual; the covariance of
    :func:`pusupu_jax.fit_errors.covariance` with ``samples`` (each entry's sample, the samples of each log), else the
    textbook one (:func:`pusupu_jax.fit_errors.textbook`), with ``added_variance`` ``(p,)`` (independent errors
    besides the residual's, in the values' squared units) added to its diagonal."""
    if samples is not None:
        found = fit_errors.covariance(J, r, *samples)
        covariance, bandwidth = found.covariance, found.bandwidth
    else:
        covariance, bandwidth = fit_errors.textbook(J, r), 0
    if added_variance is not None:
        covariance = covariance + np.diag(added_variance)
    std = np.sqrt(np.maximum(np.diag(covariance), 0.0))
    scale = np.where(std > 0, std, 1.0)
    correlation = covariance / np.outer(scale, scale)
    # semi-definite and of unit diagonal to rounding, however ill-conditioned J^T J (the machine file checks it)
    eigenvalues, eigenvectors = np.linalg.eigh((correlation + correlation.T) / 2)
    correlation = (eigenvectors * np.maximum(eigenvalues, 0.0)) @ eigenvectors.T
    unit = np.sqrt(np.where(np.diag(correlation) > 0, np.diag(correlation), 1.0))
    correlation = np.clip(correlation / np.outer(unit, unit), -1.0, 1.0)
    np.fill_diagonal(correlation, 1.0)
    return std, correlation, bandwidth


def least_squares_excited(
    residual_of: Callable[[np.ndarray], tuple[Callable[[jax.Array], jax.Array], Callable[[jax.Array], jax.Array]]],
    start: np.ndarray,
    low: np.ndarray,
    high: np.ndarray,
    say: Callable[[str], object] = lambda line: None,
    derivatives: Derivatives = Derivatives.EXACT,
    samples: tuple[np.ndarray, list[int]] | None = None,
) -> Solution:
    """Bounded least squares from ``start`` inside ``[low, high]``, with standard errors from the Jacobian at the
    optimum, that invents no value the data do not excite.

    ``samples``: each residual entry's sample and the samples of each log (:func:`pusupu_jax.fit_errors.covariance`),
    whose standard errors count the residual's correlation in time; without it, the textbook ``s^2 (J^T J)^-1``
    (each entry independent).

    ``derivatives``: the solver and the Jacobian it takes (:class:`Derivatives`): scipy's trust-region reflective
    solver with the exact Jacobian (``residual_of``'s) or with its finite differences of the residual, or MuJoCo's
    ``mujoco.minimize.least_squares`` with its own.  The Solution counts every residual call (the finite
    differences' included) and the seconds spent in the residual's and in the Jacobian's calls, each program's first
    call (its compile) left out.

    ``residual_of(free)`` gives the residual and its Jacobian as functions of the values at the indices ``free``
    (the others held at their start).  A value whose Jacobian column is below :data:`UNEXCITED_COLUMN` of the largest,
    or whose standard error is above :data:`UNEXCITED_ERROR` of its size (or of 1), is not excited: it keeps its
    start, and the others are fitted again without it.  With none excited, every value keeps its start."""
    residual_times: list[float] = []  # s, each residual call's (the finite differences' included)
    jacobian_times: list[float] = []  # s, each exact Jacobian's call
    calls = [0]  # replays: a batch of differences counts its width
    trace: list[tuple[float, float]] = []

    def timed(fun: Callable[[jax.Array], jax.Array], p: np.ndarray, times: list[float]) -> np.ndarray:
        t = time.perf_counter()
        out = np.asarray(fun(jnp.asarray(p)))
        times.append(time.perf_counter() - t)
        return out

    def traced(r: np.ndarray, width: int) -> None:
        """Count a call of ``width`` replays (``r``'s columns where it has several)."""
        calls[0] += width
        best = min(float(np.min(np.sqrt(np.mean(r**2, axis=0)))), trace[-1][1] if trace else np.inf)
        trace.append((sum(residual_times) + sum(jacobian_times), best))

    def solve(free: np.ndarray) -> tuple[_Solved, np.ndarray]:
        f, jac = residual_of(free)
        p0 = start[free]
        r0 = np.asarray(f(jnp.asarray(p0)))
        how = {
            Derivatives.EXACT: "trust-region least squares",
            Derivatives.FINITE_DIFFERENCES: "trust-region least squares, finite-difference Jacobian",
            Derivatives.MUJOCO_MINIMIZE: "mujoco.minimize, finite-difference Jacobian",
        }[derivatives]
        say(f"identify: fitting {len(free)} values ({how}, each inside its field's range)")
        evaluated = [0]

        def residual(p: np.ndarray) -> np.ndarray:
            r = timed(f, p, residual_times)
            traced(r, 1)
            evaluated[0] += 1
            say(f"identify: evaluation {evaluated[0]}: residual RMS {np.sqrt(np.mean(r**2)):.6g}")
            return r

        if derivatives is Derivatives.MUJOCO_MINIMIZE:  # its differences: each Jacobian's replays as one batch
            mesh = devices.row_mesh(p0.size)  # the points laid over the devices (one per CPU core)
            batch = jax.jit(lambda points: jax.vmap(f)(devices.spread_rows(points, mesh)))
            np.asarray(batch(jnp.asarray(np.repeat(p0[None], p0.size, axis=0))))  # compiled and run, outside timing

            def differences(points: np.ndarray) -> np.ndarray:
                r = timed(batch, points, residual_times)
                traced(r.T, len(points))
                return r

            return _mujoco_minimize(residual, differences, p0, low[free], high[free]), r0
        if derivatives is Derivatives.EXACT:
            np.asarray(jac(jnp.asarray(p0)))  # its compile and run, waited for, outside the timed calls
        from scipy.optimize import least_squares

        sol = least_squares(
            residual,
            p0,
            jac=(lambda p: timed(jac, p, jacobian_times)) if derivatives is Derivatives.EXACT else "2-point",
            bounds=(low[free], high[free]),
            method="trf",
            xtol=XTOL,
            ftol=FTOL,
            max_nfev=MAX_EVALUATIONS,
        )
        J = np.asarray(jac(jnp.asarray(sol.x))) if derivatives is Derivatives.EXACT else np.asarray(sol.jac)
        solved = _Solved(
            sol.x, J, np.asarray(sol.fun), int(sol.nfev), int(sol.njev or 0), str(sol.message),
            sol.status > 0,
        )  # fmt: skip
        return solved, r0

    free = np.arange(start.size)
    solved, r0 = solve(free)
    std, correlation, bandwidth = value_errors(solved.jac, solved.residual, samples)
    norms = np.linalg.norm(solved.jac, axis=0)
    x = solved.x
    excited = (norms > UNEXCITED_COLUMN * norms.max()) & (std < UNEXCITED_ERROR * np.maximum(np.abs(x), 1.0))
    evaluations, jacobians = solved.evaluations, solved.jacobians
    jacobian = solved.jac * excited  # the unexcited values' columns 0
    if not excited.all() and excited.any():
        say(f"identify: {int((~excited).sum())} value(s) not excited by the logs: fitting the others again")
        kept = free[excited]
        again, _ = solve(kept)
        x = start.copy()
        x[kept] = again.x
        std[kept], kept_correlation, bandwidth = value_errors(again.jac, again.residual, samples)
        correlation = np.eye(start.size)
        correlation[np.ix_(kept, kept)] = kept_correlation
        solved, evaluations, jacobians = again, evaluations + again.evaluations, jacobians + again.jacobians
        jacobian = np.zeros((again.jac.shape[0], start.size))
        jacobian[:, kept] = again.jac
    elif not excited.any():
        x = start.copy()
        correlation = np.eye(start.size)
    return Solution(
        x, std, correlation, excited, r0, solved.message, solved.converged, evaluations, jacobians, calls[0],
        sum(residual_times), sum(jacobian_times), tuple(trace), bandwidth, jacobian,
    )  # fmt: skip


def _mujoco_minimize(
    residual: Callable[[np.ndarray], np.ndarray],
    differences: Callable[[np.ndarray], np.ndarray],
    p0: np.ndarray,
    low: np.ndarray,
    high: np.ndarray,
) -> _Solved:
    """One solve by ``mujoco.minimize.least_squares`` (its tolerances as scipy's here, at most
    :data:`MAX_EVALUATIONS` iterations).  It asks for the residual at one point (``residual(p)``) or, for its forward
    differences, at one point per value at once (the columns of a matrix: ``differences(points)``, the points as
    rows, one batch of replays).  The Jacobian at the end is its differences there.  It takes finite bounds only: an
    open end (a mass's, a centre of mass's) becomes :data:`OPEN_END` times the value's scale.

    Its own rules stop on a small step or gradient, or when no step passes its sufficient-decrease test even with the
    regulariser at its limit.  On a log the model cannot match exactly, the last of these came only after some
    hundred rejected steps, one replay each, raised the regulariser to its limit; so it also stops, as scipy's solver
    does, after an iteration whose step cuts the cost by less than :data:`FTOL` of it.  It then ends at that step,
    its residual replayed once more, with the Jacobian of the iteration's start (the step changed the cost by less
    than that fraction)."""
    import io

    from mujoco import minimize

    evaluations, jacobians = [0], [0]

    class Settled(Exception):
        """An iteration cut the cost by less than FTOL of it."""

    seen: list[Any] = []  # the solver's iterations so far

    def settled(trace: list[Any]) -> None:
        seen[:] = trace
        last = trace[-1]
        if last.step is not None and 0 <= last.reduction < FTOL * last.objective:
            raise Settled

    def columns(points: np.ndarray) -> np.ndarray:
        if points.ndim == 1 or points.shape[1] == 1:
            evaluations[0] += 1
            return residual(points.reshape(-1))[:, None]
        jacobians[0] += 1
        return differences(points.T).T

    out = io.StringIO()
    box = [np.nan_to_num(low, neginf=-OPEN_END), np.nan_to_num(high, posinf=OPEN_END)]
    try:
        x, trace = minimize.least_squares(
            p0, columns, bounds=box, xtol=XTOL, gtol=1e-8, max_iter=MAX_EVALUATIONS,
            verbose=minimize.Verbosity.FULLITER, output=out, iter_callback=settled,
        )  # fmt: skip
    except Settled:
        last = seen[-1]
        x = np.clip((last.candidate + last.step).reshape(-1), box[0], box[1])
        r = columns(x[:, None]).reshape(-1)
        message = f"Terminated after {len(seen)} iterations: cost reduction under {FTOL:g} of the cost (ftol)"
        return _Solved(
            x, np.asarray(last.jacobian), r, evaluations[0], jacobians[0], message, True
        )  # fmt: skip
    end = trace[-1]
    r = np.asarray(end.residual).reshape(-1)
    lines = out.getvalue().strip().splitlines()
    return _Solved(
        x, np.asarray(end.jacobian), r, evaluations[0], jacobians[0],
        next((line for line in lines if line.startswith("Terminated")), ""), len(trace) - 1 < MAX_EVALUATIONS,
    )  # fmt: skip


def gauss_newton_step(J: np.ndarray, change: np.ndarray) -> np.ndarray:
    """The values' move ``-(J^T J)^+ J^T change`` of one Gauss-Newton step from an optimum of a residual to that of
    another close to it: ``J`` ``(n, p)`` the first residual's Jacobian at its optimum (a value's column 0: no move),
    ``change`` ``(n,)`` the second residual less the first there (the second's Jacobian taken as ``J``).  Exact for
    residuals linear in the values with one Jacobian.  Solved as the least-squares problem ``J dx = -change`` (the
    least-norm answer), not through ``J^T J``, whose condition is the square of ``J``'s."""
    move: np.ndarray = np.linalg.lstsq(J, -change, rcond=None)[0]
    return move


@dataclasses.dataclass(frozen=True)
class StepCheckChoice:
    """The step check taken where none is asked for (:func:`default_step_check`): ``step`` [s], None for none, and
    ``why``, in words for the terminal."""

    step: float | None
    why: str


def default_step_check(
    logs: list[DriveLog], mech_step: float | None, rates: LoopRates = LoopRates()
) -> StepCheckChoice:
    """``pusupu identify``'s step check where none is asked for: one step a current-loop tick (``rates``'
    ``dt_current``) for logs of a robot (a bridge's, a CSV drive table), whose machine runs in continuous time, finer
    than the replay's step; none where every log is the fitting model's own at the model's step (``source``
    :data:`pusupu_jax.run_log.SIM_SOURCE`), which the finer step would move the values away from, or where the
    replay already steps once a tick (``mech_step`` [s]; None: the model's)."""
    replay = ModelOptions().timestep if mech_step is None else mech_step
    if all(log.source == SIM_SOURCE for log in logs):
        return StepCheckChoice(None, "the logs are pusupu sim's, the model's own at its step")
    if replay <= rates.dt_current * (1 + 1e-9):
        return StepCheckChoice(None, "the replay steps once a current-loop tick")
    return StepCheckChoice(rates.dt_current, "the logs are a robot's, which runs finer than the replay's step")


def check_step_check(
    step_check: float, mech_step: float | None, rates: LoopRates = LoopRates(), name: str = "step check"
) -> None:
    """ParameterError in one line naming ``name`` unless ``step_check`` [s] is a step the replay can take
    (:func:`check_mech_step`) finer than ``mech_step`` (None: the model's)."""
    check_mech_step(step_check, rates, name)
    replay = ModelOptions().timestep if mech_step is None else mech_step
    if not step_check < replay * (1 - 1e-9):
        raise ParameterError(f"{name}: expected a step finer than the replay's {replay:g} s, got {step_check:g} s")


def check_mech_step(mech_step: float | None, rates: LoopRates = LoopRates(), name: str = "mech step") -> None:
    """ParameterError in one line naming ``name`` unless ``mech_step`` [s] is None (the model's step) or a whole
    number of ``rates``' current-loop ticks that divides the velocity period: the steps the replay's MJX machine can
    take."""
    ticks = [k for k in range(1, rates.n_velocity + 1) if rates.n_velocity % k == 0]
    if mech_step is None or any(np.isclose(mech_step, k * rates.dt_current, rtol=1e-9, atol=0) for k in ticks):
        return
    raise ParameterError(
        f"{name}: expected a whole number of current-loop ticks that divides the velocity period, one of "
        f"{', '.join(f'{k * rates.dt_current:g}' for k in ticks)} s, got {mech_step!r}"
    )


def fit(
    logs: list[DriveLog],
    machine: Machine,
    gains: ServoParams,
    hybrid: HybridGains | None = None,
    rates: LoopRates = LoopRates(),
    fields: tuple[FitField, ...] = FIT_GROUPS["friction"],
    window_s: float = WINDOW_S,
    trajectory: str | None = None,
    progress: Callable[[str], object] | None = None,
    derivatives: Derivatives = Derivatives.EXACT,
    mech_step: float | None = None,
    step_check: float | None = None,
) -> tuple[FitReport, Machine, list[dict[str, Any]]]:
    """Fit ``fields`` of ``machine`` (its values are the start) to ``logs``, each replayed over its first
    ``window_s`` [s] with ``gains`` (``hybrid``: a hybrid log's gains; ``rates``: the gains' rates; ``trajectory``:
    the path, where not the logs' own).  Returns the report, the machine with the fitted values (the unexcited ones
    as they were), and per log the arrays of the plot (``channel``, ``t``, logged and replayed efforts before and
    after).
    ``progress(line)`` is told what runs (compiles take about half a minute each on 2 CPU cores).  ``derivatives``:
    the solver's Jacobian (:class:`Derivatives`: the exact one, or finite differences to compare with).
    ``mech_step`` [s]: the replay's mechanical step (:func:`check_mech_step`; None: the model's, 0.25 ms, as the
    tuner steps it); a finer one is closer to a robot and costs time in proportion.

    ``step_check`` [s], a step finer than the replay's (None: no check): for logs of a robot, which the replay's step
    misses by a bias that the residual left after the fit does not show.  The fitted values are replayed at that step,
    and moved by one Gauss-Newton step on its residual (:func:`gauss_newton_step`, with the Jacobian at the optimum):
    the values a fit at the finer step would find, for two replays at it.  The move is kept where it lowers the finer
    replay's residual.  The moved values' standard errors and correlations are then those of a fit at the finer
    step (:func:`value_errors` of its residual at them, with the Jacobian at the optimum), with the check's own
    error, :data:`STEP_CHECK_ERROR` of each value's move, added to each variance.  Against a bridge log of
    the simulated robot stepped four times per current-loop tick, the 28 values of the default set came within 0.75 %
    of the truth this way (7.5 % without), as a fit at the 50 us step did (``docs/identify.md``).  A log of
    ``pusupu sim`` at the model's step is the replay itself: the finer step would move its values away from its truth
    (:func:`default_step_check`, ``pusupu identify``'s choice).  JAX must compute in float64
    (:func:`pusupu_jax.runtime.setup_jax`; a RuntimeError otherwise)."""
    require_x64("identify's replays and their Jacobians")
    say = progress or (lambda line: None)
    t0 = time.perf_counter()
    # every fitted value in one vector, field after field (each field.size long), scaled by its start (or SCALES)
    starts = np.concatenate([f.start(machine) for f in fields])
    owner = [(f, k) for f in fields for k in range(f.size)]
    scale = np.array([abs(v) if v != 0 else SCALES[f] for v, (f, _) in zip(starts, owner)])
    low = np.array([value_range(f)[0] for f, _ in owner]) / scale
    high = np.array([value_range(f)[1] for f, _ in owner]) / scale
    ends = np.cumsum([0, *(f.size for f in fields)])

    def split(x: Any) -> dict[FitField, Any]:
        """The vector of every fitted value (unscaled) as ``{field: its values}``."""
        return {f: x[ends[i] : ends[i + 1]] for i, f in enumerate(fields)}

    for log in logs if FitField.TORQUE_CONSTANT in fields else ():
        if log.current is None:
            raise ParameterError(
                f"{log.path}: expected measured currents to fit Kt (protocol version 2, sim --log, or a CSV's "
                "current_a columns), found torques only"
            )
    check_mech_step(mech_step, rates)
    if step_check is not None:
        check_step_check(step_check, mech_step, rates)
    replays = [_replay(log, machine, gains, hybrid, rates, window_s, trajectory, mech_step) for log in logs]
    for log, r in zip(logs, replays):
        if (c := r.steps.counts()) is not None:
            say(
                f"identify: {log.path}: the bridge's {c['commands']} commands as the robot ran them: "
                f"{c['not_run']} not run (a newer one was waiting), {c['older_feedback']} on older feedback, "
                f"{c['rows_stepped_over']} rows stepped over (skipped cycles)"
            )
    if FitField.TORQUE_CONSTANT in fields:
        for log in logs:
            if control_mode(log.mode).hybrid:
                raise ParameterError(
                    f"{log.path}: expected a log of a position mode to fit Kt, got {log.mode!r} (the force law's "
                    "current F r / (eta Kt) takes Kt as the controller was told, not as the motor is)"
                )
    scales = {  # the RMS of each channel's logged efforts over every log, so that both count alike
        c: max(float(np.sqrt(np.mean(np.concatenate(efforts) ** 2))), 1e-12)
        for c in Channel
        if (efforts := [r.effort.ravel() for r in replays if r.channel is c])
    }
    tracking = np.concatenate([(r.position - r.reference).ravel() for r in replays])
    s_theta = max(float(np.sqrt(np.mean(tracking**2))), 1e-12)

    # the logged data are the programs' arguments, not constants inside them: a fit of other logs of the same
    # shapes (another noise draw, another run of the path) traces the same programs and finds them compiled in the
    # persistent cache
    data = (
        jnp.asarray(scale),
        [(jnp.asarray(r.effort), jnp.asarray(r.position), scales[r.channel]) for r in replays],
        s_theta,
    )
    x0 = jnp.asarray(starts / scale)

    def residual_of_replays(replays: list[Replay]) -> Callable[[jax.Array, Any], jax.Array]:
        def residual(x: jax.Array, data: Any) -> jax.Array:
            """The residual of ``replays`` at every fitted value ``x`` (scaled)."""
            unit, logged, s_th = data
            values = split(x * unit)
            parts = []
            for r, (effort_log, position_log, s_e) in zip(replays, logged):
                effort, theta = r.run(values)
                parts += [((effort - effort_log) / s_e).ravel(), ((theta - position_log) / s_th).ravel()]
            return jnp.concatenate(parts)

        return residual

    # one program pair for every set of free values: a refit without the unexcited ones compiles nothing new
    residual = residual_of_replays(replays)
    residual_all, jacobian_all = jax.jit(residual), jax.jit(jax.jacfwd(residual))

    def residual_of(free: np.ndarray) -> tuple[Callable[[jax.Array], jax.Array], Callable[[jax.Array], jax.Array]]:
        """The residual as a function of the free values (scaled), the others held at their start, and its Jacobian
        (the full one's columns of the free values)."""

        def at(p: jax.Array) -> jax.Array:
            return x0.at[free].set(p)

        return (lambda p: residual_all(at(p), data)), (lambda p: jacobian_all(at(p), data)[:, free])

    say(f"identify: compiling the replay and its Jacobian ({starts.size} values; cached for logs of these shapes)")
    # each residual entry's sample (per log: the efforts' (n, n_axes) entries, then the angles'), for the standard
    # errors' count of the residual's correlation in time
    lengths = [len(r.t) for r in replays]
    offsets = np.cumsum([0, *lengths])
    rows = [np.repeat(np.arange(n) + at, r.effort.shape[1]) for n, at, r in zip(lengths, offsets, replays)]
    samples = np.concatenate([np.concatenate([k, k]) for k in rows])
    solution = least_squares_excited(residual_of, starts / scale, low, high, say, derivatives, (samples, lengths))
    r0 = solution.residual_before
    r1 = np.asarray(residual_all(jnp.asarray(solution.x), data))
    x, std, correlation, bandwidth = solution.x, solution.std, solution.correlation, solution.bandwidth
    step_rms, check_s = None, 0.0
    if step_check is not None:
        t_check = time.perf_counter()
        say(f"identify: step check: the fitted values replayed at a {step_check * 1e6:g} us step")
        finer = [_replay(log, machine, gains, hybrid, rates, window_s, trajectory, step_check) for log in logs]
        finer_residual = jax.jit(residual_of_replays(finer))
        r_at_fit = np.asarray(finer_residual(jnp.asarray(x), data))
        moved = np.clip(x + gauss_newton_step(solution.jacobian, r_at_fit - r1), low, high)
        r_moved = np.asarray(finer_residual(jnp.asarray(moved), data))
        step_rms = (float(np.sqrt(np.mean(r_at_fit**2))), float(np.sqrt(np.mean(r_moved**2))))
        if step_rms[1] < step_rms[0]:
            x = moved
            # the moved values' errors: those of the finer step's fit, from its residual at them and the Jacobian
            # that the move took as that fit's, with the check's own error, STEP_CHECK_ERROR of the move, beside them
            kept = solution.excited
            if kept.any():
                std, correlation = std.copy(), np.eye(x.size)
                std[kept], correlation[np.ix_(kept, kept)], bandwidth = value_errors(
                    solution.jacobian[:, kept],
                    r_moved,
                    (samples, lengths),
                    added_variance=(STEP_CHECK_ERROR * (moved - solution.x)[kept]) ** 2,
                )
        else:
            say(
                f"identify: step check: the move did not lower the finer replay's residual RMS ({step_rms[0]:.4g} -> "
                f"{step_rms[1]:.4g}): the values kept as fitted"
            )
        check_s = time.perf_counter() - t_check
    fitted, errors = x * scale, std * scale
    values = tuple(
        FittedValue(f, k, float(v0), float(v), float(e), bool(ok), float(d))
        for (f, k), v0, v, e, ok, d in zip(owner, starts, fitted, errors, solution.excited, fitted - solution.x * scale)
    )
    report = FitReport(
        values=values,
        correlation=tuple(tuple(float(c) for c in row) for row in correlation),
        residual_rms_before=float(np.sqrt(np.mean(r0**2))),
        residual_rms_after=float(np.sqrt(np.mean(r1**2))),
        samples=int(sum(len(r.t) for r in replays)),
        window_s=window_s,
        mech_step_s=ModelOptions().timestep if mech_step is None else mech_step,
        evaluations=solution.evaluations,
        jacobians=solution.jacobians,
        derivatives=derivatives,
        residual_calls=solution.residual_calls,
        residual_s=solution.residual_s,
        jacobian_s=solution.jacobian_s,
        trace=solution.trace,
        solver_message=solution.message,
        converged=solution.converged,
        wall_s=time.perf_counter() - t0,
        logs=tuple(
            {"path": log.path, "sha256": log.digest, "source": log.source, "timing": r.steps.counts()}
            for log, r in zip(logs, replays)
        ),
        error_bandwidth=bandwidth,
        step_check_s=step_check,
        step_check_rms=step_rms,
        step_check_wall_s=check_s,
    )
    identified = dataclasses.replace(
        with_values(machine, split(fitted)),
        uncertainty=uncertainty_of(values),
        correlation=correlation_of(values, correlation),
    )
    plots, at = [], 0  # the replayed efforts, from the residual's first part for each log (no other program)
    for r in replays:
        n, s_effort = r.effort.size, scales[r.channel]
        plots.append(
            {
                "channel": r.channel,
                "t": r.t,
                "logged": r.effort,
                "before": r.effort + s_effort * r0[at : at + n].reshape(r.effort.shape),
                "after": r.effort + s_effort * r1[at : at + n].reshape(r.effort.shape),
            }
        )
        at += 2 * n
    return report, identified, plots
