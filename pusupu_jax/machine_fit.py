"""Fitting the machine's drive-train friction to run logs (host-side driver of a differentiable replay).

A log (:func:`pusupu_jax.run_log.drive_log`: ``pusupu sim --plant mjx --log`` or ``pusupu bridge --log``) holds, per
sample, the motor angle each axis followed, and the angle, speed and torque its drive measured.  :func:`fit` replays
the logged path through the simulated closed loop (the cascade with the gains the log ran with, on the MJX machine of
the machine file), from rest at the path's start, and fits chosen drive-train fields of the machine file
(:class:`FitField`) so that the replay's motor torques and angles match the logged ones: a nonlinear least-squares
problem whose residual is

    r = [(tau_sim - tau_log) / s_tau, (theta_sim - theta_log) / s_theta]   over every logged sample and axis,

``s_tau`` the RMS of the logged torques and ``s_theta`` the RMS of the logged tracking error (so both count alike).

*Closed-loop replay, not open-loop.*  The logged run was closed loop: replaying the logged torques into the open-loop
machine drifts away from the logged motion within a fraction of a second (an unstable double integrator per axis), so
its residual stops measuring the parameters.  The replayed closed loop stays on the path, and the torque its
controller needs to get there carries the friction (Coulomb and viscous) the log's controller paid.

*Solver.*  scipy's trust-region reflective least squares (``scipy.optimize.least_squares(method='trf')``), each
value held inside its field's range (:func:`pusupu_jax.params.bounds`: no negative friction), over two jitted
programs, the residual and its Jacobian (``jax.jacfwd``: forward mode, one tangent per fitted value, exact).  An
optimistix Levenberg-Marquardt traces the whole solve, both programs inside its loop, into one program: on the
2-core CPU (beside another job) its compile for a 1 s window had not ended after 8 minutes, where the two programs
here compile in about 35 s.

*Standard errors* come from the Jacobian at the optimum, ``s^2 (J^T J)^-1`` with ``s^2`` the residual's variance
per degree of freedom.  A value the logs do not excite (its Jacobian column below ``1e-8`` of the largest, or a
standard error above half its size) is not invented: it keeps the machine file's value, is reported as not excited,
and the others are fitted again without it.
"""

from __future__ import annotations

import dataclasses
import enum
import time
from typing import Any, Callable, cast

import jax
import jax.numpy as jnp
import numpy as np

from .cascade import control_mode
from .hybrid import HybridGains, HybridReference
from .machine import MACHINE_MODES, machine_plant, machine_rates, machine_reference
from .machine_file import Machine
from .params import N_AXES, LoopRates, ParameterError, ServoParams, bounds
from .paths import platform_path_from
from .run_log import DriveLog
from .sim import rollout


class FitField(enum.StrEnum):
    """A drive-train field of the machine file that :func:`fit` can fit, per axis."""

    COULOMB = "coulomb"  # Coulomb friction at the slider [N]
    VISCOUS = "viscous"  # viscous friction at the slider [N s/m]


FIT_GROUPS = {"friction": (FitField.COULOMB, FitField.VISCOUS)}  # names of several fields at once (``--fit``)
UNITS = {FitField.COULOMB: "N", FitField.VISCOUS: "N*s/m"}
SCALES = {FitField.COULOMB: 10.0, FitField.VISCOUS: 50.0}  # a fitted value's scale where its start is 0
UNEXCITED_COLUMN = 1e-8  # a Jacobian column this small against the largest: the logs do not excite the value
UNEXCITED_ERROR = 0.5  # a standard error above this fraction of the value (or of its scale): not identified


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
    """One axis's value of one field: where the fit started, where it ended, its standard error (in the field's
    unit), and whether the logs excited it (if not, ``value`` is ``start``)."""

    field: FitField
    axis: int
    start: float
    value: float
    std_error: float
    excited: bool

    def as_dict(self) -> dict[str, Any]:
        return {
            "field": str(self.field),
            "axis": self.axis,
            "unit": UNITS[self.field],
            "start": self.start,
            "value": self.value,
            "std_error": self.std_error,
            "excited": self.excited,
        }


