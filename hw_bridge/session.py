"""One bridge run (host-side): bring the drives up through CiA 402, take over, run the loops, stop, report.

Per cycle: read the newest feedback, check it (:class:`~pusupu_jax.hw_bridge.safety.Safety`: fresh, finite, in range,
and
within the following-error window of the reference the machine was following), step the loops
(:class:`~pusupu_jax.hw_bridge.loop.BridgeLoop`), clamp the targets, send the command.  Phases:

1. *connect*: send shutdown until every drive reports 'ready to switch on' (``connect_s``);
2. *enable*: switch on, then enable operation, until every drive reports 'operation enabled';
3. *run*: :meth:`BridgeLoop.start` from the drives' actual values (no step), then the path;
4. *stop*: at the end, on a fault, or on SIGINT or SIGTERM: quick stop for ``stop_cycles``, then disable voltage.

Every way out of the cycles goes through the stop: an exception raised by the bridge's own code inside a cycle (the
loops, a decoder) is a fault like the others (``internal error``), and SIGINT and SIGTERM, caught while the run lasts,
stop it at the next cycle.  The record says why the run ended (:class:`End`).

``latency`` of a cycle: from its wake-up to its command sent: reading the feedback socket, the
checks, the step, the encoding and the ``sendto``.  ``feedback_age``: from the robot's send stamp to
our read of that feedback at the start of the cycle that used it (one monotonic clock on loopback):
the transport *plus* the wait for our next cycle, so at most one period more than the transport; none
over CANopen, whose frames carry no send time (its feedback's timestamp is 0).
"""

from __future__ import annotations

import contextlib
import dataclasses
import enum
import os
import signal
import threading
import time
from dataclasses import dataclass, field

import numpy as np

from pusupu_jax.run_log import Channel

from . import cia402, protocol
from .loop import BridgeLoop
from .runner import CycleRunner, percentiles, realtime_setup
from .safety import FaultKind, Safety


class End(enum.StrEnum):
    """Why a run ended: its path done, a fault (of the machine, the drives, the transport or the bridge's own code),
    or a signal; the first of them stands."""

    COMPLETED = "completed"
    FAULT = "fault"
    SIGINT = "SIGINT"
    SIGTERM = "SIGTERM"


SIGNALS = {signal.SIGINT: End.SIGINT, signal.SIGTERM: End.SIGTERM}
# bytes per cycle of a run, at most, that its record keeps (BridgeRun's samples and lists, the runner's timings, each
# command sent): with six axes the packets kept in the run and the commands take 1.59 kB a cycle, also the peak of
# building the per-sample lists from them after the run, which lets each packet go (tracemalloc, one packet a cycle);
# the rest is room for the lists' growth
RECORD_BYTES = 2048


def record_memory() -> int:
    """The memory [bytes] a run's record may take: half of this machine's."""
    return os.sysconf("SC_PHYS_PAGES") * os.sysconf("SC_PAGE_SIZE") // 2


def longest_run(rate: float) -> float:
    """The longest run [s] at ``rate`` [Hz] whose record fits in :func:`record_memory`, :data:`RECORD_BYTES` a cycle."""
    return record_memory() // RECORD_BYTES / rate


