"""CANopen CiA 402 between the bridge and six drives: the ``canopen`` package over ``python-can``.

Both sides use :func:`drive_dictionary`, the object dictionary of one drive (CiA 402 objects and
the predefined PDO mapping below).  Node IDs 1-6 are axes 1-6.

* set-up over SDO: the bridge writes each drive's mode of operation (0x6060: 9 CSV, 10 CST),
  reads it back (0x6061), and reads the motor's rated torque (0x6076, mN m) that scales torques and
  its rated current (0x6075, mA) that scales currents;
* each cycle the bridge sends one RPDO per drive (controlword 0x6040, target velocity 0x60FF,
  target torque 0x6071), then SYNC with a counter (CiA 301: 1 to :data:`SYNC_OVERFLOW`); on SYNC
  each drive applies its RPDO, runs one period, and answers with two TPDOs: (statusword 0x6041,
  position actual 0x6064, torque actual 0x6077) and (velocity actual 0x606C, current actual 0x6078,
  mode display 0x6061, the counter of the SYNC answered, :data:`SYNC_ECHO`): 8 bytes each.

The measured current is what a drive's torque constant is identified from (``pusupu identify``), as in the UDP
protocol's version 2; a drive whose rated current reads 0 reports none (the bridge logs null).

The echoed counter tells the bridge which command an answer belongs to, as the UDP protocol's ack
does: without it an answer that comes after the next SYNC would be taken for that SYNC's, and on a
loaded host the feedback then lagged a cycle for stretches of a run.  A drive that does not map
the echo answers 0, read as "unknown" (the answer is then taken for the last SYNC's).

Units on the bus, as drives use them: positions in increments of a 20-bit encoder (:data:`COUNTS_PER_RAD`),
speeds in increments per second, torques in thousandths of the rated torque, currents in thousandths of the
rated current. :class:`CanLink` gives the bridge the interface of :class:`pusupu_jax.hw_bridge.udp.Endpoint`
(commands out, the newest complete feedback in), so the session runs over either transport.

On a real bus, bit timing limits the rate: 19 frames per cycle at 1 Mbit/s take about 2.3 ms
(about 120 bits each), so six axes fit 400 Hz, not 1 kHz; on the virtual bus there is no bit timing.
"""

from __future__ import annotations

import math
import threading
import time
from collections import Counter

import numpy as np

from . import protocol
from .udp import Refusal

COUNTS_PER_RAD = 2**20 / (2 * math.pi)  # increments per motor radian (20-bit encoder)
N_AXES = 6
DEVICE_TYPE = 0x00020192  # CiA 402, servo drive
SYNC_OVERFLOW = 240  # the SYNC counter runs 1..240 (CiA 301 object 0x1019)
SYNC_ECHO = 0x2000  # manufacturer-specific: the counter of the SYNC a drive's TPDOs answer (u8, 0: none)


def thousandths(value, rated) -> np.ndarray:
    """``value`` in thousandths of ``rated`` (per axis), rounded and held to an INTEGER16: CiA 402's unit of torques
    (of the rated torque 0x6076) and currents (of the rated current 0x6075)."""
    return np.clip(np.round(np.asarray(value) / rated * 1000.0), -(2**15), 2**15 - 1).astype(int)


def drive_dictionary():
    """The object dictionary of one simulated drive (and of the bridge's view of it)."""
    import canopen
    from canopen.objectdictionary import (
        INTEGER8,
        INTEGER16,
        INTEGER32,
        UNSIGNED8,
        UNSIGNED16,
        UNSIGNED32,
        ODRecord,
        ODVariable,
    )

    od = canopen.ObjectDictionary()

    def var(index, name, kind, access="rw", default=0, sub=0):
        v = ODVariable(name, index, sub)
        v.data_type, v.access_type, v.default = kind, access, default
        return v

    od.add_object(var(0x1000, "Device type", UNSIGNED32, "ro", DEVICE_TYPE))
    for index, name, kind, access in (
        (0x6040, "Controlword", UNSIGNED16, "rw"),
        (0x6041, "Statusword", UNSIGNED16, "ro"),
        (0x6060, "Modes of operation", INTEGER8, "rw"),
        (0x6061, "Modes of operation display", INTEGER8, "ro"),
        (0x6064, "Position actual value", INTEGER32, "ro"),
        (0x606C, "Velocity actual value", INTEGER32, "ro"),
        (0x6071, "Target torque", INTEGER16, "rw"),
        (0x6075, "Motor rated current", UNSIGNED32, "rw"),
        (0x6076, "Motor rated torque", UNSIGNED32, "rw"),
        (0x6077, "Torque actual value", INTEGER16, "ro"),
        (0x6078, "Current actual value", INTEGER16, "ro"),
        (0x60FF, "Target velocity", INTEGER32, "rw"),
        (SYNC_ECHO, "SYNC counter echo", UNSIGNED8, "ro"),
    ):
        od.add_object(var(index, name, kind, access))

    def pdo(comm_index, map_index, cob_id, entries, name):
        comm = ODRecord(f"{name} communication parameter", comm_index)
        for sub, (n, kind, default) in enumerate(
            (("Highest sub-index", UNSIGNED8, 2), ("COB-ID", UNSIGNED32, cob_id), ("Transmission type", UNSIGNED8, 1))
        ):
            comm.add_member(var(comm_index, n, kind, "rw", default, sub))
        od.add_object(comm)
        mapping = ODRecord(f"{name} mapping parameter", map_index)
        mapping.add_member(var(map_index, "Number of entries", UNSIGNED8, "rw", len(entries), 0))
        for sub, (index, bits) in enumerate(entries, start=1):
            mapping.add_member(var(map_index, f"Entry {sub}", UNSIGNED32, "rw", (index << 16) | bits, sub))
        od.add_object(mapping)

    pdo(0x1400, 0x1600, 0x200, [(0x6040, 16), (0x60FF, 32), (0x6071, 16)], "RPDO1")
    pdo(0x1800, 0x1A00, 0x180, [(0x6041, 16), (0x6064, 32), (0x6077, 16)], "TPDO1")
    pdo(0x1801, 0x1A01, 0x280, [(0x606C, 32), (0x6078, 16), (0x6061, 8), (SYNC_ECHO, 8)], "TPDO2")
    return od