@dataclasses.dataclass(frozen=True)
class FitReport:
    """What :func:`fit` found: every fitted value, the residual's RMS before and after, the samples and the window,
    the solver's work, and the logs (path, SHA-256, what wrote them)."""

    values: tuple[FittedValue, ...]
    residual_rms_before: float
    residual_rms_after: float
    samples: int
    window_s: float
    evaluations: int
    jacobians: int
    solver_message: str
    wall_s: float
    logs: tuple[dict[str, str], ...]

    def as_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self) | {"values": [v.as_dict() for v in self.values]}

    def unexcited(self) -> list[FittedValue]:
        return [v for v in self.values if not v.excited]


@dataclasses.dataclass(frozen=True)
class Replay:
    """One log's replay: the jitted ``run(values) -> (torque, theta)`` at the logged samples ``(n, n_axes)``, and the
    logged ``torque`` and ``position`` there; ``t`` [s] along the path."""

    run: Callable[[list[jax.Array]], tuple[jax.Array, jax.Array]]
    torque: np.ndarray
    position: np.ndarray
    reference: np.ndarray
    t: np.ndarray


def _replay(
    log: DriveLog,
    machine: Machine,
    gains: ServoParams,
    hybrid: HybridGains | None,
    rates: LoopRates,
    window_s: float,
    fields: tuple[FitField, ...],
    trajectory: str | None,
) -> Replay:
    """The closed-loop replay of ``log``'s first ``window_s`` seconds on ``machine`` under ``gains``, checked against
    the log: its mode, rate and reference."""
    if log.mode not in MACHINE_MODES:
        raise ParameterError(f"{log.path}: mode: expected one of {tuple(map(str, MACHINE_MODES))}, got {log.mode!r}")
    options = machine.options()
    rates = machine_rates(options, rates)
    spec = trajectory or log.trajectory
    if not spec:
        raise ParameterError(
            f"{log.path}: expected the path it ran (a '# trajectory:' line or --trajectory), found none"
        )
    path = platform_path_from(spec, machine.geometry.home, rates)
    n = min(int(round(window_s / rates.dt_position)), len(path))
    index = np.rint(log.path_time / rates.dt_position).astype(int)  # the position period of each sample's reference
    keep = (index >= 0) & (index < n)
    if keep.sum() < 2:
        raise ParameterError(
            f"{log.path}: expected samples in the first {window_s:g} s of the path, found fewer than 2"
        )
    index = index[keep]
    servo = machine.servo(gains)
    reference = machine_reference(servo, path[:n], log.mode, options=options, rates=rates, geom=machine.geometry)
    theta_ref = np.asarray(
        cast(HybridReference, reference).theta if control_mode(log.mode).hybrid else reference,
    )[index]
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

    @jax.jit
    def run(values: list[jax.Array]) -> tuple[jax.Array, jax.Array]:
        trace = rollout(
            servo.replace(**dict(zip(fields, values))),
            model,
            reference,
            plant=plant,
            rates=rates,
            outer=mode,
            hybrid=hybrid,
        )
        return trace.torque[index], trace.theta[index]

    return Replay(run, log.torque[keep], log.position[keep], log.reference[keep], index * rates.dt_position)


@dataclasses.dataclass(frozen=True)
class Solution:
    """What :func:`least_squares_excited` found: the values ``x`` (the unexcited ones at their start), their standard
    errors, which were excited, the residual at the start, scipy's result of the last solve, and the residual and
    Jacobian evaluations over every solve."""

    x: np.ndarray
    std: np.ndarray
    excited: np.ndarray
    residual_before: np.ndarray
    result: Any
    evaluations: int
    jacobians: int


