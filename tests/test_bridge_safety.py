"""The bridge and the simulated robot under fault injection: what each side refuses, how every way out of a run ends.

The bridge runs against :class:`WireRobot`, a robot on a real loopback socket that keeps every command reaching it: in
this process and in lock step (``Bridge(lockstep_s=...)``: the results do not depend on how loaded the machine is), or
as ``pusupu bridge`` processes for their signals and exit status.  The simulated robot's controller
(:class:`~pusupu_jax.sim_robot.robot.SimRobot`) is tested alone, and behind its own UDP server; the command lines'
checks run
their ``main`` in this process.  Every packet goes through the real protocol.
"""

import contextlib
import dataclasses
import json
import os
import signal
import socket
import subprocess
import sys
import threading
import time
from dataclasses import dataclass

import numpy as np
import pytest

from pusupu_jax.hw_bridge import cia402, protocol
from pusupu_jax.hw_bridge.loop import BridgeLoop, plan
from pusupu_jax.hw_bridge.safety import Limits, Safety
from pusupu_jax.hw_bridge.session import Bridge
from pusupu_jax.hw_bridge.udp import Endpoint
from pusupu_jax.hw_bridge.loop import bridge_reference
from pusupu_jax.hw_bridge.safety import limits_for
from pusupu_jax import gains
from pusupu_jax.hybrid import HybridGains
from pusupu_jax.params import LoopRates, ServoParams

SERVO = ServoParams.table1()
RATE = 500.0  # Hz, as the loopback runs of test_bridge.py
N = 6
WAIT = 10.0  # s: the longest any step of these tests waits for the other side on a loaded machine
TIMEOUT = 600  # s: for a subprocess, which compiles cold on a slow machine


@dataclass(frozen=True)
class Setup:
    path: object  # the gain file
    loop: BridgeLoop  # compiled once for the module
    limits: Limits


@pytest.fixture(scope="module")
def setup(tmp_path_factory):
    """Table 1's gains in IMC, all drives CSV, rates scaled to a 500 Hz position loop; the bridge's loops on the arc."""
    path = gains.write(tmp_path_factory.mktemp("safety") / "imc.yaml", SERVO, HybridGains(), LoopRates(), mode="imc")
    g = gains.load(path)
    loop = BridgeLoop(g, bridge_reference(g, "arc", plan(g, None, RATE)[1]), rate=RATE)
    return Setup(path, loop, limits_for(g.servo))


@contextlib.contextmanager
def _time_limit(seconds: int):
    """The block ends in TimeoutError after ``seconds`` (what runs in this process would hang if it regressed)."""

    def expire(signum, frame):
        raise TimeoutError(f"more than {seconds} s")

    before = signal.signal(signal.SIGALRM, expire)
    signal.alarm(seconds)
    try:
        yield
    finally:
        signal.alarm(0)
        signal.signal(signal.SIGALRM, before)


def _resized(fb: protocol.Feedback, n: int) -> protocol.Feedback:
    """``fb`` with ``n`` axes (the first ones, or the first ones repeated): a valid packet of another axis count."""
    return protocol.Feedback(
        fb.sequence,
        fb.timestamp_ns,
        fb.ack,
        *(np.resize(a, n) for a in (fb.statusword, fb.mode, fb.position, fb.velocity, fb.torque)),
        fb.platform,
    )


class WireRobot:
    """Six ideal CSV drives behind a loopback UDP socket, in a thread.

    Every command that arrives is decoded with the protocol and kept (``commands``); the drives' CiA 402 state
    machines take its controlwords, and while all six are enabled each position integrates its speed target over one
    period (``enabled`` counts those commands).  The reply is the drives' feedback, unless ``act(robot, feedback)``
    returns other datagrams to send, as ``(bytes, socket)`` pairs: the faults of the tests (``foreign`` is a second
    socket, on another port).
    """

    def __init__(self, act=None):
        self.sock, self.foreign = (socket.socket(socket.AF_INET, socket.SOCK_DGRAM) for _ in range(2))
        for s in (self.sock, self.foreign):
            s.bind(("127.0.0.1", 0))
        self.sock.settimeout(0.05)
        self.act = act or (lambda robot, fb: [(protocol.encode_feedback(fb), robot.sock)])
        self.drives = [cia402.DriveStateMachine() for _ in range(N)]
        self.theta = np.zeros(N)
        self.commands = []
        self.enabled = 0
        self.error = None
        self._done = threading.Event()
        self._thread = threading.Thread(target=self._serve, daemon=True)
        self._thread.start()

    @property
    def port(self) -> int:
        return self.sock.getsockname()[1]

    def _serve(self):
        sequence = 0
        try:
            while not self._done.is_set():
                try:
                    data, addr = self.sock.recvfrom(protocol.MAX_PACKET)
                except socket.timeout:
                    continue
                cmd = protocol.decode(data, protocol.COMMAND, N)
                self.commands.append(cmd)
                for d, word in zip(self.drives, cmd.controlword):
                    d.command(int(word))
                speed = np.zeros(N)
                if all(d.enabled for d in self.drives):
                    speed = cmd.target
                    self.theta = self.theta + speed / RATE
                    self.enabled += 1
                fb = protocol.Feedback(
                    sequence,
                    time.monotonic_ns(),
                    cmd.sequence,
                    np.array([d.statusword for d in self.drives], np.uint16),
                    cmd.mode,
                    self.theta.copy(),
                    speed,
                    np.zeros(N),
                    np.full(3, np.nan),
                )
                sequence += 1
                for datagram, s in self.act(self, fb):
                    s.sendto(datagram, addr)
        except Exception as e:  # raised again in the test by close()
            self.error = e

    def close(self, sent: int) -> None:
        """Wait until the ``sent`` commands of the run have arrived, stop, and raise what the thread raised."""
        end = time.monotonic() + WAIT
        while len(self.commands) < sent and time.monotonic() < end and self.error is None:
            time.sleep(1e-3)
        self._done.set()
        self._thread.join(WAIT)
        for s in (self.sock, self.foreign):
            s.close()
        if self.error is not None:
            raise self.error
        assert len(self.commands) == sent


