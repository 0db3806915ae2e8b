"""The cascade and a plant over a reference, as one jitted scan of nested scans.

Time structure (static, from :class:`~pusupu_jax.params.LoopRates`): the outer scan runs
at the rate of the outermost closed loop; inside each position period the velocity loop
runs ``n_position`` times; inside each velocity period the plant's mechanics steps
``n_velocity / n_mech`` times; inside each mechanical step the current loop and the
electrical model tick ``n_mech`` times with the motor speed held, and the mechanics then
advances with the mean motor torque of those ticks.

Measurements are taken at the start of each period (sample, then compute, then hold), so
each loop sees the plant through a zero-order hold, as a digital drive does.  A drive that takes its speed from
its encoder's counts sees the mean speed of the last velocity period (``counted_speed``: the angle's change over
that period, over the period); at a mechanical step of one velocity period that is the speed at its start, since
the semi-implicit step moves each angle by the step times the new speed.

:func:`rollout` is the pure function (jit-, vmap- and grad-able); :func:`simulate` is
the host-side entry point that validates inputs, converts slider references to motor
angles and dispatches to a cached jitted (and, for batched parameters, vmapped) rollout.
The record is a :class:`~pusupu_jax.trace.Trace`; long runs on the host are cut into chunks by
:mod:`pusupu_jax.chunked`.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Callable, NamedTuple, cast

import jax
import jax.numpy as jnp
import numpy as np
import numpy.typing as npt

from . import cascade as cascade_
from . import compliance as compliance_law
from . import hybrid as hybrid_law
from . import loops
from .params import AxisLoad, LoopRates, ParameterError, ServoParams, validate
from .plant import AxisPlant, PlantDrives
from .plant.axis import screw_ratio
from .plant.kinematics import inverse_kinematics
from .trace import Trace

if TYPE_CHECKING:
    from jax.typing import ArrayLike

    from .plant import Plant
    from .plant.geometry import Geometry

MODES = cascade_.AXIS_MODES  # the single-axis plant's position modes
STARTS = ("rest", "zero")


@jax.tree_util.register_dataclass
@dataclass(frozen=True)
class Injected:
    """A reference sample with signals added at the controller outputs: how a loop gain is measured by injection.

    ``reference``: the mode's own sample.  ``velocity`` [rad/s] ``(n_axes,)``: added to the position controller's
    output, the velocity reference the velocity loops receive (in 'velocity' mode, to the reference itself).
    ``current`` [A] ``(m, n_axes)``: added to the velocity controller's output (after its ``+-I_max`` clamp), the
    current reference the current loops receive, in each of the period's ``m`` velocity periods
    (``rates.n_position`` in the position modes, 1 in 'velocity').  The trace's ``command`` and
    ``current_reference`` record the sums, so that a controller's own output is the recorded signal less the
    injection (:mod:`pusupu_jax.injection`).
    """

    reference: Any
    velocity: Any
    current: Any


def _injected(ref: Any) -> tuple[Any, Injected | None]:
    """``(the mode's sample, the Injected or None)`` of a reference sample."""
    return (ref.reference, ref) if isinstance(ref, Injected) else (ref, None)


AGES = 8  # the periods of encoder readings a Commanded sample reaches back over (the present's included)


@jax.tree_util.register_dataclass
@dataclass(frozen=True)
class Commanded:
    """A reference sample as a bridge's command reached the robot: how a bridge log is replayed
    (:func:`pusupu_jax.machine_fit.bridge_commands`).  Position modes, the drives' loops in the robot.

    The position loop steps on ``reference`` (the mode's own sample) with the encoders' angles and speeds the robot
    read ``age`` periods of its own before the present (``()`` int in ``[0, AGES)``; 0: the present): the bridge
    computed the command from the newest feedback it had, which a late packet leaves older.  The drives and the
    machine run the period under the command only where ``taken`` (``()`` bool): a robot that found a newer command
    waiting took that one and ran no period under this one, whose step the position loop took all the same.  The
    trace records each command's start, so a sample is the start of the command after the one it answers."""

    reference: Any
    taken: Any
    age: Any


def _commanded(ref: Any) -> tuple[Any, Commanded | None]:
    """``(the sample inside, the Commanded or None)`` of a reference sample."""
    return (ref.reference, ref) if isinstance(ref, Commanded) else (ref, None)


class Carry(NamedTuple):
    """The scan carry: the plant, the electrical model (inverter, armature) and the controllers."""

    plant: Any
    electrical: Any  # (..., n_axes, 2): inverter voltage [V], armature current [A]
    cascade: cascade_.CascadeState
    outer: Any = None  # the compliance law's state (compliance.AdmittanceState) when one runs outside the cascade
    counted: Any = None  # the motor angles [rad] at the last velocity tick, where the drives count their speed
    # where the reference is Commanded: the encoders' angles [rad] and speeds [rad/s] after each of the last AGES
    # periods the robot ran, newest (the present) first, ((AGES, n_axes), (AGES, n_axes))
    measured: Any = None


class Rest(NamedTuple):
    """The part of a run's start that no controller changes: the plant at rest in its initial state, its motor angles
    ``theta0`` [rad] there, and its static equilibrium ``statics`` (``plant.statics``: what the holding torques of
    every mode are solved from)."""

    plant: Any
    theta0: jax.Array
    statics: Any


def plant_rest(plant: Plant, aux: Any) -> Rest:
    """:class:`Rest` of ``plant`` (prepared as ``aux``): the same in every mode."""
    plant_state = plant.init(aux)
    theta0, _ = plant.measure(aux, plant_state)
    return Rest(plant_state, theta0, plant.statics(aux, plant_state))


def initial_state(
    drive: loops.Drive,
    plant: Plant,
    aux: Any,
    mode: cascade_.ControlMode,
    start: str = "rest",
    force_ff0: ArrayLike | None = None,
    rest: Rest | None = None,
    counted_speed: bool = False,
) -> Carry:
    """The plant at rest in its initial state, and the cascade as ``start`` says; with ``counted_speed`` (drives that
    count their speed, :func:`pieces`), the angles they last read are the plant's there (at rest they count none).

    ``start='rest'``: the cascade holding the plant there, as on a machine that has been standing
    under control (:func:`pusupu_jax.cascade.rest`): the motor currents that hold it
    (``plant.holding_torque``; in hybrid mode branch 6 pushes ``force_ff0``, its ``F_q`` at
    t = 0 [N]) and the electrical model carrying them.  ``start='zero'``: every controller and
    electrical state zero, so that the plant sags under gravity until the integrators catch up
    (how runs started before; kept to reproduce old figures).  ``rest``: the plant's :func:`plant_rest`, computed
    before (by a program of its own, shared by every mode: :mod:`pusupu_jax.chunked`), or None to compute it here.
    """
    if start not in STARTS:
        raise ValueError(f"rollout: expected start in {STARTS}, got {start!r}")
    if rest is None:
        rest = plant_rest(plant, aux)
    counted = rest.theta0 if counted_speed else None
    if start == "zero":
        electrical0 = loops.electrical_init(drive.electrical)
        return Carry(rest.plant, electrical0, cascade_.init(drive, mode, rest.theta0), counted=counted)
    force = (mode.force_axis, force_ff0) if mode.hybrid else (None, None)
    i = plant.holding_torque(aux, rest.statics, *force) / drive.Kt
    electrical, u = loops.electrical_rest(drive.electrical, i)
    force0 = 0.0 if force_ff0 is None else force_ff0
    return Carry(rest.plant, electrical, cascade_.rest(drive, mode, i, u, rest.theta0, force0), counted=counted)


def current_ticks(
    drive: loops.Drive, electrical: jax.Array, s: cascade_.CascadeState, i_ref: jax.Array, omega: jax.Array, n: int
) -> tuple[jax.Array, cascade_.CascadeState, jax.Array, jax.Array]:
    """``n`` current periods of the drives and their motors' electrics with the motor speed ``omega`` [rad/s] held.

    Returns ``(electrical, state, mean motor torque [N m], the first period's inverter command [V])``:
    the mechanics then advances one step with that torque (``n = rates.n_mech``).
    """

    def tick(
        ce: tuple[jax.Array, cascade_.CascadeState], _: None
    ) -> tuple[tuple[jax.Array, cascade_.CascadeState], tuple[jax.Array, jax.Array]]:
        xe, sc = ce
        sc, u = cascade_.current_tick(drive, sc, i_ref, loops.electrical_current(xe), omega)
        torque = drive.Kt * loops.electrical_current(xe)
        return (loops.electrical_step(drive.electrical, xe, u, omega), sc), (torque, u)

    (xe, sc), (torques, u) = jax.lax.scan(tick, (electrical, s), None, length=n)
    return xe, sc, jnp.mean(torques, axis=0), u[0]


class Pieces(NamedTuple):
    """The pieces of a rollout: one outer period, the trace record of it, the period [s] and the initial carry."""

    # (carry, reference sample) -> (carry, (command, current references (m, n_axes)))
    period: Callable[[Carry, Any], tuple[Carry, Any]]
    # (carry at the period's start, reference sample, (command, current references)[, observation])
    # -> trace entries; the observation when the period already made it
    record: Callable[..., dict[str, Any]]
    dt: float
    init: Callable[[str, Any, Rest | None], Carry]  # (start, force_ff0, the plant's rest or None) -> carry
    observe: Callable[[Carry], Any]  # carry -> what the plant's observe() returns (for a law outside the cascade)
    sensed: Callable[[Carry], tuple[jax.Array, jax.Array]]  # carry -> the encoders' angles and speeds the drives read


def period_dt(rates: LoopRates, mode: cascade_.ControlMode) -> float:
    """The period [s] of the outermost loop ``mode`` closes (one sample of its reference)."""
    return {"current": rates.dt_mech, "velocity": rates.dt_velocity, "position": rates.dt_position}[mode.closed]


def plant_side(params: ServoParams, plant_params: Any) -> tuple[ServoParams, Any]:
    """``(the drive values the machine has, the plant's own parameters)``: ``params`` and ``plant_params`` as they
    are, or, for a :class:`~pusupu_jax.plant.PlantDrives`, ``params`` with its drive values over them and its
    ``params``.  The plant, the motor and its drive's own feedforward (:func:`pusupu_jax.loops.on_machine`) run on
    the first; the controllers and the host's force law on ``params``."""
    if isinstance(plant_params, PlantDrives):
        return params.replace(**plant_params.drives), plant_params.params
    return params, plant_params


def pieces(
    params: ServoParams,
    plant_params: Any,
    *,
    plant: Plant,
    rates: LoopRates,
    mode: cascade_.ControlMode,
    hybrid: hybrid_law.HybridGains | None,
    counted_speed: bool = False,
) -> Pieces:
    """The closures of one rollout (traced: call inside a jitted function) for ``mode`` against ``plant``.
    ``counted_speed``: the drives' speed is the motor angle's change over the last velocity period, over that period
    [rad/s] (as a drive counting encoder counts measures it), not the motors' speed at the period's start; the
    current loop's ticks keep the motors' speed (the back-EMF)."""
    if mode.hybrid != (hybrid is not None):
        raise ValueError("rollout: hybrid gains are needed exactly when outer='hybrid'")
    drive = loops.discretize(params, rates)
    machine, plant_params = plant_side(params, plant_params)
    if machine is not params:
        drive = loops.on_machine(drive, machine, rates)
    aux = plant.prepare(machine, plant_params, rates.dt_mech)
    n_mech_steps = rates.n_velocity // rates.n_mech

    def sensed(c: Carry) -> tuple[jax.Array, jax.Array]:
        """The motor angles [rad] and speeds [rad/s] the drives read at a velocity tick (each position tick is one)."""
        theta, omega = plant.measure(aux, c.plant)
        return (theta, (theta - c.counted) / rates.dt_velocity) if counted_speed else (theta, omega)

    def record(c: Carry, ref: Any, out: tuple[jax.Array, jax.Array], observation: Any = None) -> dict[str, Any]:
        ref, _ = _injected(_commanded(ref)[0])
        command, i_refs = out
        theta, omega = plant.measure(aux, c.plant)
        x, v = plant.slider(aux, c.plant)
        i = loops.electrical_current(c.electrical)
        return dict(
            reference=mode.theta(ref),
            command=command,
            theta=theta,
            omega=omega,
            position=x,
            velocity=v,
            current=i,
            torque=drive.Kt * i,
            current_reference=i_refs,
            state=c.cascade,
            observation=plant.observe(aux, c.plant) if observation is None else observation,
        )

    def mech_step(c: Carry, i_ref: jax.Array) -> tuple[Carry, jax.Array]:
        _, omega = plant.measure(aux, c.plant)
        xe, sc, torque, u = current_ticks(drive, c.electrical, c.cascade, i_ref, omega, rates.n_mech)
        return c._replace(plant=plant.step(aux, c.plant, torque), electrical=xe, cascade=sc), u

    # Reverse mode keeps only each velocity period's inputs and runs the period again in the backward pass
    # (jax.checkpoint), instead of stacking every intermediate of its plant step and current ticks over the scans.
    # The same values, for about one more forward pass of the period, with far fewer arrays to stack: on the
    # tuner's default gradient (MJX machine, 2-core CPU) XLA's compile fell from 36 to 25 s and a call from 6.3 to
    # 4.9 s.  prevent_cse=False: the scans that call it already keep XLA from merging the recomputation back into
    # the forward pass, so the barriers that would prevent it are not needed (jax.checkpoint's documentation).
    @functools.partial(jax.checkpoint, prevent_cse=False)
    def velocity_period(
        c: Carry, w_ref: jax.Array, i_force: jax.Array | None = None, injected_current: jax.Array | None = None
    ) -> tuple[Carry, jax.Array]:
        theta, omega = sensed(c)
        sc, i_ref = cascade_.velocity_tick(drive, mode, c.cascade, w_ref, omega, i_force)
        if injected_current is not None:
            i_ref = i_ref + injected_current
        c = c._replace(cascade=sc, counted=theta if counted_speed else None)
        if n_mech_steps == 1:  # the machine's case: a scan of one step is one more level for the gradient to nest
            return mech_step(c, i_ref)[0], i_ref
        c, _ = jax.lax.scan(lambda cc, _: mech_step(cc, i_ref), c, None, length=n_mech_steps)
        return c, i_ref

    def position_period(c: Carry, ref: Any) -> tuple[Carry, tuple[jax.Array, jax.Array]]:
        ref, commanded = _commanded(ref)
        ref, injected = _injected(ref)
        if commanded is None:
            theta, omega = sensed(c)
        else:  # the feedback the bridge had
            theta, omega = (x[commanded.age] for x in c.measured)
        sc, w_ref, i_force = cascade_.position_tick(drive, mode, c.cascade, ref, theta, omega, hybrid)
        if injected is not None:
            w_ref = w_ref + injected.velocity
        ran, i_refs = jax.lax.scan(
            lambda cc, d: velocity_period(cc, w_ref, i_force, d),
            c._replace(cascade=sc),
            None if injected is None else injected.current,
            length=rates.n_position,
        )
        if commanded is None:
            return ran, (w_ref, i_refs)
        ran = ran._replace(measured=tuple(jnp.concatenate([r[None], m[:-1]]) for r, m in zip(sensed(ran), c.measured)))
        held = c._replace(cascade=sc)  # the position loop stepped; the drives and the machine ran no period
        return jax.tree.map(lambda a, b: jnp.where(commanded.taken, a, b), ran, held), (w_ref, i_refs)

    def current_period(c: Carry, i_ref: jax.Array | Injected) -> tuple[Carry, tuple[jax.Array, jax.Array]]:
        if isinstance(i_ref, Injected):
            raise ValueError("rollout: injection needs the velocity loop closed, got mode 'current'")
        c, u = mech_step(c, i_ref)
        return c, (u, i_ref[None])

    def inner_velocity_period(c: Carry, w_ref: Any) -> tuple[Carry, tuple[jax.Array, jax.Array]]:
        w_ref, injected = _injected(w_ref)
        if injected is not None:
            w_ref = w_ref + injected.velocity
        c, i_ref = velocity_period(c, w_ref, None, None if injected is None else injected.current[0])
        return c, (i_ref, i_ref[None])

    period = {"current": current_period, "velocity": inner_velocity_period, "position": position_period}[mode.closed]
    return Pieces(
        period,
        record,
        period_dt(rates, mode),
        lambda start, force_ff0, rest: initial_state(drive, plant, aux, mode, start, force_ff0, rest, counted_speed),
        lambda c: plant.observe(aux, c.plant),
        sensed,
    )


def compliant_pieces(
    base: Pieces,
    params: ServoParams,
    gains: compliance_law.AdmittanceGains,
    geom: Geometry,
    *,
    mode: cascade_.ControlMode,
) -> Pieces:
    """``base`` (closed up to the position loop) under the admittance of :mod:`pusupu_jax.compliance`.

    Each position period first reads the plant's ``contact_force`` [N] (as at the period's
    start, like every measurement), steps the admittance, and runs ``base``'s period on the
    inner reference whose motor angles are the nominal inverse kinematics of ``geom`` at the
    path's pose plus the offset, ``(s(q + x_c) - s(home)) / r`` [rad].  The reference is a
    :class:`~pusupu_jax.compliance.ComplianceReference`; the trace records the angles actually
    followed, and the observation adds ``compliance_offset`` [m] at each period's start, before that
    period's admittance step (so ``reference[k]`` follows from ``compliance_offset[k + 1]``).
    """
    if mode.closed != cascade_.Loop.POSITION:
        raise ValueError(f"rollout: compliance needs the position loop closed, got mode {mode.name!r}")
    r = screw_ratio(params)
    s_home = inverse_kinematics(geom, jnp.asarray(geom.home))

    def inner(c: Carry, ref: compliance_law.ComplianceReference) -> Any:
        pose = ref.pose.at[:3].add(c.outer.offset)
        return mode.with_theta(ref.inner, (inverse_kinematics(geom, pose) - s_home) / r)

    def period(c: Carry, ref: compliance_law.ComplianceReference) -> tuple[Carry, tuple[Any, Any, Any]]:
        observation = base.observe(c)
        state = compliance_law.step(gains, c.outer, observation["contact_force"], ref.force_setpoint, base.dt)
        c = c._replace(outer=state)
        inner_ref = inner(c, ref)
        c, out = base.period(c, inner_ref)
        return c, (out, inner_ref, observation)

    def record(c: Carry, ref: compliance_law.ComplianceReference, out: tuple[Any, Any, Any]) -> dict[str, Any]:
        command, inner_ref, observation = out
        rec = base.record(c, inner_ref, command, observation)
        return rec | {"observation": rec["observation"] | {"compliance_offset": c.outer.offset}}

    return Pieces(
        period,
        record,
        base.dt,
        lambda start, force_ff0, rest: base.init(start, force_ff0, rest)._replace(outer=compliance_law.init()),
        base.observe,
        base.sensed,
    )


def rollout(
    params: ServoParams,
    plant_params: Any,
    reference: Any,
    *,
    plant: Plant = AxisPlant(),
    rates: LoopRates = LoopRates(),
    outer: str = "imc",
    remat: bool = False,
    hybrid: hybrid_law.HybridGains | None = None,
    start: str = "rest",
    init: Carry | None = None,
    compliance: tuple[compliance_law.AdmittanceGains, Geometry] | None = None,
    counted_speed: bool = False,
) -> Trace:
    """Run the cascade closed up to ``outer`` against ``plant`` (pure; jit with plant, rates, outer, remat, start
    and counted_speed static).

    ``outer``: 'current', 'velocity', 'imc' (2-DOF IMC, ``params.imc_form``), 'pid', 'pid_ff'
    (PID with velocity feedforward), 'ros_pid' (the PID fields run as ROS's PID does:
    :func:`pusupu_jax.loops.ros_pid_step`) or 'hybrid'.  ``start``: 'rest' (the static equilibrium,
    :func:`initial_state`) or 'zero'.  ``init``: a carry to start from instead (one that
    :func:`~pusupu_jax.chunked.run_chunked` kept at a mark, for a window of a longer run); its trace's ``t`` starts
    at 0.

    ``reference`` has shape ``(N, n_axes)`` in the outer loop's units, one sample per
    outer period: motor angle [rad] for 'imc' and 'pid', motor speed [rad/s] for
    'velocity', current [A] for 'current' (one per mechanical step).

    ``outer='hybrid'`` is the force/position hybrid control of :mod:`pusupu_jax.hybrid`:
    ``reference`` is a :class:`~pusupu_jax.hybrid.HybridReference` and ``hybrid`` its
    :class:`~pusupu_jax.hybrid.HybridGains`.  Every axis runs the IMC cascade, but the
    current reference of axis ``FORCE_AXIS`` is replaced by ``F_6 r / (eta Kt)`` (clamped
    to its ``I_max``), so that axis's position and velocity controllers run without
    effect; ``state['force']`` records ``rho``, ``rho'`` and ``F_6`` [N].  ``remat=True``
    recomputes each outer period in the backward pass instead of storing its inner steps
    (``jax.checkpoint``): reverse-mode memory then grows with the number of outer periods
    only, for about one extra forward pass.

    ``compliance``: ``(AdmittanceGains, Geometry)`` runs the admittance of
    :mod:`pusupu_jax.compliance` outside the position loops (:func:`compliant_pieces`; the
    plant must observe a ``contact_force``); ``reference`` is then a
    :class:`~pusupu_jax.compliance.ComplianceReference`.

    A reference whose samples are :class:`Injected` adds its signals at the controller outputs (the velocity and
    current references), for measuring loop gains (:mod:`pusupu_jax.injection`).  A reference of :class:`Commanded`
    samples runs a bridge's commands as its log says the robot ran them (:mod:`pusupu_jax.machine_fit`).

    ``counted_speed``: the drives take their speed from the encoder's counts (:func:`pieces`); the trace's ``omega``
    stays the motors' speed.
    """
    mode = cascade_.control_mode(outer)
    cascade = _cascade(params, plant_params, plant, rates, mode, hybrid, compliance, counted_speed)
    if init is None:
        init = _start(cascade, mode, jax.tree.map(lambda x: x[0], reference), start, compliance)
    if isinstance(reference, Commanded):  # every reading the robot had before its first period: the start's
        init = init._replace(measured=tuple(jnp.stack([x] * AGES) for x in cascade.sensed(init)))
    _, rec = jax.lax.scan(_body(cascade, remat), init, reference)
    return _trace(rec, cascade.dt)


def _cascade(
    params: ServoParams,
    plant_params: Any,
    plant: Plant,
    rates: LoopRates,
    mode: cascade_.ControlMode,
    hybrid: hybrid_law.HybridGains | None,
    compliance: tuple[compliance_law.AdmittanceGains, Geometry] | None,
    counted_speed: bool = False,
) -> Pieces:
    cascade = pieces(
        params, plant_params, plant=plant, rates=rates, mode=mode, hybrid=hybrid, counted_speed=counted_speed
    )
    return cascade if compliance is None else compliant_pieces(cascade, params, *compliance, mode=mode)


def _start(
    cascade: Pieces,
    mode: cascade_.ControlMode,
    first: Any,
    start: str,
    compliance: tuple[compliance_law.AdmittanceGains, Geometry] | None,
    rest: Rest | None = None,
) -> Carry:
    """The carry at ``start`` for a reference whose first sample is ``first`` (``rest``: :func:`initial_state`'s)."""
    first, _ = _injected(_commanded(first)[0])
    first = first.inner if compliance is not None else first
    return cascade.init(start, first.force_ff if mode.hybrid else None, rest)


def initial_carry(
    params: ServoParams,
    plant_params: Any,
    first: Any,
    *,
    plant: Plant = AxisPlant(),
    rates: LoopRates = LoopRates(),
    outer: str = "imc",
    hybrid: hybrid_law.HybridGains | None = None,
    start: str = "rest",
    compliance: tuple[compliance_law.AdmittanceGains, Geometry] | None = None,
    rest: Rest | None = None,
) -> Carry:
    """The carry :func:`rollout` starts from, for a reference whose first sample is ``first`` (pure; arguments as
    :func:`rollout`'s).  With :func:`rollout_chunk`, a run cut into calls of one fixed length.  ``rest``: the plant's
    :func:`plant_rest`, computed before, or None to compute it here (:func:`initial_state`)."""
    mode = cascade_.control_mode(outer)
    return _start(
        _cascade(params, plant_params, plant, rates, mode, hybrid, compliance), mode, first, start, compliance, rest
    )


def rollout_chunk(
    params: ServoParams,
    plant_params: Any,
    reference: Any,
    carry: Carry,
    n_valid: ArrayLike,
    *,
    plant: Plant = AxisPlant(),
    rates: LoopRates = LoopRates(),
    outer: str = "imc",
    hybrid: hybrid_law.HybridGains | None = None,
    compliance: tuple[compliance_law.AdmittanceGains, Geometry] | None = None,
) -> tuple[dict[str, Any], Carry]:
    """``reference`` ``(C, ...)`` from ``carry``: ``(records, the carry after its first n_valid periods)`` (pure;
    arguments as :func:`rollout`'s).  The records are :class:`Trace`'s fields but ``t``.

    ``n_valid`` (traced): the carry advances through the first ``n_valid`` periods only; the periods after them are
    computed and recorded, but leave the carry as it was (a select per period).  So one compiled program of length
    ``C`` runs a path of any length, in calls that stop wherever one wants the carry
    (:func:`~pusupu_jax.chunked.run_chunked`), and a run that keeps no carry runs the same program.  The select costs
    no run time that shows on the MJX machine (3 s of the arc in calls of 250 periods, 2-core CPU: 1.27 to 1.73 s
    with it, 1.31 to 1.57 s without), some 10 % on the single-axis plant, whose step is a few small matrices.
    """
    mode = cascade_.control_mode(outer)
    body = _body(_cascade(params, plant_params, plant, rates, mode, hybrid, compliance), False)

    def step(c: Carry, x: tuple[Any, jax.Array]) -> tuple[Carry, dict[str, Any]]:
        ref, valid = x
        c_next, rec = body(c, ref)
        return jax.tree.map(lambda new, old: jnp.where(valid, new, old), c_next, c), rec

    n = jax.tree.leaves(reference)[0].shape[0]
    carry, rec = jax.lax.scan(step, carry, (reference, jnp.arange(n) < n_valid))
    return rec, carry


def _body(cascade: Pieces, remat: bool) -> Callable[[Carry, Any], tuple[Carry, dict[str, Any]]]:
    def body(c: Carry, ref: Any) -> tuple[Carry, dict[str, Any]]:
        c_next, command = cascade.period(c, ref)
        return c_next, cascade.record(c, ref, command)

    return jax.checkpoint(body) if remat else body


def _trace(rec: dict[str, Any], dt: float) -> Trace:
    return Trace(t=jnp.arange(rec["reference"].shape[0]) * dt, **rec)


_rollout_jit = jax.jit(rollout, static_argnames=("plant", "rates", "outer", "remat", "start"))


@functools.lru_cache(maxsize=None)
def _batched_rollout(
    plant: Plant, rates: LoopRates, outer: str, load_axis: int | None, start: str
) -> jax.stages.Wrapped:
    return jax.jit(
        jax.vmap(
            functools.partial(rollout, plant=plant, rates=rates, outer=outer, start=start), in_axes=(0, load_axis, 0)
        )
    )


def simulate(
    params: ServoParams | None = None,
    reference: npt.ArrayLike | None = None,
    *,
    load: AxisLoad | None = None,
    plant: Plant = AxisPlant(),
    rates: LoopRates = LoopRates(),
    mode: str = "imc",
    start: str = "rest",
) -> Trace:
    """Simulate the position-controlled machine (host-side entry point).

    ``reference``: slider positions [m], shape ``(N,)`` (same for every axis) or
    ``(N, n_axes)``, one sample per position-loop period ``rates.dt_position``; the
    machine starts at rest at zero, held there by its drives (``start='rest'``) or with every
    controller state zero (``'zero'``).  ``mode``: 'imc' (2-DOF IMC, ``params.imc_form``),
    'pid' (baseline) or 'pid_ff' (PID with velocity feedforward).
    ``params`` with a leading batch dimension ``(B, n_axes)`` runs a vmapped batch
    (``load`` batched alike or shared).  Returns a :class:`Trace`.
    """
    params = ServoParams.table1() if params is None else params
    load = AxisLoad.default() if load is None else load
    if mode not in MODES:
        raise ParameterError(f"mode: expected one of {tuple(map(str, MODES))}, got {mode!r}")
    if start not in STARTS:
        raise ParameterError(f"start: expected one of {STARTS}, got {start!r}")
    validate(params)
    validate(load)
    ref = np.asarray(reference, dtype=float) if reference is not None else None
    if ref is None or ref.ndim not in (1, 2) or ref.shape[0] < 1 or (ref.ndim == 2 and ref.shape[1] != plant.n_axes):
        raise ParameterError(
            f"reference: expected slider positions of shape (N,) or (N, {plant.n_axes}), "
            f"got {None if ref is None else ref.shape}"
        )
    if not np.isfinite(ref).all():
        raise ParameterError("reference: expected finite slider positions [m], found NaN or inf")
    if ref.ndim == 1:
        ref = np.repeat(ref[:, None], plant.n_axes, axis=1)
    theta_ref = jnp.asarray(ref) / screw_ratio(params)[..., None, :]
    if np.ndim(params.lambda1) == 1:
        # jax.jit's wrapper returns Any
        return cast(Trace, _rollout_jit(params, load, theta_ref, plant=plant, rates=rates, outer=mode, start=start))
    load_axis = 0 if np.ndim(load.mass) == 2 else None
    return cast(Trace, _batched_rollout(plant, rates, mode, load_axis, start)(params, load, theta_ref))
