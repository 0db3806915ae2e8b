"""A simulated robot behind the bridge's transport: the MJX machine and its drives' inner loops, in step with the
bridge.

A package of its own (``pusupu_jax.sim_robot``), since it imports the mechanism (MuJoCo MJX),
which the bridge (``pusupu_jax.hw_bridge``) never does; it speaks the bridge's transports and
drive state machine.  ``pusupu sim-robot --listen udp://127.0.0.1:PORT`` runs it.

Each valid command from the bridge goes to the six drives' CiA 402 state machines, and a drive
faults, as a CiA 402 drive does, on a mode of operation it does not have (it has CSV and CST) or a
target that is not finite or beyond its limit (:func:`~pusupu_jax.params.command_limits`); a
faulted drive applies no torque.  While all six are 'operation enabled' the machine advances one
bridge period under the command (CSV: each drive's velocity loop follows the speed target; CST:
its current loop follows the torque target), with the same drive-side functions the simulator
scans (:func:`pusupu_jax.sim.pieces`, :func:`pusupu_jax.cascade.velocity_tick`).  Then the robot
replies with the actual values.  In 'quick stop active' the drives stop the machine with their own
velocity loops (speed zero); in any other state the brakes hold it (the mechanism does not
move).  The machine runs one period per command, so it keeps the bridge's real-time rate; if
commands stop for ``watchdog_s`` while enabled, the drives fault (their own sync watchdog) and the
brakes engage.

A new session starts when the drives are brought up again from 'switch on disabled': the
machine is then at rest at home, held by its drives, and the next fault of the schedule arms.

Faults on demand (``--fault KIND@T[:ARG]``, one per session, ``T`` [s] of machine time after enable, so
that they come at the same cycle however loaded the host is):
``stop`` (silent for ARG s, default 1), ``delay`` (replies ARG s late, default 0.02),
``drop`` (replies dropped with probability ARG, default 1), ``reorder`` (replies sent in
reverse order in blocks of ARG, default 8), ``corrupt`` (a byte flipped with probability
ARG, default 1; over CANopen a frame cut short), ``nan`` (NaN positions; not over CANopen, whose
values are integers), ``range`` (positions ARG rad off, default 1e4: metres of travel),
``garbage`` (every reply comes with malformed, truncated, oversized, wrong-version and replayed
packets; over CANopen, cut-short frames and the previous answer again), ``none``.  ARG's bounds
are in :data:`ARGS` (at most 60 s of silence or delay, blocks of 1 to 1000 replies).
"""

from __future__ import annotations

import enum
import functools
import gc
import heapq
import os
import sys
import time
from dataclasses import dataclass

import jax
import jax.numpy as jnp
import mujoco
import numpy as np

from pusupu_jax import cascade, loops, sim
from pusupu_jax.gains import GainFile
from pusupu_jax.machine import machine_plant, machine_rates
from pusupu_jax.machine_file import Machine
from pusupu_jax.params import command_limits
from pusupu_jax.plant.friction import Friction, slider_friction
from pusupu_jax.plant.model import ModelOptions, build_model, slide_dofs, slide_qpos
from pusupu_jax.runtime import require_x64

from pusupu_jax.hw_bridge import cia402, protocol
from pusupu_jax.hw_bridge.canopen_link import thousandths
from pusupu_jax.hw_bridge.compiled import FlatStep, cpu
from pusupu_jax.hw_bridge.runner import realtime_setup, steal_seconds
from pusupu_jax.hw_bridge.udp import Endpoint


class Injected(enum.StrEnum):
    """A fault the simulated robot injects on demand (the module docstring says what each does)."""

    NONE = "none"
    STOP = "stop"
    DELAY = "delay"
    DROP = "drop"
    REORDER = "reorder"
    CORRUPT = "corrupt"
    NAN = "nan"
    RANGE = "range"
    GARBAGE = "garbage"


FAULTS = tuple(Injected)
# the argument of each fault that takes one: its bounds and what it is (a reorder block, in replies, is a whole number)
ARGS = {
    Injected.STOP: (0.0, 60.0, "seconds of silence"),
    Injected.DELAY: (0.0, 60.0, "seconds of delay"),
    Injected.DROP: (0.0, 1.0, "a probability"),
    Injected.REORDER: (1, 1000, "a whole number of replies"),
    Injected.CORRUPT: (0.0, 1.0, "a probability"),
    Injected.RANGE: (-1e6, 1e6, "rad of motor angle"),
}
TARGET_TOLERANCE = 1e-3  # of a limit: a target beyond it by less is taken (CANopen rounds a torque to 1/1000 of rated)
DEFAULT_ARG = {
    Injected.STOP: 1.0,
    Injected.DELAY: 0.02,
    Injected.DROP: 1.0,
    Injected.REORDER: 8,
    Injected.CORRUPT: 1.0,
    Injected.RANGE: 1.0e4,
}