def _from(enabled: int, fault):
    """An ``act`` that answers as the drives do until ``enabled`` commands ran enabled, then as ``fault`` does."""

    def act(robot, fb):
        return fault(robot, fb) if robot.enabled >= enabled else [(protocol.encode_feedback(fb), robot.sock)]

    return act


def _bridge_run(setup: Setup, robot: WireRobot, duration=0.6):
    """The bridge in lock step against ``robot`` for ``duration`` [s] of the arc: the run's record, once every command
    it sent has reached the robot."""
    ep = Endpoint(protocol.FEEDBACK, n_axes=N, peer=("127.0.0.1", robot.port))
    try:
        run = Bridge(setup.loop, ep, Safety(setup.limits, 5), connect_s=1.0, lockstep_s=0.05).run(
            duration, realtime=False
        )
    finally:
        ep.close()
    robot.close(len(run.commands))
    return run


def _ended_safe(robot: WireRobot, limits: Limits) -> None:
    """What reached the robot ends with the stop: quick stop, then disable voltage (each for as long as the bridge's
    stop gives it: a real-time run counts skipped cycles too); and no command it received was outside the limits
    (finite, within each axis's speed or torque limit)."""
    words = [set(c.controlword.tolist()) for c in robot.commands]
    assert all(len(w) == 1 for w in words)
    words = [w.pop() for w in words]
    first = words.index(cia402.QUICK_STOP)
    disable = words.index(cia402.DISABLE_VOLTAGE, first)
    assert set(words[first:disable]) == {cia402.QUICK_STOP} and set(words[disable:]) == {cia402.DISABLE_VOLTAGE}
    for c in robot.commands:
        bound = np.where(c.mode == protocol.CSV, limits.velocity, limits.torque)
        assert np.isfinite(c.target).all() and np.all(np.abs(c.target) <= bound), c


# ---------------------------------------------------------------- packets of another axis count


def test_packets_are_decoded_only_at_their_versions_length_and_the_sessions_axis_count():
    """A valid packet (CRC and all) whose axis count is not the session's is refused ("axes"), and so is one a byte
    longer or shorter than its version's layout gives for its kind and axis count ("length")."""
    import zlib

    fb = protocol.Feedback(
        3, 0, 2, np.full(N, 0x27, np.uint16), np.full(N, 9, np.int8), np.ones(N), np.ones(N), np.ones(N), np.zeros(3)
    )
    assert len(protocol.encode_feedback(fb)) == 26 + 28 * N + 24 + 4  # version 1: header, axes, platform, CRC
    assert protocol.decode(protocol.encode_feedback(fb), protocol.FEEDBACK, N).sequence == 3
    for n in (1, N - 1, N + 1, protocol.MAX_AXES):
        data = protocol.encode_feedback(_resized(fb, n))
        assert protocol.decode(data, protocol.FEEDBACK).position.shape == (n,)  # valid in itself
        with pytest.raises(protocol.ProtocolError) as e:
            protocol.decode(data, protocol.FEEDBACK, N)
        assert e.value.reason == "axes" and f"expected {N} axes (the session's), got {n}" in str(e.value)
    body = protocol.encode_feedback(fb)[:-4]
    for bad in (body + b"\0", body[:-1]):
        with pytest.raises(protocol.ProtocolError) as e:
            protocol.decode(bad + zlib.crc32(bad).to_bytes(4, "little"), protocol.FEEDBACK, N)
        assert e.value.reason == "length"


def test_feedback_of_version_2_carries_the_measured_currents_and_has_its_own_length():
    """Version 2's feedback appends the measured current to each axis (36 bytes an axis): it round-trips, version 1's
    decodes as before with no current, and each is refused at the other's length."""
    import zlib

    fb = protocol.Feedback(
        3, 0, 2, np.full(N, 0x27, np.uint16), np.full(N, 9, np.int8), np.ones(N), np.ones(N), np.ones(N), np.zeros(3)
    )
    two = dataclasses.replace(fb, current=np.linspace(-2.0, 3.0, N))
    data = protocol.encode_feedback(two)
    assert len(data) == 26 + 36 * N + 24 + 4 and data[4] == 2
    back = protocol.decode(data, protocol.FEEDBACK, N)
    np.testing.assert_array_equal(back.current, two.current)
    np.testing.assert_array_equal(back.torque, two.torque)
    assert protocol.decode(protocol.encode_feedback(fb), protocol.FEEDBACK, N).current is None
    for version, body in ((1, data[:-4]), (2, protocol.encode_feedback(fb)[:-4])):
        relabelled = body[:4] + bytes([version]) + body[5:]
        with pytest.raises(protocol.ProtocolError) as e:
            protocol.decode(relabelled + zlib.crc32(relabelled).to_bytes(4, "little"), protocol.FEEDBACK, N)
        assert e.value.reason == "length"