def node_dictionary(node_id: int):
    """:func:`drive_dictionary` with the PDO COB-IDs of node ``node_id`` (0x200 + id, 0x180 + id, 0x280 + id)."""
    od = drive_dictionary()
    for index in (0x1400, 0x1800, 0x1801):
        od[index][1].default += node_id
    return od


def open_bus(url: str):
    """``can://INTERFACE/CHANNEL`` (``can://udp_multicast/239.74.163.2``, ``can://socketcan/can0``) -> a python-can
    bus."""
    import can

    rest = url[len("can://") :] if url.startswith("can://") else ""
    interface, _, channel = rest.partition("/")
    if not interface or not channel:
        raise ValueError(f"expected can://INTERFACE/CHANNEL, got {url!r}")
    kw = {"receive_own_messages": False} if interface == "udp_multicast" else {}
    return can.Bus(interface=interface, channel=channel, **kw)


class CanLink:
    """The bridge's side: six remote CiA 402 drives, set up over SDO, driven by RPDO + SYNC, read by TPDO."""

    # the feedback's sequence numbers are this link's count of the answers it returned, not the drives' periods
    robot_sequence = False

    def __init__(self, bus, drive_modes, rated_torque=None, sdo_timeout: float = 2.0, sdo_retries: int = 3):
        import can
        import canopen

        self.network = canopen.Network(bus)
        self.network.notifier = can.Notifier(bus, self.network.listeners, 0.1)
        self._can_error = can.CanError
        self.nodes = []
        self.rejected: Counter = Counter()
        self._sequence = 0
        self.arrived: list = []  # the answer the last poll returned, if any (the UDP endpoint's every packet)
        self._sent = None  # the sequence of the last command sent
        self._lock = threading.Lock()
        self._first = [None] * N_AXES  # each drive's TPDO1 values, until its TPDO2 completes the answer
        self._answers = [{} for _ in range(N_AXES)]  # per drive, its last two answers: echo -> values
        self._count = np.zeros(N_AXES, int)  # answers completed, per drive
        self._taken = (None, np.zeros(N_AXES, int))  # the command of the answer last returned, and the counts then
        for k in range(N_AXES):
            node = self.network.add_node(k + 1, node_dictionary(k + 1))
            # set-up is not cyclic: wait [s] and retry (the transfers are idempotent writes and reads) rather than
            # fail a bring-up on a loaded host (a clean-clone suite run lost one 0.5 s SDO response)
            node.sdo.RESPONSE_TIMEOUT, node.sdo.MAX_RETRIES = sdo_timeout, sdo_retries
            node.rpdo.read(from_od=True)
            node.tpdo.read(from_od=True)
            for j in (1, 2):
                node.tpdo[j].add_callback(lambda m, k=k, j=j: self._on_tpdo(k, j))
            self.nodes.append(node)
        self.modes = np.asarray(drive_modes, np.int8)
        self.rated = np.zeros(N_AXES)
        self.rated_current = np.zeros(N_AXES)  # A; 0: the drive reports no current
        for k, node in enumerate(self.nodes):  # SDO set-up
            node.sdo["Modes of operation"].raw = int(self.modes[k])
            shown = node.sdo["Modes of operation display"].raw
            if shown != self.modes[k]:
                raise RuntimeError(f"drive {k + 1}: mode of operation {self.modes[k]} not taken (shows {shown})")
            self.rated[k] = node.sdo["Motor rated torque"].raw * 1e-3  # N m
            self.rated_current[k] = node.sdo["Motor rated current"].raw * 1e-3  # A
        if rated_torque is not None and not np.allclose(self.rated, rated_torque, rtol=1e-3):
            raise RuntimeError(f"drives' rated torque {self.rated} N m, expected {rated_torque}")

    def _on_tpdo(self, k: int, j: int) -> None:
        """A TPDO of drive ``k`` (the notifier's thread): its values are kept as they arrive, since the next answer
        overwrites the PDO maps; a TPDO2 after a TPDO1 completes the drive's answer to the SYNC it echoes.  A TPDO
        shorter than its mapping is dropped and counted (``rejected['PDO length']``), and changes nothing."""
        m = self.nodes[k].tpdo[j]
        if len(m.data) * 8 < m.length:  # CiA 301: a PDO shorter than its mapping is not processed
            with self._lock:
                self.rejected["PDO length"] += 1
            return
        if j == 1:
            self._first[k] = (m["Statusword"].raw, m["Position actual value"].raw, m["Torque actual value"].raw)
            return
        first, self._first[k] = self._first[k], None
        if first is None:  # its TPDO1 was lost: no complete answer
            return
        echo = m["SYNC counter echo"].raw
        with self._lock:
            answers = self._answers[k]
            answers.pop(echo, None)
            answers[echo] = first + (
                m["Velocity actual value"].raw,
                m["Modes of operation display"].raw,
                m["Current actual value"].raw,
            )
            if len(answers) > 2:
                answers.pop(next(iter(answers)))
            self._count[k] += 1

    def send_command(self, cmd: protocol.Command) -> None:
        """One RPDO per drive, then SYNC; a frame the bus does not take ends the command's frames and is counted
        (``rejected['send failed']``), as a UDP endpoint counts a failed send."""
        velocity = np.round(np.where(self.modes == protocol.CSV, cmd.target, 0.0) * COUNTS_PER_RAD)
        torque = thousandths(np.where(self.modes == protocol.CST, cmd.target, 0.0), self.rated)
        try:
            for k, node in enumerate(self.nodes):
                m = node.rpdo[1]
                m["Controlword"].raw = int(cmd.controlword[k])
                m["Target velocity"].raw = int(np.clip(velocity[k], -(2**31), 2**31 - 1))
                m["Target torque"].raw = int(torque[k])
                m.transmit()
            self._sent = cmd.sequence
            self.network.sync.transmit(cmd.sequence % SYNC_OVERFLOW + 1)
        except self._can_error:  # a full transmit queue, a bus-off controller
            self.rejected[Refusal.SEND_FAILED] += 1

    def _acknowledged(self, echo: int) -> int:
        """The command sequence whose SYNC carried counter ``echo``: the latest sent with that counter (0: unknown)."""
        if not echo or self._sent is None:
            return 0
        return max(self._sent - (self._sent % SYNC_OVERFLOW + 1 - echo) % SYNC_OVERFLOW, 0)

    def poll(self, timeout: float = 0.0):
        """The newest answer that all six drives gave, to one SYNC, since the last one returned (waiting up to
        ``timeout`` [s] for it), as a :class:`~pusupu_jax.hw_bridge.protocol.Feedback` whose ``ack`` is the command that
        SYNC
        followed (0: unknown); None if there is none.  While the drives' TPDOs of one SYNC are still arriving, the
        answer before it is the newest complete one.  Drives that do not echo the counter (0) give each drive's last
        answer, once every drive has a new one."""
        end = time.monotonic() + timeout
        self.arrived = []
        while (answer := self._take()) is None and time.monotonic() < end:
            time.sleep(20e-6)
        if answer is None:
            return None
        echo, rows = answer
        status, position, torque, velocity, mode, current = (np.array(c) for c in zip(*rows))
        fb = protocol.Feedback(  # timestamp 0: a CAN frame carries no send time (the bridge reports no feedback age)
            self._sequence,
            0,
            self._acknowledged(echo),
            status.astype(np.uint16),
            mode.astype(np.int8),
            position / COUNTS_PER_RAD,
            velocity / COUNTS_PER_RAD,
            torque * self.rated / 1000.0,
            np.full(3, np.nan),
            current * self.rated_current / 1000.0 if self.rated_current.all() else None,
        )
        self._sequence += 1
        self.arrived = [fb]
        return fb

    def _take(self):
        """``(echo, one row of values per drive)`` of the newest answer not yet returned, or None."""
        with self._lock:
            common = set(self._answers[0]).intersection(*self._answers[1:])
            last, counts = self._taken
            if common - {0}:
                echo = max(common - {0}, key=self._acknowledged)
                if last is not None and self._acknowledged(echo) <= last:
                    return None
            elif common and (self._count > counts).all():
                echo = 0
            else:
                return None
            self._taken = (self._acknowledged(echo), self._count.copy())
            return echo, [self._answers[k][echo] for k in range(N_AXES)]

    def close(self) -> None:
        self.network.notifier.stop()
        self.network.bus.shutdown()