@contextlib.contextmanager
def _signals_noted(noted: list):
    """For the block, SIGINT and SIGTERM appended to ``noted`` instead of their usual effect, and the handlers of before
    put back after it; in the main thread only (Python runs signal handlers there alone)."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    before = {s: signal.signal(s, lambda signum, frame: noted.append(signum)) for s in SIGNALS}
    try:
        yield
    finally:
        for s, handler in before.items():
            signal.signal(s, signal.SIG_DFL if handler is None else handler)  # None: a handler not set from Python


@dataclass
class BridgeRun:
    """The record of one run: per-cycle arrays (``phase == 'run'`` cycles) and counters."""

    rate: float
    cycles: int = 0
    missed: int = 0
    skipped: int = 0
    latency_us: list = field(default_factory=list)
    feedback_age_us: list = field(default_factory=list)
    # per run cycle with a fresh sample, the time [us] its record took inside the cycle (keeping the sample): all that
    # logging does inside a cycle; the lists below are built from the samples after the run (settle), and the log's
    # file is written from them
    record_us: list = field(default_factory=list)
    # in the run, per sample that came (every packet, not only the newest of a cycle): the cycle of the reference it
    # answers and the packet (a protocol.Feedback)
    kept: list = field(default_factory=list, repr=False)
    robot_sequence: bool = False  # the packets' sequence numbers are the robot's, one a period (the endpoint's word)
    t: list = field(default_factory=list)
    numbers: list = field(default_factory=list)  # per sample, (its sequence number, the command's it answers) or None
    path_time: list = field(default_factory=list)  # per sample, the time along the path of its reference [s]
    reference: list = field(default_factory=list)
    position: list = field(default_factory=list)
    drive: list = field(default_factory=list)  # per sample (3, n_axes): velocity [rad/s], torque [N m], current [A]
    platform: list = field(default_factory=list)
    platform_reference: list = field(default_factory=list)
    # every command sent: (cycle, controlword, target, its sequence number, the feedback's it answers)
    commands: list = field(default_factory=list)
    # per command sent, the time along the path of the reference row it was computed from [s] (None: outside the run),
    # built after the run (settle)
    command_path_time: list = field(default_factory=list)
    faults: list = field(default_factory=list)
    rejected: dict = field(default_factory=dict)
    realtime: list = field(default_factory=list)
    completed: bool = False
    ended: End | None = None
    run_start: int | None = None  # the cycle at which the path began (None: it never did)

    def settle(self, loop) -> None:
        """After the run: the per-sample lists from the samples kept in it, against ``loop``'s reference (the time
        along the path, the motor angles and, where the path has it, the platform pose in force at each sample)."""
        self.kept.reverse()
        while self.kept:  # each packet let go as its fields are taken: the record's peak stays near its size
            cycle, fb = self.kept.pop()
            self.t.append(cycle / loop.rate)
            self.numbers.append((fb.sequence, fb.ack) if self.robot_sequence else None)
            self.reference.append(loop.reference_at(cycle))
            self.path_time.append(loop.path_time(cycle))
            self.position.append(fb.position)
            current = fb.current if fb.current is not None else np.full(len(fb.torque), np.nan)
            self.drive.append(np.stack([fb.velocity, fb.torque, current]))
            self.platform.append(fb.platform)
            if loop.reference.platform is not None:
                p = min(max(cycle // loop.n_position - loop.takeover_periods, 0), len(loop.reference.platform) - 1)
                self.platform_reference.append(loop.reference.platform[p])
        start = self.run_start if self.run_start is not None else np.inf
        self.command_path_time = [
            loop.path_time(k - self.run_start) if start <= k and word == cia402.ENABLE_OPERATION else None
            for k, word, *_ in self.commands
        ]

    def report(self, screw=None) -> BridgeReport:
        """The run's figures (``screw``: each axis's screw ratio [m/rad], for the branches' errors)."""
        branch_rms = branch_max = rms = peak = None
        if self.position and screw is not None:
            e = (np.asarray(self.position) - np.asarray(self.reference)) * np.asarray(screw) * 1e3
            branch_rms, branch_max = np.sqrt(np.mean(e**2, axis=0)).tolist(), np.abs(e).max(axis=0).tolist()
        if self.platform and self.platform_reference and np.isfinite(np.asarray(self.platform)).all():
            e = np.linalg.norm(np.asarray(self.platform) - np.asarray(self.platform_reference), axis=1) * 1e3
            rms, peak = float(np.sqrt(np.mean(e**2))), float(e.max())
        return BridgeReport(
            rate_hz=self.rate,
            cycles=self.cycles,
            missed_deadlines=self.missed,
            missed_fraction=self.missed / max(self.cycles + self.skipped, 1),
            skipped_cycles=self.skipped,
            latency_us=percentiles(self.latency_us),
            feedback_age_us=percentiles(self.feedback_age_us),
            record_us=percentiles(self.record_us),
            faults=tuple(f.line() for f in self.faults),
            rejected_packets=dict(self.rejected),
            realtime=tuple(self.realtime),
            completed=self.completed,
            ended=self.ended,
            branch_rms_error_mm=branch_rms,
            branch_max_error_mm=branch_max,
            rms_tracking_error_mm=rms,
            max_tracking_error_mm=peak,
        )