@pytest.mark.parametrize("n", [1, N + 1])
def test_feedback_of_another_axis_count_is_refused_and_the_run_stops_safely(setup, n):
    """A robot whose replies turn into valid packets of 1 or 7 axes (short and long feedback) mid-run: each is refused
    and counted ("axes"), the feedback goes stale, and the bridge stops the machine: quick stop, then disable voltage,
    on the wire; no command outside the limits."""
    robot = WireRobot(_from(50, lambda robot, fb: [(protocol.encode_feedback(_resized(fb, n)), robot.sock)]))
    run = _bridge_run(setup, robot)
    rep = run.report()
    assert [f.kind for f in run.faults] == ["feedback stale"], rep.faults
    assert rep.rejected_packets["axes"] >= 5 and not rep.completed
    _ended_safe(robot, setup.limits)


@pytest.fixture(scope="module")
def robot_model(setup):
    """The simulated robot's machine and drives (C MuJoCo and the compiled drive step) for the gain file, at RATE."""
    from pusupu_jax.sim_robot.robot import RobotModel

    return RobotModel(gains.load(setup.path), RATE)


def test_the_simulated_robots_encoders_read_whole_counts_and_its_drives_count_their_speed(setup, robot_model):
    """A machine with coarse encoders (4096 counts a revolution): under a speed command every angle the robot reports
    is a whole number of counts from its encoder's phase (drawn per axis from the seed, within one count), and every
    speed its drives use and report is the counts seen over one velocity period (0.25 ms) times the count; the
    built-in machine's ideal encoders report angles that are not.  Both follow the command to 10 % after 0.16 s.
    Another seed mounts the encoders at other phases."""
    import mujoco

    from pusupu_jax.machine_file import Machine
    from pusupu_jax.sim_robot.robot import RobotModel

    machine = dataclasses.replace(Machine.default(), encoder_counts=np.full(N, 4096))
    coarse = RobotModel(gains.load(setup.path), RATE, machine=machine)
    count = 2 * np.pi / 4096
    target = np.full(N, 20.0)  # rad/s at the motors, every slider alike: the platform rises, 32 mm/s
    for model, quantised in ((coarse, True), (robot_model, False)):
        d = mujoco.MjData(model.m)
        state = model.reset(d)
        steps = []
        for _ in range(100):  # 0.2 s
            state, _ = model.advance(d, state, target, np.zeros(N, bool))
            theta, omega, _ = model.actual(d)
            steps.append((theta / count, omega * model.rates.dt_velocity / count))
        counts = np.array(steps)
        counts[:, 0] += model.phase
        whole = np.allclose(counts, np.round(counts), rtol=0, atol=1e-6)
        assert whole == quantised
        speed = counts[-20:, 1].mean(axis=0) * count / model.rates.dt_velocity  # rad/s, over the last 40 ms
        assert np.all(np.abs(speed - target) < 0.1 * target), speed  # observed 18.2 (ideal) and 18.6 (4096 counts)
    other = RobotModel(gains.load(setup.path), RATE, machine=machine, noise_seed=1).phase
    assert np.all((0 <= coarse.phase) & (coarse.phase < 1)) and np.all(np.abs(other - coarse.phase) > 1e-6)


def test_the_simulated_robots_finer_steps_converge_and_the_models_step_is_near_them(setup, robot_model):
    """``fine_steps``: the machine stepped 1, 2, 4 and 16 times per current-loop tick (each tick on the latest
    speed) under the same speed commands (six speeds, reversed after 0.1 s).  Against 16, the motors' currents and
    angles over 0.2 s differ less with every halving of the step, by about half (semi-implicit Euler is of first
    order: asserted 1.8x).  The model's own stepping (one step a velocity period, what the tuner and identify step)
    stays within 3 % of the currents' peak of it (measured 2.4 %, in the transients of the sudden reversal, at this
    module's rates: a 0.5 ms velocity period)."""
    import mujoco

    from pusupu_jax.sim_robot.robot import RobotModel

    target = np.array([20.0, -20.0, 40.0, 0.0, 10.0, -30.0])  # rad/s

    def run(model):
        d = mujoco.MjData(model.m)
        state, out = model.reset(d), []
        for k in range(100):  # 0.2 s
            state, current = model.advance(d, state, target if k < 50 else -target, np.zeros(N, bool))
            out.append(np.concatenate([current, model.actual(d)[0]]))
        return np.array(out)

    g = gains.load(setup.path)
    fine = {n: run(RobotModel(g, RATE, fine_steps=n)) for n in (1, 2, 4, 16)}
    errors = [np.abs(fine[n] - fine[16]).max(axis=0) for n in (1, 2, 4)]  # currents [A], then angles [rad]
    assert np.all(errors[0] > 1.8 * errors[1]) and np.all(errors[1] > 1.8 * errors[2]), errors
    model_step = np.abs(run(robot_model) - fine[16]).max(axis=0)
    assert model_step[:N].max() < 0.03 * np.abs(fine[16][:, :N]).max()
    with pytest.raises(ValueError, match=r"fine_steps: expected a whole number of steps of at least 1, got 0"):
        RobotModel(g, RATE, fine_steps=0)