@dataclass(frozen=True)
class FaultSpec:
    kind: Injected = Injected.NONE
    at: float = 0.0  # s after enable
    arg: float | None = None

    @classmethod
    def parse(cls, text: str) -> "FaultSpec":
        """``KIND@T[:ARG]`` or ``none``, ``T`` finite and not negative and ``ARG`` within :data:`ARGS` (no ``ARG`` for
        the kinds that take none); ValueError naming what was expected."""
        name, _, rest = text.partition("@")
        at, _, arg = rest.partition(":")
        kind = Injected(name) if name in FAULTS else None
        try:
            spec = cls(kind, float(at) if at else 0.0, float(arg) if arg else DEFAULT_ARG.get(kind))
        except ValueError:
            raise ValueError(f"--fault: expected KIND@SECONDS[:ARG] with numbers, got {text!r}") from None
        if kind is None or not 0 <= spec.at < np.inf:
            raise ValueError(
                f"--fault: expected KIND@SECONDS[:ARG], KIND one of {tuple(map(str, FAULTS))} and "
                f"SECONDS finite and not negative, got {text!r}"
            )
        if kind not in ARGS and arg:
            raise ValueError(f"--fault {text}: expected no ARG for {kind}, got {arg!r}")
        if kind in ARGS:
            low, high, what = ARGS[kind]
            whole = isinstance(low, int)
            if not (low <= spec.arg <= high and (not whole or spec.arg == int(spec.arg))):
                raise ValueError(f"--fault {text}: expected ARG {what} in [{low:g}, {high:g}], got {arg}")
        return spec