def least_squares_excited(
    residual_of: Callable[[np.ndarray], tuple[Callable[[jax.Array], jax.Array], Callable[[jax.Array], jax.Array]]],
    start: np.ndarray,
    low: np.ndarray,
    high: np.ndarray,
    say: Callable[[str], object] = lambda line: None,
) -> Solution:
    """Bounded least squares (scipy's trust-region reflective solver) from ``start`` inside ``[low, high]``, with
    standard errors from the Jacobian at the optimum, that invents no value the data do not excite.

    ``residual_of(free)`` gives the residual and its Jacobian as functions of the values at the indices ``free``
    (the others held at their start).  A value whose Jacobian column is below :data:`UNEXCITED_COLUMN` of the largest,
    or whose standard error is above :data:`UNEXCITED_ERROR` of its size (or of 1), is not excited: it keeps its
    start, and the others are fitted again without it.  With none excited, every value keeps its start."""
    from scipy.optimize import least_squares

    def solve(free: np.ndarray) -> tuple[Any, np.ndarray, np.ndarray, np.ndarray]:
        f, jac = residual_of(free)
        p0 = start[free]
        say(f"identify: compiling the replay and its Jacobian ({len(free)} values)")
        r0 = np.asarray(f(jnp.asarray(p0)))
        jac(jnp.asarray(p0))
        say("identify: fitting (trust-region least squares, each value inside its field's range)")
        sol = least_squares(
            lambda p: np.asarray(f(jnp.asarray(p))),
            p0,
            jac=lambda p: np.asarray(jac(jnp.asarray(p))),
            bounds=(low[free], high[free]),
            method="trf",
            xtol=1e-9,
            ftol=1e-9,
        )
        J = np.asarray(jac(jnp.asarray(sol.x)))
        dof = max(J.shape[0] - J.shape[1], 1)
        variance = 2 * sol.cost / dof
        std = np.sqrt(np.maximum(np.diag(variance * np.linalg.pinv(J.T @ J)), 0.0))
        return sol, r0, std, J

    free = np.arange(start.size)
    sol, r0, std, J = solve(free)
    norms = np.linalg.norm(J, axis=0)
    x = sol.x
    excited = (norms > UNEXCITED_COLUMN * norms.max()) & (std < UNEXCITED_ERROR * np.maximum(np.abs(x), 1.0))
    evaluations, jacobians = sol.nfev, sol.njev
    if not excited.all() and excited.any():
        say(f"identify: {int((~excited).sum())} value(s) not excited by the logs: fitting the others again")
        kept = free[excited]
        again, _, std_kept, _ = solve(kept)
        x = start.copy()
        x[kept] = again.x
        std[kept] = std_kept
        sol, evaluations, jacobians = again, evaluations + again.nfev, jacobians + again.njev
    elif not excited.any():
        x = start.copy()
    return Solution(x, std, excited, r0, sol, int(evaluations), int(jacobians or 0))