def test_the_simulated_robots_current_sensors_carry_the_machines_noise(setup, robot_model):
    """A machine with ``current_noise`` (0.1 A, 0.3 A on axis 6): the currents the robot reports scatter about the
    motors' armature currents with that standard deviation (within 5 % over 4000 draws: the sample deviation's own
    spread is 1.1 %), drawn from the seed it is given, and the torques it reports are ``Kt`` times them; the built-in
    machine reports the armature currents exactly."""
    from pusupu_jax.machine_file import Machine
    from pusupu_jax.sim_robot.robot import RobotModel

    sigma = np.array([0.1] * 5 + [0.3])
    machine = dataclasses.replace(Machine.default(), current_noise=sigma)
    model = RobotModel(gains.load(setup.path), RATE, machine=machine, noise_seed=7)
    armature = np.linspace(-2.0, 3.0, N)  # A
    reported, current = (np.array(x) for x in zip(*[model.sensed(armature) for _ in range(4000)]))
    noise = current - armature
    np.testing.assert_allclose(noise.std(axis=0), sigma, rtol=0.05)
    np.testing.assert_allclose(noise, sigma * np.random.default_rng(7).standard_normal((4000, N)), rtol=1e-9)
    np.testing.assert_allclose(reported, model.Kt * current, rtol=1e-14)
    exact_torque, exact_current = robot_model.sensed(armature)
    assert np.array_equal(exact_current, armature) and np.array_equal(exact_torque, robot_model.Kt * armature)


def _command(sequence, word, target=np.zeros(N), mode=protocol.CSV):
    return protocol.Command(
        sequence,
        0,
        0,
        np.full(N, word, np.uint16),
        np.broadcast_to(np.asarray(mode, np.int8), N),
        np.asarray(target, float),
    )


def test_the_simulated_robot_refuses_a_command_of_another_axis_count_and_serves_on(robot_model):
    """The simulated robot behind its UDP server, enabled: a valid one-axis command (CRC and all) is refused and counted
    ("axes"), and the next six-axis command is answered as any other."""
    from pusupu_jax.sim_robot.robot import SimRobot, UdpServer

    ep = Endpoint(protocol.COMMAND, n_axes=N)
    server = UdpServer(SimRobot(robot_model, watchdog_s=WAIT, log=lambda line: None), ep)
    serving = threading.Thread(target=server.serve, args=(2.0,), daemon=True)
    serving.start()
    bridge = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    bridge.settimeout(WAIT)
    try:
        replies = []
        words = (cia402.SHUTDOWN, cia402.SWITCH_ON, cia402.ENABLE_OPERATION, cia402.ENABLE_OPERATION)
        for seq, word in enumerate(words):
            if seq == 3:
                one = protocol.Command(
                    seq + 100, 0, 0, np.array([word], np.uint16), np.array([protocol.CSV], np.int8), np.array([1.0])
                )
                bridge.sendto(protocol.encode_command(one), ep.address)
            bridge.sendto(protocol.encode_command(_command(seq + 200, word, np.full(N, 1.0))), ep.address)
            replies.append(protocol.decode(bridge.recvfrom(protocol.MAX_PACKET)[0], protocol.FEEDBACK, N))
        serving.join(WAIT)
    finally:
        bridge.close()
        ep.close()
    assert [r.ack for r in replies] == [200, 201, 202, 203]
    assert {cia402.state_of(int(w)) for w in replies[-1].statusword} == {cia402.OPERATION_ENABLED}
    assert ep.rejected == {"axes": 1}


# ---------------------------------------------------------------- feedback from the robot alone


def test_the_endpoint_takes_feedback_from_the_robots_address_and_port_alone():
    """The peer named by host name is resolved to the address senders are seen from; the same valid packet from
    another port of the same host is refused and counted ("sender"), before it is decoded."""
    robot, other = (socket.socket(socket.AF_INET, socket.SOCK_DGRAM) for _ in range(2))
    for s in (robot, other):
        s.bind(("127.0.0.1", 0))
    ep = Endpoint(protocol.FEEDBACK, n_axes=N, peer=("localhost", robot.getsockname()[1]))
    fb = protocol.Feedback(1, 0, 0, np.zeros(N, np.uint16), np.zeros(N, np.int8), *np.zeros((3, N)), np.zeros(3))
    try:
        other.sendto(protocol.encode_feedback(fb), ep.address)
        other.sendto(b"not a packet", ep.address)
        robot.sendto(protocol.encode_feedback(fb), ep.address)
        got = ep.poll(timeout=WAIT)
        assert got is not None and got.sequence == 1
        assert ep.rejected == {"sender": 2} and ep.accepted == 1
    finally:
        for s in (robot, other):
            s.close()
        ep.close()


def test_feedback_from_another_port_is_refused_and_the_run_stops_safely(setup):
    """An impostor: from mid-run the robot's replies come from another port (valid packets answering the commands): each
    is refused and counted ("sender"), the feedback goes stale, and the bridge stops the machine: quick stop, then
    disable voltage, on the wire; no command outside the limits."""
    robot = WireRobot(_from(50, lambda robot, fb: [(protocol.encode_feedback(fb), robot.foreign)]))
    run = _bridge_run(setup, robot)
    rep = run.report()
    assert [f.kind for f in run.faults] == ["feedback stale"], rep.faults
    assert (
        rep.rejected_packets == {"sender": rep.rejected_packets["sender"]}
        and rep.rejected_packets["sender"] >= 5
        and not rep.completed
    )
    _ended_safe(robot, setup.limits)


# ---------------------------------------------------------------- the simulated drives check their targets