@dataclass(frozen=True)
class BridgeReport:
    """What a run reports: its cycles at ``rate_hz`` [Hz], the missed deadlines (and their fraction of the cycles
    due), the skipped cycles, the cycle's latency, the feedback's age and the time the run's record took inside a
    cycle (:func:`~pusupu_jax.hw_bridge.runner.percentiles` [us], None without samples), each fault as a line, the
    packets refused by kind, the real-time settings asked for and what came of each, whether the path completed and
    why the run ended; where the run followed the path, per branch the RMS and largest error [mm] (at the motor
    angle, through the screw) and the platform's RMS and largest tracking error [mm] (where the robot reports its
    platform)."""

    rate_hz: float
    cycles: int
    missed_deadlines: int
    missed_fraction: float
    skipped_cycles: int
    latency_us: dict[str, float] | None
    feedback_age_us: dict[str, float] | None
    record_us: dict[str, float] | None
    faults: tuple[str, ...]
    rejected_packets: dict[str, int]
    realtime: tuple[str, ...]
    completed: bool
    ended: End | None
    branch_rms_error_mm: list[float] | None = None
    branch_max_error_mm: list[float] | None = None
    rms_tracking_error_mm: float | None = None
    max_tracking_error_mm: float | None = None

    def as_dict(self) -> dict:
        """The report as ``pusupu bridge --json`` prints it: every field, the errors only where the run has them."""
        return {
            k: list(v) if isinstance(v, tuple) else v
            for k, v in dataclasses.asdict(self).items()
            if v is not None or k in ("latency_us", "feedback_age_us", "record_us", "ended")
        }