class RobotModel:
    """The mechanism (C MuJoCo) and its drives (the simulator's functions, compiled on the CPU), one bridge period per
    call.

    The mechanism is the machine's own MuJoCo model (:func:`pusupu_jax.plant.model.build_model`, seeded
    kinematic errors included) stepped by C MuJoCo with the MJX plant's armature, torque mapping and
    drive-train friction (:func:`pusupu_jax.plant.friction.slider_friction`, in numpy, at the slider
    speeds at each step's start), as the MJX machine steps: one step per velocity period (the timestep is
    ``rates.dt_velocity``), the current loop's ticks inside it on the speed at its start, their mean torque held over
    it.  With ``fine_steps`` N, a truth finer than that model: N steps per current-loop tick (the timestep
    ``rates.dt_current / N``), each tick on the motors' speed after the last step, its torque held over its N steps;
    with the machine's ``encoder_counts``, the drives and the feedback see whole encoder counts, where each
    encoder's counts fall against its motor's angle (how it was mounted) a phase within one count drawn per axis
    from ``noise_seed``, and each drive's speed is the counts it saw over the last velocity period; with its
    ``current_noise``, each current the drives report (and the torque they report, ``Kt`` times it) carries Gaussian
    noise of that standard deviation, drawn from ``noise_seed`` (the drives' own current loops close on the true
    current);
    the drives at rest start from the MJX plant's static equilibrium, as the simulator's runs do.  Why C
    MuJoCo: on this 2-core CPU an MJX step through JAX's dispatch took about 300 us, more than a 250 us
    cycle; C MuJoCo takes tens (and the friction law in numpy 2 us).
    """

    def __init__(
        self,
        gains: GainFile,
        rate: float | None = None,
        kin_error_seed: int | None = None,
        cst: bool = False,
        machine: Machine | None = None,
        noise_seed: int = 0,
        fine_steps: int | None = None,
    ):
        from pusupu_jax.hw_bridge.loop import bridge_rates

        require_x64("the simulated robot's drives")
        if fine_steps is not None and not (isinstance(fine_steps, int) and fine_steps >= 1):
            raise ValueError(f"fine_steps: expected a whole number of steps of at least 1, got {fine_steps!r}")
        self.fine_steps = fine_steps
        self.servo = servo = gains.servo
        self.rates = bridge_rates(gains.rates, cst, rate)  # the bridge's, for its drive-mode pattern
        machine = Machine.default() if machine is None else machine
        step = self.rates.dt_velocity if fine_steps is None else self.rates.dt_current / fine_steps
        options = machine.options(ModelOptions(timestep=step, kin_error_seed=kin_error_seed))
        nominal = ModelOptions(timestep=self.rates.dt_velocity)
        plant = machine_plant(nominal)
        rates = machine_rates(nominal, self.rates)
        vmode = cascade.control_mode("velocity")
        carry0 = jax.jit(
            lambda model: sim.pieces(servo, model, plant=plant, rates=rates, mode=vmode, hybrid=None).init(
                "rest", None, None
            )
        )(jax.device_put(plant.variant(options, machine.geometry), cpu()))
        self.m = build_model(machine.geometry, options)
        self.dofs, self.qpos = slide_dofs(self.m), slide_qpos(self.m)
        r = np.asarray(servo.lead / (2 * np.pi), dtype=float)
        self.m.dof_armature[self.dofs] = np.asarray(servo.eta * servo.J, dtype=float) / r**2
        self.r, self.force_gain = r, np.asarray(servo.eta, dtype=float) / r
        self.friction = jax.tree.map(lambda x: np.asarray(x, dtype=float), Friction.of(servo))  # numpy: no dispatch
        self.Kt = np.asarray(servo.Kt, dtype=float)
        self.velocity_limit, self.torque_limit = command_limits(servo)  # rad/s, N m: a drive faults on more
        self.platform = self.m.body("platform").id
        # the encoders: one count [rad at the motor], or None (ideal); a drive measures its speed as the counts it
        # saw over one velocity period, as a drive without a speed observer does
        counts = machine.encoder_counts
        self.count = None if counts is None else 2 * np.pi / np.asarray(counts, dtype=float)
        # the encoders' phases [counts], a stream of the seed's own: the current noise's draws stay those of the seed
        self.phase = np.random.default_rng((noise_seed, 1)).uniform(size=len(servo.Kt))
        self._last_angle = np.zeros(len(self.Kt))
        self._measured = np.zeros(len(self.Kt))
        self.current_noise = machine.current_noise  # A, or None: noise-free current sensors
        self._noise = np.random.default_rng(noise_seed)

        def velocity_part(d, state, target, cst_mask, omega):
            electrical, sc = state
            sc, i_vel = cascade.velocity_tick(d, vmode, sc, jnp.where(cst_mask, 0.0, target), omega)
            limit = d.velocity.limit
            return (electrical, sc), jnp.where(cst_mask, jnp.clip(target / d.Kt, -limit, limit), i_vel)

        def ticks(n, d, state, i_ref, omega):
            electrical, sc = state
            electrical, sc, torque, _ = sim.current_ticks(d, electrical, sc, i_ref, omega, n)
            # the torque the motors gave over the ticks (the mechanism's), and the armature current after them:
            # what the current sensors read when the drives answer, the sample the simulator's trace records
            return (electrical, sc), jnp.concatenate([torque, loops.electrical_current(electrical)])

        def velocity_period(d, state, target, cst_mask, omega):
            state, i_ref = velocity_part(d, state, target, cst_mask, omega)
            return ticks(rates.n_mech, d, state, i_ref, omega)

        z, no = np.zeros(len(self.Kt)), np.zeros(len(self.Kt), bool)
        consts, state0 = (loops.discretize(servo, rates),), (carry0.electrical, carry0.cascade)
        if fine_steps is None:
            self._drive = FlatStep(velocity_period, consts, state0, (z, no, z))
        else:  # the velocity tick, then each current tick apart
            self._drive = FlatStep(velocity_part, consts, state0, (z, no, z))
            self._tick = FlatStep(functools.partial(ticks, 1), consts, state0, (z, z))
        self.drive0 = self._drive.state
        self.current0 = np.asarray(loops.electrical_current(carry0.electrical))

    def reset(self, d):
        """``d``, an ``MjData`` of this model, reset in place to the machine at rest at home, held by its drives;
        returns
        the drives' state.  In place, since allocating one in the serving process, whose memory is locked
        (``mlockall``: new pages are faulted in at once), took 32 ms at the start of a bridge session, and the
        bridge's watchdog stopped the session."""
        mujoco.mj_resetData(self.m, d)
        mujoco.mj_forward(self.m, d)
        self._last_angle[:] = self._encoder(d)
        self._measured[:] = 0.0
        return self.drive0

    def _encoder(self, d):
        """The motor angles [rad] the encoders read in ``d``: the true ones, or whole counts of them from each
        encoder's phase."""
        theta = (d.qpos[self.qpos] - self.m.qpos0[self.qpos]) / self.r
        return theta if self.count is None else (np.floor(theta / self.count + self.phase) - self.phase) * self.count

    def _speed(self, d):
        """The motor speeds [rad/s] the drives measure in ``d``, one velocity period after the last reading: the
        true ones, or the counts seen since then over that period."""
        if self.count is None:
            return d.qvel[self.dofs] / self.r
        angle = self._encoder(d)
        speed = (angle - self._last_angle) / self.rates.dt_velocity
        self._last_angle[:] = angle
        return speed

    def actual(self, d):
        """``(theta [rad], omega [rad/s], platform [m])`` of the machine in ``d`` as its drives measure them: the
        encoders' angles, the speeds of the last velocity period (:meth:`_speed`), and the platform's true
        position."""
        omega = d.qvel[self.dofs] / self.r if self.count is None else self._measured
        return self._encoder(d), omega, d.xpos[self.platform].copy()

    def sensed(self, current):
        """``(torque [N m], current [A])`` as the drives report them when their motors' armature current is
        ``current``: that current with the current sensors' noise where the machine has it, and the torque ``Kt``
        times the reported current."""
        if self.current_noise is not None:
            current = current + self.current_noise * self._noise.standard_normal(len(current))
        return self.Kt * current, current

    def advance(self, d, state, target, cst_mask):
        """One bridge period under ``target`` (CSV: rad/s; CST: N m): the drive state and the motors' armature
        currents [A] at its end (what the drives' sensors read when they answer)."""
        n = len(self.Kt)
        current = np.zeros(n)
        for _ in range(1 if np.any(cst_mask) else self.rates.n_position):  # velocity periods in a bridge period
            self._measured = self._speed(d)
            if self.fine_steps is None:
                state, out = self._drive(state, target, cst_mask, self._measured)
                self._step(d, out[:n], 1)
                current = out[n:]
                continue
            state, i_ref = self._drive(state, target, cst_mask, self._measured)
            for _ in range(self.rates.n_velocity):  # each current tick on the motors' speed now
                state, out = self._tick(state, i_ref, d.qvel[self.dofs] / self.r)
                self._step(d, out[:n], self.fine_steps)
                current = out[n:]
        return state, current

    def _step(self, d, torque, steps):
        """``steps`` steps of the mechanism in ``d`` under the motors' ``torque`` [N m], the drive train's friction
        taken at the slider speeds at each step's start."""
        for _ in range(steps):
            d.qfrc_applied[self.dofs] = self.force_gain * torque - slider_friction(self.friction, d.qvel[self.dofs])
            mujoco.mj_step(self.m, d)