def test_a_simulated_drive_faults_on_a_target_beyond_its_limits_or_a_mode_it_does_not_have(robot_model, setup):
    """As a CiA 402 drive does: enabled, a drive given a NaN, inf, 1e308 or beyond-the-limit target (CSV: V_max/Ke, CST:
    Kt I_max) or a mode of operation other than CSV and CST faults (statusword), reports no torque, and the brakes hold
    the machine; the other drives stay enabled, and a target at the limit (what the bridge clamps to) is taken."""
    from pusupu_jax.sim_robot.robot import SimRobot

    vmax, tmax = setup.limits.velocity[1], setup.limits.torque[1]
    cases = {
        "nan": (np.nan, protocol.CSV),
        "inf": (-np.inf, protocol.CSV),
        "1e308": (1e308, protocol.CSV),
        "speed": (1.01 * vmax, protocol.CSV),
        "torque": (-1.01 * tmax, protocol.CST),
        "mode 8 (CSP)": (0.0, 8),
        "mode -1": (0.0, -1),
    }
    for name, (bad, mode_2) in cases.items():
        log = []
        robot = SimRobot(robot_model, watchdog_s=WAIT, log=log.append)
        for seq, word in enumerate((cia402.SHUTDOWN, cia402.SWITCH_ON, cia402.ENABLE_OPERATION)):
            robot.handle(_command(seq, word), time.monotonic())
        cst = protocol.CST if mode_2 == protocol.CST else protocol.CSV
        modes = np.where(np.arange(N) == 1, cst, protocol.CSV)
        moved = robot.handle(
            _command(3, cia402.ENABLE_OPERATION, np.where(modes == protocol.CST, tmax, vmax), modes), time.monotonic()
        )
        assert {cia402.state_of(int(w)) for w in moved.statusword} == {cia402.OPERATION_ENABLED}, name
        target = np.where(np.arange(N) == 1, bad, 0.0)
        modes[1] = mode_2
        faulted = robot.handle(_command(4, cia402.ENABLE_OPERATION, target, modes), time.monotonic())
        held = robot.handle(_command(5, cia402.ENABLE_OPERATION, np.full(N, 0.5 * vmax)), time.monotonic())
        states = [cia402.state_of(int(w)) for w in held.statusword]
        assert states == [cia402.OPERATION_ENABLED] + [cia402.FAULT] + [cia402.OPERATION_ENABLED] * 4, name
        assert faulted.torque[1] == held.torque[1] == 0.0 and np.abs(moved.torque[1]) > 0, name
        np.testing.assert_array_equal(held.position, faulted.position)  # the brakes hold
        assert len(log) == 1 and log[0].startswith("sim-robot: session 0: drive 2 faulted:"), (name, log)


# ---------------------------------------------------------------- every way out of a run ends in the stop


@pytest.mark.parametrize("where", ["step", "decoder"])
def test_an_exception_inside_a_cycle_ends_in_the_stop_and_the_report(setup, monkeypatch, where):
    """An exception raised by the bridge's own code in a cycle (injected into the loops' step, or into the decoder of
    the robot's feedback) is a fault ("internal error", with the exception): quick stop, then disable voltage, on
    the wire, and the run's record and report; no command outside the limits."""
    if where == "step":
        real_step = BridgeLoop.step

        def step(loop, cycle, theta, omega):
            if cycle == 50:
                raise FloatingPointError("injected into the step")
            return real_step(loop, cycle, theta, omega)

        monkeypatch.setattr(BridgeLoop, "step", step)
    else:
        real_decode, decoded = protocol.decode, []

        def decode(data, kind=None, n_axes=None):
            if kind == protocol.FEEDBACK:
                decoded.append(data)
                if len(decoded) == 60:
                    raise IndexError("injected into the decoder")
            return real_decode(data, kind, n_axes)

        monkeypatch.setattr(protocol, "decode", decode)
    robot = WireRobot()
    run = _bridge_run(setup, robot)
    rep = run.report()
    error = "FloatingPointError: injected into the step" if where == "step" else "IndexError: injected into the decoder"
    assert [(f.kind, f.detail) for f in run.faults] == [("internal error", error)], rep.faults
    assert rep.ended == "fault" and not rep.completed and rep.cycles == len(robot.commands)
    _ended_safe(robot, setup.limits)


def _lagging(lag: int, states: list):
    """An ``act`` whose replies come ``lag`` commands late until the drives first run enabled (as on a loaded host
    whose feedback queues up), then at once; ``states`` gets the drives' states after each command."""
    held = []

    def act(robot, fb):
        states.append({d.state for d in robot.drives})
        held.append(protocol.encode_feedback(fb))
        if robot.enabled:
            held.clear()
            return [(protocol.encode_feedback(fb), robot.sock)]
        return [(held.pop(0), robot.sock)] if len(held) > lag else []

    return act


@pytest.mark.parametrize("lag", [1, 4])
def test_bring_up_on_late_feedback_walks_the_state_machine_once(setup, lag):
    """Drives in fault, whose feedback comes ``lag`` commands late during bring-up: the bridge decides each
    controlword on feedback that answers the one before, so the drives walk fault, switch on disabled, ready,
    switched on, operation enabled once each and in that order (a statusword from before the last controlword taken
    for the present state sends 'fault reset' to ready drives and 'switch on' to enabled ones), and the run
    completes, ending in quick stop and disable voltage."""
    states = []
    robot = WireRobot(_lagging(lag, states))
    for d in robot.drives:
        d.fault()
    run = _bridge_run(setup, robot, duration=0.2)
    assert run.completed and not run.faults, run.report().faults
    assert all(len(s) == 1 for s in states)
    walk = [s.pop() for s in states]
    walk = [w for k, w in enumerate(walk) if not k or w != walk[k - 1]]
    assert walk == [
        cia402.FAULT,
        cia402.SWITCH_ON_DISABLED,
        cia402.READY,
        cia402.SWITCHED_ON,
        cia402.OPERATION_ENABLED,
        cia402.QUICK_STOP_ACTIVE,
        cia402.SWITCH_ON_DISABLED,
    ], walk
    _ended_safe(robot, setup.limits)