def fit(
    logs: list[DriveLog],
    machine: Machine,
    gains: ServoParams,
    hybrid: HybridGains | None = None,
    rates: LoopRates = LoopRates(),
    fields: tuple[FitField, ...] = FIT_GROUPS["friction"],
    window_s: float = 2.0,
    trajectory: str | None = None,
    progress: Callable[[str], object] | None = None,
) -> tuple[FitReport, Machine, list[dict[str, np.ndarray]]]:
    """Fit ``fields`` of ``machine`` (its values are the start) to ``logs``, each replayed over its first
    ``window_s`` [s] with ``gains`` (``hybrid``: a hybrid log's gains; ``rates``: the gains' rates; ``trajectory``:
    the path, where not the logs' own).  Returns the report, the machine with the fitted values (the unexcited ones
    as they were), and per log the arrays of the plot (``t``, logged and replayed torques before and after).
    ``progress(line)`` is told what runs (compiles take about half a minute each on 2 CPU cores)."""
    say = progress or (lambda line: None)
    t0 = time.perf_counter()
    starts = np.stack([np.broadcast_to(np.asarray(machine.drives[f], float), (N_AXES,)) for f in fields])
    scale = np.where(starts != 0, np.abs(starts), np.array([[SCALES[f]] for f in fields]))
    ranges = {f.name: bounds(f) for f in dataclasses.fields(ServoParams) if f.name in fields}

    # an end of the field's range (params.bounds), or no limit
    def limit(field: str, end: int, beyond: float) -> float | str:
        b = ranges[field]
        return b[end] if b is not None and isinstance(b[end], (int, float)) else beyond

    low = np.stack([np.full(N_AXES, limit(f, 0, -np.inf)) for f in fields]) / scale
    high = np.stack([np.full(N_AXES, limit(f, 1, np.inf)) for f in fields]) / scale
    replays = [_replay(log, machine, gains, hybrid, rates, window_s, fields, trajectory) for log in logs]
    s_tau = max(float(np.sqrt(np.mean(np.concatenate([r.torque.ravel() for r in replays]) ** 2))), 1e-12)
    tracking = np.concatenate([(r.position - r.reference).ravel() for r in replays])
    s_theta = max(float(np.sqrt(np.mean(tracking**2))), 1e-12)

    programs: dict[tuple[Any, ...], tuple[Callable[[jax.Array], jax.Array], Callable[[jax.Array], jax.Array]]] = {}

    def residual_of(free: np.ndarray) -> tuple[Callable[[jax.Array], jax.Array], Callable[[jax.Array], jax.Array]]:
        """The residual as a function of the free values (scaled), the others held at their start, and its Jacobian:
        jitted once per set of free values."""
        if tuple(free) in programs:
            return programs[tuple(free)]

        def residual(p: jax.Array) -> jax.Array:
            x = jnp.asarray(starts / scale).ravel().at[free].set(p)
            values = list(x.reshape(starts.shape) * scale)
            parts = []
            for r in replays:
                torque, theta = r.run(values)
                parts += [((torque - r.torque) / s_tau).ravel(), ((theta - r.position) / s_theta).ravel()]
            return jnp.concatenate(parts)

        programs[tuple(free)] = jax.jit(residual), jax.jit(jax.jacfwd(residual))
        return programs[tuple(free)]

    solution = least_squares_excited(residual_of, (starts / scale).ravel(), low.ravel(), high.ravel(), say)
    sol, r0, x, std, excited = solution.result, solution.residual_before, solution.x, solution.std, solution.excited
    evaluations, jacobians = solution.evaluations, solution.jacobians
    fitted = x.reshape(starts.shape) * scale
    errors = std.reshape(starts.shape) * scale
    flags = excited.reshape(starts.shape)
    values = tuple(
        FittedValue(f, a, float(starts[i, a]), float(fitted[i, a]), float(errors[i, a]), bool(flags[i, a]))
        for i, f in enumerate(fields)
        for a in range(N_AXES)
    )
    f_all, _ = residual_of(np.arange(starts.size))
    r1 = np.asarray(f_all(jnp.asarray(fitted.ravel() / scale.ravel())))
    report = FitReport(
        values=values,
        residual_rms_before=float(np.sqrt(np.mean(r0**2))),
        residual_rms_after=float(np.sqrt(np.mean(r1**2))),
        samples=int(sum(len(r.t) for r in replays)),
        window_s=window_s,
        evaluations=evaluations,
        jacobians=jacobians,
        solver_message=str(sol.message),
        wall_s=time.perf_counter() - t0,
        logs=tuple({"path": log.path, "sha256": log.digest, "source": log.source} for log in logs),
    )
    identified = dataclasses.replace(
        machine,
        name=f"{machine.name} identified",
        drives=machine.drives | {str(f): np.asarray(fitted[i], float) for i, f in enumerate(fields)},
    )
    plots, at = [], 0  # the replayed torques, from the residual's first part for each log (no other program)
    for r in replays:
        n = r.torque.size
        plots.append(
            {
                "t": r.t,
                "logged": r.torque,
                "before": r.torque + s_tau * r0[at : at + n].reshape(r.torque.shape),
                "after": r.torque + s_tau * r1[at : at + n].reshape(r.torque.shape),
            }
        )
        at += 2 * n
    return report, identified, plots