class SimRobot:
    """The robot's controller, transport aside: a command in, the drives and the machine one period on, feedback out.

    Also the drives' sync watchdog (:meth:`watch`) and the faults that change what the robot measures or
    whether it answers (``stop``, ``nan``, ``range``); the transports add the faults of their packets.
    """

    def __init__(self, model: RobotModel, faults=(), watchdog_s: float = 0.05, log=print):
        self.model = model
        self.faults = list(faults)
        self.watchdog_s = watchdog_s
        self.log = log
        self.drives = [cia402.DriveStateMachine() for _ in model.Kt]
        self.mode = np.full(len(self.drives), protocol.CSV, np.int8)
        self.session = -1
        self.sequence = 0
        self.last = time.monotonic()
        self.stalls = Stalls(log)
        self.data = mujoco.MjData(model.m)  # made once, before the serving process locks its memory
        self._new_session()

    def _new_session(self):
        self.session += 1
        self.state = self.model.reset(self.data)
        self.current = self.model.current0
        self.fault = self.faults[self.session] if self.session < len(self.faults) else FaultSpec()
        self.enabled_at = None
        self.sim_time = 0.0  # s of machine time since enable (periods run)
        self.silent_until = 0.0
        self.applied = 0
        self.began = False  # the session's fault has come due (begins)

    @property
    def due(self) -> bool:
        """The session's fault is due: ``at`` seconds of machine time (periods run) after enable."""
        return self.enabled_at is not None and self.sim_time >= self.fault.at

    def active(self, kind: Injected, now: float) -> bool:
        """The session's fault is ``kind`` and :attr:`due`."""
        return self.fault.kind == kind and self.due

    def begins(self, what: str, number: int) -> None:
        """After each command: the first time the session's fault is due, say so on the log, naming the command as the
        bridge numbers it (``what``, ``number``: its sequence over UDP, its SYNC's counter over CANopen).  A command the
        robot never received (a frame lost while it stalled) runs no period, so the onset can come later in the
        bridge's count than ``at`` seconds after enable."""
        if self.began or self.fault.kind == Injected.NONE or not self.due:
            return
        self.began = True
        self.log(f"sim-robot: session {self.session}: fault {self.fault.kind} begins on {what} {number}")

    def watch(self, now: float) -> None:
        """Each turn of the serving loop: the drives' sync watchdog (enabled and no command for ``watchdog_s``: fault,
        brakes on), and the loop's own stalls (:class:`Stalls`)."""
        self.stalls.turn(now)
        if all(d.enabled for d in self.drives) and now - self.last > self.watchdog_s:
            for d in self.drives:
                d.fault()
            self.log(
                f"sim-robot: session {self.session}: no command for {self.watchdog_s * 1e3:.0f} ms: "
                "drives faulted, brakes on"
            )

    def handle(self, cmd: protocol.Command, now: float) -> protocol.Feedback | None:
        """Apply one command; the feedback to send (None: the robot is silent)."""
        if now < self.silent_until:
            return None
        if self.active(Injected.STOP, now):
            self.silent_until = now + self.fault.arg
            self.fault = FaultSpec()
            self.log(f"sim-robot: session {self.session}: stopped (silent for {self.silent_until - now:.2f} s)")
            return None
        self.last = now
        before = {d.state for d in self.drives}
        for d, w in zip(self.drives, cmd.controlword):
            d.command(int(w))
        self._refuse(cmd)
        after = {d.state for d in self.drives}
        if after == {cia402.READY} and before != {cia402.READY} and self.enabled_at is not None:
            self._new_session()  # brought up again after a session that ran
        elif self.enabled_at is not None and cia402.OPERATION_ENABLED not in after and self.fault.kind != Injected.NONE:
            self.log(f"sim-robot: session {self.session}: stopped by the bridge; fault {self.fault.kind} ends")
            self.fault = FaultSpec()
        if after == {cia402.OPERATION_ENABLED}:
            if self.enabled_at is None:
                self.enabled_at = now
            self.mode = np.asarray(cmd.mode, np.int8)
            cst = self.mode == protocol.CST
            self.state, self.current = self.model.advance(
                self.data, self.state, np.asarray(cmd.target, dtype=float), cst
            )
            self.sim_time += self.model.rates.dt_velocity * (1 if cst.any() else self.model.rates.n_position)
        elif after == {cia402.QUICK_STOP_ACTIVE}:
            self.state, self.current = self.model.advance(
                self.data, self.state, np.zeros(len(self.drives)), np.zeros(len(self.drives), bool)
            )
        self.applied = cmd.sequence
        theta, omega, platform = self.model.actual(self.data)
        if self.active(Injected.NAN, now):
            theta = theta * np.nan
        if self.active(Injected.RANGE, now):
            theta = theta + self.fault.arg
        faulted = np.array([d.state == cia402.FAULT for d in self.drives])
        # a faulted drive's power stage is off
        torque, current = (np.where(faulted, 0.0, x) for x in self.model.sensed(self.current))
        fb = protocol.Feedback(
            self.sequence,
            time.monotonic_ns(),
            self.applied,
            np.array([d.statusword for d in self.drives], np.uint16),
            self.mode,
            theta,
            omega,
            torque,  # the torque a drive reports: Kt times the current it measures
            platform,
            current,  # the current loop's current as its sensor measures it [A] (protocol version 2)
        )
        self.sequence += 1
        return fb

    def _refuse(self, cmd: protocol.Command) -> None:
        """Fault each drive whose command a CiA 402 drive would not take: a mode of operation other than CSV and CST, or
        a target that is not finite or beyond its limit (CSV: ``V_max/Ke`` [rad/s], CST: ``Kt I_max`` [N m]; by more
        than :data:`TARGET_TOLERANCE` of it)."""
        mode, target = np.asarray(cmd.mode), np.asarray(cmd.target, dtype=float)
        known = (mode == protocol.CSV) | (mode == protocol.CST)
        bound = np.where(mode == protocol.CST, self.model.torque_limit, self.model.velocity_limit)
        bad = ~known | ~(np.abs(target) <= bound * (1 + TARGET_TOLERANCE))  # NaN is beyond every bound
        for k in np.flatnonzero(bad):
            if self.drives[k].state == cia402.FAULT:
                continue
            self.drives[k].fault()
            why = (
                f"target {target[k]:.6g}, expected a finite number within +-{bound[k]:.6g}"
                if known[k]
                else f"mode of operation {mode[k]}, expected {protocol.CSV} (CSV) or {protocol.CST} (CST)"
            )
            self.log(f"sim-robot: session {self.session}: drive {k + 1} faulted: {why}")