def _signal_at(enabled: int, sig):
    """An ``act`` that answers as the drives do and sends this process ``sig`` at the ``enabled``-th enabled command, if
    a handler other than the one of before the run is set (so a run that ended early fails its test, and SIGTERM never
    ends the test process)."""
    usual = signal.getsignal(sig)

    def act(robot, fb):
        if robot.enabled == enabled and signal.getsignal(sig) is not usual:
            os.kill(os.getpid(), sig)
        return [(protocol.encode_feedback(fb), robot.sock)]

    return act


def test_a_runs_log_reads_back_as_its_record(setup, tmp_path):
    """A lock-step run that a fault stops (the robot's feedback goes NaN after 40 enabled commands), written to MCAP
    and read back with the mcap package's reader: every command with its cycle and controlword, a latency for each
    command of the run and none outside it, every fresh sample with the measured speeds, torques and currents (the
    robot answers in protocol version 2 from its 20th enabled command), the run's timing (the commands' and samples'
    numbers, the feedback each command answered, the rows of the references), the fault, each channel with its JSON
    Schema, log times in order, and the metadata."""
    from pusupu_jax import run_log
    from pusupu_jax.hw_bridge.session import run_log as bridge_channels

    def with_current(robot, fb):
        fb = dataclasses.replace(fb, torque=0.1 * fb.velocity, current=0.2 * fb.velocity)
        return [(protocol.encode_feedback(fb), robot.sock)]

    def nan_feedback(robot, fb):
        return with_current(robot, dataclasses.replace(fb, position=fb.position * np.nan))

    robot = WireRobot(_from(20, lambda robot, fb: (nan_feedback if robot.enabled >= 40 else with_current)(robot, fb)))
    run = _bridge_run(setup, robot)
    assert [f.kind for f in run.faults] == ["feedback invalid"]
    path = run_log.write(tmp_path / "run.mcap", bridge_channels(run), {"mode": "imc", "rate_hz": RATE}, 10**18)
    topics, metadata = run_log.read(path)
    assert metadata == {"mode": "imc", "rate_hz": json.dumps(RATE)}
    commands, feedback, faults = (topics[t][1] for t in ("/bridge/command", "/bridge/feedback", "/bridge/fault"))
    assert [(m["cycle"], m["controlword"]) for _, m in commands] == [(k, w) for k, w, *_ in run.commands]
    assert [m["latency_us"] for _, m in commands if m["latency_us"] is not None] == pytest.approx(run.latency_us)
    assert len(feedback) == len(run.t) and [m["cycle"] for _, m in faults] == [run.faults[0].cycle]
    assert faults[0][1]["kind"] == "feedback invalid"
    samples = [m for _, m in feedback]
    two = [m for m in samples if m["current_a"][0] is not None]
    assert two and all(all(c is None for c in m["current_a"]) for m in samples[: len(samples) - len(two)])
    for m in two:
        assert m["current_a"] == pytest.approx([0.2 * v for v in m["velocity_rad_s"]], abs=1e-15)
        assert m["torque_nm"] == pytest.approx([0.1 * v for v in m["velocity_rad_s"]], abs=1e-15)
    assert any(v != 0 for m in two for v in m["velocity_rad_s"])
    # the run's timing: each command numbered, with the feedback it answered and its reference's row; each sample its
    # robot's packet number and the command it answers; in lock step, every command's answer the next one's feedback
    assert [m["sequence"] for _, m in commands] == list(range(len(commands)))
    ran = [m for _, m in commands if m["path_time_s"] is not None]
    assert len(ran) == len(run.latency_us) and np.allclose(np.diff([m["path_time_s"] for m in ran]), 1 / RATE)
    numbers = {m["sequence"]: m["ack"] for m in samples}
    assert len(numbers) == len(samples) and list(numbers) == sorted(numbers)
    assert set(numbers.values()) <= {m["sequence"] for m in ran}
    assert all(numbers[m["feedback"]] == m["sequence"] - 1 for m in ran[1:] if m["feedback"] in numbers)
    for topic, (schema, messages) in topics.items():
        assert set(schema["required"]) <= set(messages[0][1]), topic
        times = [t for t, _ in messages]
        assert times == sorted(times) and times[0] >= 10**18, topic


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM], ids=lambda s: s.name)
def test_a_signal_mid_run_ends_in_the_stop_and_the_run_puts_the_handlers_back(setup, sig):
    """SIGINT or SIGTERM at the robot's tenth enabled command: the run stops at the next cycle, quick stop then disable
    voltage on the wire, its record says the signal ended it (no fault), and the signal handlers of before are back."""
    before = {s: signal.getsignal(s) for s in (signal.SIGINT, signal.SIGTERM)}
    robot = WireRobot(_signal_at(10, sig))
    run = _bridge_run(setup, robot)
    rep = run.report()
    assert rep.ended == sig.name and not rep.faults and not rep.completed, rep
    assert {s: signal.getsignal(s) for s in before} == before
    assert 10 <= robot.enabled <= 11  # the next cycle stopped
    _ended_safe(robot, setup.limits)