class Bridge:
    """Runs ``loop`` against the drives behind ``endpoint``: a :class:`~pusupu_jax.hw_bridge.udp.Endpoint` of FEEDBACK
    or a
    :class:`~pusupu_jax.hw_bridge.canopen_link.CanLink` (``send_command``, which counts a failed send in ``rejected``
    and does not
    raise, ``poll``, ``rejected``; and ``received_at`` [s, monotonic] where its feedback carries a send time)."""

    def __init__(
        self,
        loop: BridgeLoop,
        endpoint,
        safety: Safety,
        *,
        connect_s: float = 5.0,
        stop_cycles: int = 50,
        max_consecutive_misses: int = 3,
        hold_s: float = 0.0,
        lockstep_s: float = 0.0,
    ):
        """``lockstep_s`` > 0: each cycle waits up to that long for the answer to the previous command, and late
        cycles move the deadlines after them instead of skipping (``CycleRunner`` 'rephase'): a run whose result
        does not depend on scheduling, for tests on a shared machine.  0 (default): real time."""
        self.loop, self.endpoint, self.safety = loop, endpoint, safety
        self.lockstep_s = lockstep_s
        self.connect_cycles = int(connect_s * loop.rate)
        self.stop_cycles = stop_cycles
        self.max_misses = max_consecutive_misses
        self.hold_cycles = int(hold_s * loop.rate)

    def run(self, duration: float | None = None, realtime: bool = True) -> BridgeRun:
        """Up to ``duration`` [s] of the path (default: all of it, takeover included); returns the record.

        SIGINT and SIGTERM are caught while it runs (from the main thread): the run stops as on a fault, and its record
        says which signal ended it; the handlers of before are put back when it returns."""
        loop, ep, safety = self.loop, self.endpoint, self.safety
        n_axes = len(loop.drive_modes)
        rec = BridgeRun(loop.rate, robot_sequence=ep.robot_sequence)
        st = {
            "phase": "connect",
            "since": 0,
            "feedback": None,
            "age": 0,
            "sequence": 0,
            "run_start": None,
            "run_cycles": None,
            "misses": 0,
            "fresh": False,
            "word": None,
            "word_since": 0,
        }
        zeros = np.zeros(n_axes)
        sent = {}  # command sequence -> run cycle
        noted = []  # the signals received

        def send(k, controlword, target, t_wake):
            fb = st["feedback"]
            cmd = protocol.Command(
                st["sequence"],
                time.monotonic_ns(),
                fb.sequence if fb else 0,
                np.full(n_axes, controlword, np.uint16),
                loop.drive_modes,
                target,
            )
            ep.send_command(cmd)
            st["sequence"] += 1
            rec.commands.append((k, controlword, target, cmd.sequence, cmd.ack))
            return time.monotonic() - t_wake

        def states():
            fb = st["feedback"]
            return {cia402.state_of(int(w)) for w in fb.statusword} if fb is not None else set()

        def answered() -> bool:
            """The feedback shows the drives after the controlword being sent (or does not say which command it
            answers).  Bring-up decides its next controlword on such feedback only and sends the same one until then:
            a statusword from before the last controlword, read as the present state, sent 'switch on' to drives
            already in 'operation enabled' (CiA 402 transition 5, disable operation) and 'fault reset' (bit 1
            clear: disable voltage) to drives already reset and ready."""
            fb = st["feedback"]
            return fb is not None and (not fb.ack or fb.ack >= st["word_since"])

        def bring_up(k, word, t_wake):
            """Send controlword ``word`` of the connect or enable phase in cycle ``k``."""
            if word != st["word"]:
                st["word"], st["word_since"] = word, st["sequence"]
            send(k, word, zeros, t_wake)

        def stop(k, why: End):
            """The stop phase from cycle ``k``, for ``why``."""
            st["phase"], st["since"] = "stop", k
            rec.ended = rec.ended or why

        def failed(k, e: Exception):
            """An exception of the bridge's own code in cycle ``k``: a fault, and the stop."""
            safety.fault(k, FaultKind.INTERNAL_ERROR, f"{type(e).__name__}: {e}")
            stop(k, End.FAULT)

        def operate(k, skipped, t_wake):
            """Cycle ``k`` of the connect, enable and run phases: True when it sent its command, False when it went into
            the stop (whose first command it leaves to the stop phase)."""
            packet = ep.poll()
            arrived = list(ep.arrived)  # every packet of this cycle, oldest first: the record keeps each
            end = t_wake + self.lockstep_s
            while (
                self.lockstep_s
                and st["phase"] == "run"
                and (packet is None or packet.ack not in (0, st["sequence"] - 1))
                and time.monotonic() < end
            ):
                packet = ep.poll(timeout=min(1e-3, max(end - time.monotonic(), 1e-6))) or packet
                arrived += ep.arrived
            if packet is not None:
                st["feedback"], st["age"], st["fresh"] = packet, 0, True
            else:
                st["age"] += 1 + skipped
                st["fresh"] = False
            phase = st["phase"]
            fb = st["feedback"]
            settled = answered()
            if phase == "connect":
                if settled and states() in ({cia402.READY}, {cia402.SWITCHED_ON}):
                    st["phase"], st["since"] = "enable", k
                elif k - st["since"] > self.connect_cycles:
                    safety.fault(
                        k,
                        FaultKind.FEEDBACK_STALE,
                        f"the drives did not come up in {self.connect_cycles} cycles "
                        f"(states: {sorted(states()) or 'no feedback'})",
                    )
                    stop(k, End.FAULT)
                if not settled:
                    word = st["word"] or cia402.SHUTDOWN
                elif cia402.FAULT in states() and st["word"] != cia402.FAULT_RESET:  # a rising edge of bit 7
                    word = cia402.FAULT_RESET
                elif cia402.QUICK_STOP_ACTIVE in states():  # left in quick stop: only disable voltage leaves it
                    word = cia402.DISABLE_VOLTAGE
                else:
                    word = cia402.SHUTDOWN
                bring_up(k, word, t_wake)
                return True
            if phase == "enable":
                s = states()
                if s == {cia402.OPERATION_ENABLED} and st["fresh"] and settled:
                    k6 = loop.mode.force_axis
                    loop.start(
                        fb.position,
                        fb.torque,
                        float(fb.torque[k6] * loop.force_per_torque[k6]) if loop.mode.hybrid else None,
                    )
                    st["phase"], st["run_start"] = "run", k
                    rec.run_start = k
                    total = loop.cycles + self.hold_cycles
                    st["run_cycles"] = total if duration is None else min(total, int(round(duration * loop.rate)))
                elif k - st["since"] > self.connect_cycles:
                    safety.fault(k, FaultKind.DRIVE_FAULT, f"the drives did not enable (states: {sorted(s)})")
                    stop(k, End.FAULT)
                    return False
                else:
                    word = (
                        st["word"]
                        if not settled
                        else cia402.SWITCH_ON
                        if s == {cia402.READY}
                        else cia402.ENABLE_OPERATION
                    )
                    bring_up(k, word, t_wake)
                    return True
            j = k - st["run_start"]
            st["misses"] = st["misses"] + 1 if skipped else 0
            ok = not safety.tripped
            if ok and st["misses"] > self.max_misses:
                safety.fault(k, FaultKind.DEADLINE, f"{st['misses']} consecutive cycles missed their deadline")
                ok = False
            if ok and states() - {cia402.OPERATION_ENABLED}:
                safety.fault(k, FaultKind.DRIVE_FAULT, f"a drive left 'operation enabled' (states: {sorted(states())})")
                ok = False
            # the feedback shows the machine after the command it acknowledges (over CANopen, which has no
            # acknowledgement: the last one): compare it with the reference of the cycle after that
            ja = sent.get(fb.ack, -1) if fb.ack else j - 1
            ok = (
                ok
                and safety.check_feedback(k, st["age"], fb.position, fb.velocity, fb.torque)
                and safety.check_following(k, j / loop.rate, loop.reference_at(ja + 1), fb.position)
            )
            if not ok:
                stop(k, End.FAULT)
                return False
            target = safety.limit_command(k, loop.drive_modes, loop.step(j, fb.position, fb.velocity))
            rec.latency_us.append(send(k, cia402.ENABLE_OPERATION, target, t_wake) * 1e6)
            if st["fresh"] and fb.timestamp_ns:
                rec.feedback_age_us.append((ep.received_at - fb.timestamp_ns * 1e-9) * 1e6)
            if st["fresh"]:  # the record: each sample that came, and the cycle of the reference it answers
                t_record = time.perf_counter_ns()
                kept = len(rec.kept)
                for p in arrived:  # the newest (fb) acts; the older ones were periods the robot ran all the same
                    jp = sent.get(p.ack, -1) if p.ack else j - 1
                    if jp >= 0:
                        rec.kept.append((jp + 1, p))
                if len(rec.kept) > kept:
                    rec.record_us.append((time.perf_counter_ns() - t_record) * 1e-3)
            sent[st["sequence"] - 1] = j
            if j + 1 >= st["run_cycles"]:
                rec.completed = not safety.tripped
                stop(k + 1, End.COMPLETED if rec.completed else End.FAULT)
            return True

        def cycle(k, skipped):
            t_wake = time.monotonic()
            if noted and st["phase"] != "stop":
                stop(k, SIGNALS[noted[0]])
            if st["phase"] != "stop":
                try:
                    if operate(k, skipped, t_wake):
                        return True
                except Exception as e:  # the loops, a decoder: whatever it is, the machine is stopped
                    failed(k, e)
            # stop: quick stop, then disable voltage
            word = cia402.QUICK_STOP if k - st["since"] < self.stop_cycles else cia402.DISABLE_VOLTAGE
            send(k, word, zeros, t_wake)
            return k - st["since"] < self.stop_cycles + 5

        def prepare(k):
            if st["phase"] == "run":
                try:
                    loop.warm(k - st["run_start"])
                except Exception as e:  # as in the cycle's step
                    failed(k, e)

        run_s = duration if duration is not None else len(loop.reference.theta) * loop.rates.dt_position + 30.0
        with _signals_noted(noted):
            granted = realtime_setup() if realtime else None
            if granted:
                rec.realtime = granted.lines()
            try:
                stats = CycleRunner(loop.rate, "rephase" if self.lockstep_s else "skip").run(
                    cycle,
                    2 * self.connect_cycles + int(run_s * loop.rate) + self.hold_cycles + 2 * self.stop_cycles,
                    prepare=prepare,
                )
            finally:
                if granted:
                    granted.restore()
        rec.cycles, rec.missed, rec.skipped = stats.cycles, stats.missed, stats.skipped
        rec.settle(loop)
        rec.faults = list(safety.faults)
        rec.rejected = dict(ep.rejected)
        return rec