class Stalls:
    """The serving loop's turns that came more than ``threshold`` [s] after the one before (the robot did not run:
    its CPU was taken, or a command took that long), each logged with the hypervisor's steal time per CPU since the
    previous report (:func:`~pusupu_jax.hw_bridge.runner.steal_seconds`), the first ``shown`` of them; ``count`` counts
    all."""

    def __init__(self, log, threshold: float = 5e-3, shown: int = 20):
        self.log, self.threshold, self.shown = log, threshold, shown
        self.count = 0
        self.last = None
        self.steal = steal_seconds()

    def turn(self, now: float) -> None:
        gap = 0.0 if self.last is None else now - self.last
        self.last = now
        if gap <= self.threshold:
            return
        self.count += 1
        if self.count > self.shown:
            return
        steal, before = steal_seconds(), self.steal
        self.steal = steal
        stolen = (
            "not counted"
            if steal is None or before is None
            else ", ".join(f"CPU {k} {1e3 * d:.0f} ms" for k, d in enumerate(steal - before))
        )
        more = " (the last shown; later stalls are counted only)" if self.count == self.shown else ""
        self.log(
            f"sim-robot: stall {self.count}: the serving loop did not turn for {gap * 1e3:.1f} ms; "
            f"hypervisor steal since the previous report: {stolen}{more}"
        )