@pytest.mark.slow
def test_pusupu_bridge_on_sigint_or_sigterm_prints_its_report_and_exits_130_or_143(setup):
    """``pusupu bridge`` processes against wire robots, one sent SIGINT and one SIGTERM once their robot saw ten enabled
    commands: each ends with quick stop then disable voltage on the wire, prints the report a completed run prints
    (here JSON) with the signal as the reason it ended and a line on stderr, and exits 130 or 143.  (At 100 Hz, a
    real-time run whose deadlines survive a loaded machine.)  The first binds to 0.0.0.0 (it sends to 127.0.0.1
    alone) and says so on stderr, in one line."""
    runs = {}
    try:
        for sig in (signal.SIGINT, signal.SIGTERM):
            robot = WireRobot()
            bind = ["--bind", "0.0.0.0"] if sig == signal.SIGINT else []
            proc = subprocess.Popen(
                [
                    sys.executable,
                    "-m",
                    "pusupu_jax.cli",
                    "bridge",
                    "--gains",
                    str(setup.path),
                    "--robot",
                    f"udp://127.0.0.1:{robot.port}",
                    "--rate",
                    "100",
                    "--duration",
                    "600",  # s: both run until their signal, the first while the second starts
                    "--watchdog",
                    "50",
                    "--no-realtime",
                    "--json",
                    *bind,
                ],
                stdout=subprocess.PIPE,
                stderr=subprocess.PIPE,
                text=True,
            )
            runs[sig] = (robot, proc)
            # the second starts once the first runs: it loads the programs the first compiled (persistent cache)
            end = time.monotonic() + TIMEOUT
            while robot.enabled < 10 and proc.poll() is None and time.monotonic() < end:
                time.sleep(1e-3)
        for sig, (robot, proc) in runs.items():
            proc.send_signal(sig)
        for sig, (robot, proc) in runs.items():
            out, err = proc.communicate(timeout=TIMEOUT)
            assert proc.returncode == 128 + sig, (sig, proc.returncode, err)
            rep = json.loads(out)
            robot.close(rep["cycles"])
            assert rep["ended"] == sig.name and not rep["completed"] and not rep["faults"], rep
            assert f"pusupu: {sig.name}: the run stopped (quick stop, then disable voltage)" in err.splitlines()
            warnings = [line for line in err.splitlines() if line.startswith("pusupu: warning:")]
            assert warnings == (
                [
                    "pusupu: warning: --bind 0.0.0.0: the bridge takes packets on every interface "
                    "(0.0.0.0), not on loopback alone"
                ]
                if sig == signal.SIGINT
                else []
            ), err
            _ended_safe(robot, setup.limits)
    finally:
        for robot, proc in runs.values():
            proc.kill()
            proc.wait()


# ---------------------------------------------------------------- the following error (CiA 402 0x6065, 0x6066)


def test_the_following_error_trips_once_an_error_stays_beyond_its_window_past_its_time_out(setup):
    """Cycle by cycle at 1 kHz: an error beyond the window (converted from slider travel with the screw ratio) for up to
    the time-out passes, one cycle more does not; an error back inside the window restarts the count."""
    lim = setup.limits
    safety = Safety(lim)
    beyond = np.zeros(N)
    beyond[2] = 1.01 * lim.following_error[2] / lim.screw[2]  # rad of motor angle
    inside = 0.99 * beyond
    steps = int(round(lim.following_error_time[2] * 1e3))  # 50 cycles of 1 ms
    for k in range(steps + 1):
        assert safety.check_following(k, k * 1e-3, beyond, np.zeros(N)), k
    assert safety.check_following(steps + 1, (steps + 1) * 1e-3, inside, np.zeros(N))  # back inside: no count
    for k in range(steps + 2, 2 * steps + 3):
        assert safety.check_following(k, k * 1e-3, np.zeros(N), -beyond), k
    assert not safety.check_following(2 * steps + 3, (2 * steps + 3) * 1e-3, np.zeros(N), -beyond)
    assert [f.kind for f in safety.faults] == ["following error"]
    assert (
        safety.faults[0].detail == "axis 3 5.05 mm of slider travel from its reference, beyond its 5 mm window "
        "for 51 ms (time-out 50 ms)"
    )


def _axis_1_stuck(offset: float):
    """The fault of an ``act``: axis 1 holds still ``offset`` [rad] from where it was, whatever its target."""
    held = []

    def fault(robot, fb):
        if not held:
            held.append(robot.theta[0] + offset)
        robot.theta[0] = fb.position[0] = held[0]
        return [(protocol.encode_feedback(fb), robot.sock)]

    return fault