def run_log(rec: BridgeRun) -> list[Channel]:
    """The run's record as MCAP channels (:mod:`pusupu_jax.run_log`), timed from the bridge's first cycle:
    ``/bridge/command`` (every command sent: cycle, controlword, targets, its sequence number and the feedback's it
    answers, and in the run its latency and the time along the path of the reference it was computed from),
    ``/bridge/feedback`` (every sample of the run that came, each packet of a cycle's, not only the newest the loops
    act on: the reference the machine was following, the measured angles, speeds, torques and currents, the platform
    where the robot reports it, the robot's sequence number) and ``/bridge/fault`` (each fault with its
    cycle)."""
    period = 1.0 / rec.rate
    command = Channel(
        "/bridge/command",
        "pusupu.BridgeCommand",
        {
            "cycle": {"type": "integer", "description": "the bridge's cycle, from its first"},
            "controlword": {"type": "integer", "description": "CiA 402 controlword (0x6040) sent to every drive"},
            "target": {
                "type": "array",
                "items": {"type": "number"},
                "description": "per axis: speed target [rad/s] (CSV) or torque target [N m] (CST)",
            },
            "latency_us": {
                "type": ["number", "null"],
                "description": "from the cycle's wake-up to its command sent [us] "
                "(run phase; null before and after it)",
            },
            "sequence": {"type": "integer", "description": "the command's sequence number (u32, +1 a command)"},
            "feedback": {
                "type": "integer",
                "description": "the sequence number of the feedback packet the command was computed from (0: none)",
            },
            "path_time_s": {
                "type": ["number", "null"],
                "description": "the time along the path of the reference row the command was computed from [s] "
                "(negative on the takeover ramp; null outside the run phase). A cycle skipped sends no command, so "
                "the run's commands can step over a row",
            },
        },
    )
    latency = iter(rec.latency_us)
    for (k, word, target, number, answers), path_time in zip(rec.commands, rec.command_path_time, strict=True):
        # the run's commands are those with a reference row: from the run's start until its stop
        command.messages.append(
            (
                k * period,
                {
                    "cycle": k,
                    "controlword": int(word),
                    "target": target,
                    "latency_us": next(latency, None) if path_time is not None else None,
                    "sequence": int(number),
                    "feedback": int(answers),
                    "path_time_s": path_time,
                },
            )
        )
    feedback = Channel(
        "/bridge/feedback",
        "pusupu.BridgeFeedback",
        {
            "path_time_s": {
                "type": "number",
                "description": "the time along the path of the sample's reference [s] (negative on the takeover ramp)",
            },
            "reference_rad": {
                "type": "array",
                "items": {"type": "number"},
                "description": "per axis: the motor angle the machine was following [rad]",
            },
            "position_rad": {"type": "array", "items": {"type": "number"}, "description": "per axis: measured [rad]"},
            "velocity_rad_s": {
                "type": "array",
                "items": {"type": "number"},
                "description": "per axis: the motor speed the drive measured [rad/s]",
            },
            "torque_nm": {
                "type": "array",
                "items": {"type": "number"},
                "description": "per axis: the motor torque the drive reported [N m]",
            },
            "current_a": {
                "type": "array",
                "items": {"type": ["number", "null"]},
                "description": "per axis: the motor current the drive measured [A] (null: not reported, protocol "
                "version 1 or CANopen)",
            },
            "platform_m": {
                "type": "array",
                "items": {"type": ["number", "null"]},
                "description": "the platform's position where the robot reports it [m] (null: not reported)",
            },
            "platform_reference_m": {
                "type": "array",
                "items": {"type": "number"},
                "description": "the platform's reference position [m] (empty: none)",
            },
            "sequence": {
                "type": ["integer", "null"],
                "description": "the robot's sequence number of the packet (u32, +1 a packet: one a period it ran; "
                "null over CANopen, whose answers carry none)",
            },
            "ack": {
                "type": ["integer", "null"],
                "description": "the sequence number of the command the robot ran in the period (null over CANopen)",
            },
        },
    )
    offset = 0.0 if rec.run_start is None else rec.run_start * period
    for i, t in enumerate(rec.t):
        feedback.messages.append(
            (
                offset + t,
                {
                    "path_time_s": rec.path_time[i],
                    "reference_rad": rec.reference[i],
                    "position_rad": rec.position[i],
                    "velocity_rad_s": rec.drive[i][0],
                    "torque_nm": rec.drive[i][1],
                    "current_a": rec.drive[i][2],
                    "platform_m": rec.platform[i],
                    "platform_reference_m": rec.platform_reference[i] if i < len(rec.platform_reference) else [],
                    "sequence": None if rec.numbers[i] is None else int(rec.numbers[i][0]),
                    "ack": None if rec.numbers[i] is None else int(rec.numbers[i][1]),
                },
            )
        )
    fault = Channel(
        "/bridge/fault",
        "pusupu.BridgeFault",
        {
            "cycle": {"type": "integer", "description": "the cycle it came in"},
            "kind": {"type": "string", "enum": [str(k) for k in FaultKind]},
            "detail": {"type": "string"},
        },
    )
    for f in rec.faults:
        fault.messages.append((f.cycle * period, {"cycle": f.cycle, "kind": str(f.kind), "detail": f.detail}))
    return [command, feedback, fault]