class HeldReplies:
    """The replies that the ``delay`` and ``reorder`` faults hold back, for either transport: ``send(reply)`` sends one.

    ``reply`` sends at once, holds until ``now + ARG`` (delay: sent by :meth:`release`), or collects blocks of
    ARG replies sent newest first (reorder).  :meth:`follow` drops what is held when the robot starts a new session.
    """

    def __init__(self, robot: SimRobot, send):
        self.robot, self.send = robot, send
        self.session = robot.session
        self.queue = []  # (due time, order, reply): replies held back (delay)
        self.block = []  # replies held back to be sent in reverse (reorder)

    def follow(self) -> None:
        if self.robot.session != self.session:
            self.session, self.queue, self.block = self.robot.session, [], []

    def reply(self, reply, order: int, now: float) -> None:
        r = self.robot
        if r.active(Injected.REORDER, now):
            self.block.append(reply)
            if len(self.block) >= int(r.fault.arg):
                for held in reversed(self.block):
                    self.send(held)
                self.block = []
        elif r.active(Injected.DELAY, now):
            heapq.heappush(self.queue, (now + r.fault.arg, order, reply))
        else:
            self.send(reply)

    def release(self, now: float) -> None:
        """Send the delayed replies that are due.  (Over CAN the SYNC callback's thread adds them and the serving
        thread releases them: each heapq call is atomic under the GIL, and what is added later is due later.)"""
        while self.queue and self.queue[0][0] <= now:
            self.send(heapq.heappop(self.queue)[2])