def test_an_axis_that_stops_following_its_path_trips_the_following_error_and_a_clean_run_does_not(setup):
    """From the robot's 50th enabled command axis 1 holds still 10 mm of slider travel off (twice the window): the
    following error trips once its 50 ms time-out has passed (the 26th cycle at 500 Hz after the bridge reads the
    first such reply), and the bridge stops the machine; the same robot without the fault completes its run with no
    fault (its axes follow their path).  Quick stop, then disable voltage, on the wire, both times."""
    lim = setup.limits
    robot = WireRobot(_from(50, _axis_1_stuck(2 * lim.following_error[0] / lim.screw[0])))
    run = _bridge_run(setup, robot)
    assert [f.kind for f in run.faults] == ["following error"] and run.faults[0].detail.startswith("axis 1 "), (
        run.report().faults
    )
    enabled = next(k for k, word, *_ in run.commands if word == cia402.ENABLE_OPERATION)
    stuck = enabled + 50  # the robot's 50th enabled command: the bridge's of cycle enabled + 49, answered in lock step
    assert stuck + 26 <= run.faults[0].cycle <= stuck + 26 + 3, (run.faults[0].line(), enabled)  # late replies: later
    assert run.report().ended == "fault"
    _ended_safe(robot, lim)
    clean = WireRobot()
    run = _bridge_run(setup, clean)
    rep = run.report(screw=setup.loop.drive.screw)
    assert rep.completed and rep.ended == "completed" and not rep.faults, rep.faults
    assert max(rep.branch_max_error_mm) < 0.1 * 1e3 * min(lim.following_error)
    _ended_safe(clean, lim)


# ---------------------------------------------------------------- an address beyond loopback is said


def test_the_simulated_robot_says_so_when_it_listens_beyond_loopback(setup, monkeypatch, capsys):
    """``pusupu sim-robot --listen udp://0.0.0.0:PORT`` (its ``main``, in this process): one line on stderr as soon as
    the address is read, naming it, before anything else (here a bad option ends the command there, nothing bound)."""
    from pusupu_jax.cli.cli import main

    monkeypatch.setenv("PUSUPU_XLA_WORKAROUND", "0")  # this process's XLA flags are set already
    with pytest.raises(SystemExit) as e:
        main(["sim-robot", "--gains", str(setup.path), "--listen", "udp://0.0.0.0:5600", "--drive-watchdog", "0"])
    err = capsys.readouterr().err.splitlines()
    assert (
        e.value.code == 2
        and err[0]
        == "pusupu: warning: --listen udp://0.0.0.0:5600: the simulated robot takes "
        "commands on every interface (0.0.0.0), not on loopback alone"
        and err[1].startswith("pusupu: error:")
    ), err
    with pytest.raises(SystemExit):
        main(["sim-robot", "--gains", str(setup.path), "--listen", "udp://localhost:5600", "--drive-watchdog", "0"])
    assert not capsys.readouterr().err.startswith("pusupu: warning:")


# ---------------------------------------------------------------- bounds on the work a command line asks for

BEYOND = [
    (["bridge", "--rate", "0.001"], "rate: expected a number of Hz in [1, 4000], got 0.001"),
    (["bridge", "--rate", "2e4"], "rate: expected a number of Hz in [1, 4000], got 20000.0"),
    (["bridge", "--duration", "1e9"], "--duration: expected at most "),
    (["bridge", "--lockstep", "nan"], "--lockstep: expected seconds in [0, 10], got nan"),
    (["bridge", "--robot", "udp://127.0.0.1:0"], "--robot: expected udp://HOST:PORT with a port from 1 to 65535"),
    (["bridge", "--robot", "udp://[::1]:5600"], "--robot: expected a host with an IPv4 address, got '::1'"),
    (["bridge", "--log", "/proc/run.mcap"], "--log: cannot write in '/proc'"),  # found by making a file
    (["sim-robot", "--kin-error", "-1"], "--kin-error: expected a non-negative integer seed, got -1"),
    (["sim-robot", "--seconds", "nan"], "--seconds: expected a positive number of seconds, got nan"),
    (["sim-robot", "--fine-steps", "0"], "--fine-steps: expected a whole number of steps from 1 to 64, got 0"),
    (["sim-robot", "--rate", "0.001"], "rate: expected a number of Hz in [1, 4000], got 0.001"),
    (
        ["sim-robot", "--fault", "reorder@0.3:1e18"],
        "--fault reorder@0.3:1e18: expected ARG a whole number of replies in [1, 1000], got 1e18",
    ),
    (["sim-robot", "--fault", "drop@0.3:2"], "--fault drop@0.3:2: expected ARG a probability in [0, 1], got 2"),
]


@pytest.mark.parametrize("argv,expected", BEYOND, ids=[" ".join(argv) for argv, _ in BEYOND])
def test_numbers_beyond_their_bounds_are_refused_in_one_line(setup, monkeypatch, capsys, argv, expected):
    """``pusupu bridge`` and ``pusupu sim-robot`` (their ``main``, in this process, with a time limit): a rate below
    1 Hz or above 4 kHz, a run whose record would not fit in half of the memory (``--duration 1e9`` asked for
    terabytes), a negative seed, a non-finite time, an unbounded or impossible fault argument: one line on stderr
    naming what was expected and what was found, exit 2, nothing sent or bound."""
    from pusupu_jax.cli.cli import main

    monkeypatch.setenv("PUSUPU_XLA_WORKAROUND", "0")  # this process's XLA flags are set already
    command, *options = argv
    where = ["--robot", "udp://127.0.0.1:9"] if command == "bridge" else []
    with _time_limit(120), pytest.raises(SystemExit) as e:
        main([command, "--gains", str(setup.path), *where, "--no-realtime", *options])
    err = capsys.readouterr().err
    assert e.value.code == 2 and err.count("\n") == 1 and err.startswith("pusupu: error: ") and expected in err, err
    if command == "bridge" and "--duration" in options:  # the limit, for the rate of the gain file: 1 kHz
        from pusupu_jax.hw_bridge.session import longest_run

        assert f"expected at most {longest_run(1000.0):.6g} s at 1000 Hz" in err and "got 1e+09" in err, err