class UdpServer:
    """The robot behind UDP, with the faults of its packets: ``drop``, ``corrupt``, ``garbage``, ``reorder``,
    ``delay``."""

    def __init__(self, robot: SimRobot, endpoint: Endpoint, seed: int = 0):
        self.robot, self.ep = robot, endpoint
        self.rng = np.random.default_rng(seed)
        self.held = HeldReplies(robot, endpoint.send)
        self._last = b""

    def _send(self, fb: protocol.Feedback, now: float) -> None:
        r, data = self.robot, protocol.encode_feedback(fb)
        if r.active(Injected.DROP, now) and self.rng.random() < r.fault.arg:
            return
        if r.active(Injected.CORRUPT, now) and self.rng.random() < r.fault.arg:
            b = bytearray(data)
            b[int(self.rng.integers(len(b)))] ^= 0xFF
            data = bytes(b)
        if r.active(Injected.GARBAGE, now):
            for bad in (
                data[:17],
                data + bytes(protocol.MAX_PACKET),
                data[:4] + b"\x09" + data[5:],
                b"\x00" * len(data),
                self._last or data,
            ):
                self.ep.send(bad)
            self._last = data
        self.held.reply(data, fb.sequence, now)

    def serve(self, max_s: float | None = None) -> None:
        """Serve commands until ``max_s`` [s] pass (None: until interrupted)."""
        end = None if max_s is None else time.monotonic() + max_s
        while end is None or time.monotonic() < end:
            cmd = self.ep.poll(timeout=0.001)
            now = time.monotonic()
            self.held.release(now)
            self.robot.watch(now)
            if cmd is None:
                continue
            fb = self.robot.handle(cmd, now)
            self.robot.begins("command", cmd.sequence)
            self.held.follow()
            if fb is not None:
                self._send(fb, now)


class CanServer:
    """The robot behind CANopen: six CiA 402 drive nodes (``canopen.LocalNode``) on one bus, driven by SYNC.

    Each drive answers SDO requests from its dictionary; on SYNC the robot takes every drive's last
    RPDO, runs one period, and sends each drive's two TPDOs (the second echoes the SYNC's counter).
    Faults: ``stop`` and ``drop`` (no TPDOs), ``range`` (positions off), ``delay`` (each SYNC's TPDOs
    sent ARG s late), ``reorder`` (the TPDOs of ARG SYNCs held, then sent newest first), ``corrupt``
    (each TPDO cut short with probability ARG: a CAN controller's CRC drops frames with flipped bits, so
    the damage that reaches software is a wrong length) and ``garbage`` (each answer comes after a cut-short
    copy of each of its TPDOs and before the previous answer, sent again); NaN has no integer encoding on
    the bus.
    """

    def __init__(self, robot: SimRobot, bus, seed: int = 0):
        import canopen

        from pusupu_jax.hw_bridge.canopen_link import COUNTS_PER_RAD, N_AXES, node_dictionary

        self.robot, self.scale = robot, COUNTS_PER_RAD
        self.rng = np.random.default_rng(seed)
        self._last = []  # the previous answer's frames (garbage: sent again)
        self.network = canopen.Network(bus)
        self.nodes = []
        for k in range(N_AXES):
            node = canopen.LocalNode(k + 1, node_dictionary(k + 1))
            self.network.add_node(node)
            node.sdo["Motor rated torque"].raw = int(round(float(robot.model.Kt[k] * robot.model.servo.I_max[k]) * 1e3))
            node.sdo["Motor rated current"].raw = int(round(float(robot.model.servo.I_max[k]) * 1e3))  # mA
            node.sdo["Modes of operation display"].raw = protocol.CSV
            node.add_write_callback(lambda index, subindex, od, data, node=node: self._on_write(node, index, data))
            node.rpdo.read(from_od=True)
            node.tpdo.read(from_od=True)
            self.nodes.append(node)
        self.rated = np.array([n.sdo["Motor rated torque"].raw for n in self.nodes], float) * 1e-3  # N m, fixed
        self.rated_current = np.array([n.sdo["Motor rated current"].raw for n in self.nodes], float) * 1e-3  # A
        self.held = HeldReplies(robot, self._send)
        import can

        self.network.notifier = can.Notifier(bus, self.network.listeners, 0.1)
        self.network.subscribe(0x80, self._on_sync)

    def _on_write(self, node, index, data) -> None:
        if index == 0x6060:  # the mode of operation, set over SDO, is displayed
            node.sdo["Modes of operation display"].raw = int.from_bytes(data[:1], "little", signed=True)

    def _on_sync(self, can_id, data, timestamp) -> None:
        now = time.monotonic()
        r = self.robot
        modes = np.array([n.sdo["Modes of operation display"].raw for n in self.nodes], np.int8)
        rated = self.rated
        maps = [n.rpdo[1] for n in self.nodes]
        target = np.where(
            modes == protocol.CST,
            np.array([m["Target torque"].raw for m in maps]) * rated / 1000.0,
            np.array([m["Target velocity"].raw for m in maps]) / self.scale,
        )
        cmd = protocol.Command(
            r.applied + 1, 0, 0, np.array([m["Controlword"].raw for m in maps], np.uint16), modes, target
        )
        fb = r.handle(cmd, now)
        r.begins("SYNC counter", data[0] if data else 0)
        self.held.follow()
        if fb is None or (r.active(Injected.DROP, now) and r.fault.arg >= 1.0):
            return
        frames = []  # the answer: each drive's two TPDOs, as (COB-ID, bytes) to send now or later
        torque, current = thousandths(fb.torque, rated), thousandths(fb.current, self.rated_current)
        for k, node in enumerate(self.nodes):
            t1, t2 = node.tpdo[1], node.tpdo[2]
            t1["Statusword"].raw = int(fb.statusword[k])
            t1["Position actual value"].raw = int(np.clip(round(fb.position[k] * self.scale), -(2**31), 2**31 - 1))
            t1["Torque actual value"].raw = int(torque[k])
            t2["Velocity actual value"].raw = int(np.clip(round(fb.velocity[k] * self.scale), -(2**31), 2**31 - 1))
            t2["Current actual value"].raw = int(current[k])
            t2["Modes of operation display"].raw = int(modes[k])
            t2["SYNC counter echo"].raw = data[0] if data else 0
            frames += [(t1.cob_id, bytes(t1.data)), (t2.cob_id, bytes(t2.data))]
        if r.active(Injected.CORRUPT, now):
            frames = [self._cut(f) if self.rng.random() < r.fault.arg else f for f in frames]
        if r.active(Injected.GARBAGE, now):
            frames, self._last = [self._cut(f) for f in frames] + frames + self._last, frames
        self.held.reply(frames, fb.sequence, now)

    def _cut(self, frame):
        """``frame`` with its data cut to a shorter length (0 to all but one byte)."""
        cob_id, payload = frame
        return cob_id, payload[: int(self.rng.integers(len(payload)))]

    def _send(self, frames) -> None:
        for cob_id, payload in frames:
            self.network.send_message(cob_id, payload)

    def serve(self, max_s: float | None = None) -> None:
        end = None if max_s is None else time.monotonic() + max_s
        while end is None or time.monotonic() < end:
            time.sleep(0.001)
            now = time.monotonic()
            self.held.release(now)
            self.robot.watch(now)


def main_loop(
    model: RobotModel, listen: str, faults, max_s=None, watchdog_s: float = 0.05, realtime: bool = True
) -> int:
    """Serve on ``listen`` (udp://HOST:PORT or can://INTERFACE/CHANNEL) until interrupted; one line when ready.
    ``watchdog_s``: the drives' sync watchdog (:meth:`SimRobot.watch`) [s].

    ``realtime``: ask for what a robot controller has (:func:`pusupu_jax.hw_bridge.runner.realtime_setup`: SCHED_FIFO at
    priority 70 on the first CPU, since the bridge takes the last); what the OS refused is said on stderr.  A 1 kHz
    command costs the robot about 140 us at p50 (four compiled drive steps and C MuJoCo steps), so a stall of a
    few ms on its CPU leaves the bridge without feedback past its watchdog (:class:`Stalls` reports them; README,
    "The real-time figures")."""
    robot = SimRobot(model, faults, watchdog_s, log=lambda m: print(m, file=sys.stderr, flush=True))
    if listen.startswith("can://"):
        from pusupu_jax.hw_bridge.canopen_link import open_bus

        server = CanServer(robot, open_bus(listen))
        where = listen
    else:
        from pusupu_jax.hw_bridge.udp import parse_url

        ep = Endpoint(protocol.COMMAND, n_axes=len(model.Kt), bind=parse_url(listen))
        server = UdpServer(robot, ep)
        where = "udp://{}:{}".format(*ep.address)
    # the objects of the set-up (JAX, MuJoCo, the compiled steps) leave the collector's view: a full collection
    # over them took 30-190 ms here (30 to 190 periods at 1 kHz without replies), and the bridge's watchdog stopped
    # runs on it
    gc.collect()
    gc.freeze()
    if realtime:
        granted = realtime_setup(priority=70, cpu=sorted(os.sched_getaffinity(0))[0])
        refused = [line for line in granted.lines() if "refused" in line]
        if refused:
            print(f"sim-robot: real-time {'; '.join(refused)}", file=sys.stderr, flush=True)
    print(f"sim-robot: listening on {where}", flush=True)
    try:
        server.serve(max_s)
    except KeyboardInterrupt:
        pass
    return 0
