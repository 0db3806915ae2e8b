"""The bridge's UDP protocol, versions 1 and 2: fixed-layout little-endian packets with sequence numbers and a CRC.

Every packet::

    offset size  field
    0      4     magic b"PSPU"
    4      1     version (1 or 2)
    5      1     kind: 1 command (bridge -> robot), 2 feedback (robot -> bridge)
    6      1     n_axes (1..16)
    7      1     flags (0; reserved)
    8      4     sequence (u32, +1 per packet of a sender, wrapping)
    12     8     timestamp (i64, ns on the sender's CLOCK_MONOTONIC)
    20     4     ack (u32): command -> the feedback sequence it answers; feedback -> the last command applied
    24     2     payload length (u16, bytes)
    26     ...   payload
    end    4     CRC-32 (zlib/IEEE 802.3) of every byte before it

Command payload, per axis (12 bytes): controlword (u16, CiA 402 object 0x6040), mode of
operation (i8, 0x6060: 9 cyclic synchronous velocity, 10 cyclic synchronous torque), pad (u8),
target (f64: motor speed [rad/s] in CSV, motor torque [N m] in CST).

Feedback payload: per axis (28 bytes) statusword (u16, 0x6041), mode display (i8, 0x6061), pad
(u8), position (f64, motor angle from home [rad]), velocity (f64, [rad/s]), torque (f64, actual
motor torque [N m]); then the platform position (3 f64, [m]; NaN when the robot does not know it).
Version 2's feedback appends to each axis (36 bytes) the measured motor current (f64, [A]): what a
drive's torque constant is identified from, since the torque it reports is that current times the
constant it was told.  Its command is version 1's; a bridge takes feedback of either version, so a
robot of version 1 needs no change.

:data:`LAYOUTS` holds these layouts per version, and a packet is decoded only when its length is
its version's for its kind and axis count, to the byte, and its axis count is the session's (the
receiver's ``n_axes``): each version has its own row and leaves the others' checks as they are.
:func:`decode` refuses anything else with a :class:`ProtocolError` whose ``reason`` names the check
that failed; the receiver counts refusals by reason and drops the packet.
"""

from __future__ import annotations

import functools
import struct
import zlib
from dataclasses import dataclass

import numpy as np

MAGIC = b"PSPU"
VERSION = 1  # of the commands; feedback is version 1, or 2 where it carries the measured currents
COMMAND, FEEDBACK = 1, 2
MAX_AXES = 16
MAX_PACKET = 1024  # bytes: larger datagrams are refused before decoding
CSV, CST = 9, 10  # CiA 402 modes of operation (object 0x6060)

_HEADER = struct.Struct("<4sBBBBIqIH")
_CRC = struct.Struct("<I")
# per version and kind: the struct codes (one per value) of one axis's fields, then of the fields after the axes.
# Version 1's fields keep their places in a later version (which may append to an axis or to the tail), so the decoder
# reads them there
LAYOUTS = {
    1: {
        COMMAND: ("HbBd", ""),  # controlword, mode, pad, target
        FEEDBACK: ("HbBddd", "3d"),  # statusword, mode, pad, position, velocity, torque; the platform
    },
    2: {
        COMMAND: ("HbBd", ""),
        FEEDBACK: ("HbBdddd", "3d"),  # version 1's, then the measured current
    },
}
REASONS = ("size", "magic", "version", "kind", "axes", "length", "crc")


class ProtocolError(ValueError):
    """A packet that is not a valid packet of a version in :data:`LAYOUTS`; ``reason`` is one of :data:`REASONS`."""

    def __init__(self, reason: str, detail: str):
        super().__init__(f"{reason}: {detail}")
        self.reason = reason


@dataclass(frozen=True)
class Command:
    """One cycle's command to the drives; arrays ``(n_axes,)``."""

    sequence: int
    timestamp_ns: int
    ack: int  # the feedback sequence this command answers
    controlword: np.ndarray  # u16
    mode: np.ndarray  # i8: CSV or CST per axis
    target: np.ndarray  # rad/s (CSV) or N m (CST)


@dataclass(frozen=True)
class Feedback:
    """One sample of the drives' actual values; arrays ``(n_axes,)``."""

    sequence: int
    timestamp_ns: int
    ack: int  # the last command sequence the robot applied
    statusword: np.ndarray  # u16
    mode: np.ndarray  # i8
    position: np.ndarray  # motor angle from home, rad
    velocity: np.ndarray  # rad/s
    torque: np.ndarray  # N m
    platform: np.ndarray  # (3,) m, NaN when unknown
    current: np.ndarray | None = None  # measured motor current, A (version 2; None: not reported)


def _pack(
    kind: int, sequence: int, timestamp_ns: int, ack: int, n_axes: int, payload: bytes, version: int = VERSION
) -> bytes:
    head = _HEADER.pack(
        MAGIC, version, kind, n_axes, 0, sequence & 0xFFFFFFFF, timestamp_ns, ack & 0xFFFFFFFF, len(payload)
    )
    body = head + payload
    return body + _CRC.pack(zlib.crc32(body))


@functools.lru_cache(maxsize=2 * MAX_AXES * len(LAYOUTS))
def _payload(version: int, kind: int, n: int) -> struct.Struct:
    """The payload layout of a ``kind`` packet of ``n`` axes in ``version`` (one ``struct`` call packs or unpacks it
    whole: a numpy structured array costs several times more per field at kilohertz rates)."""
    axis, tail = LAYOUTS[version][kind]
    return struct.Struct("<" + axis * n + tail)


def _interleave(*columns) -> list:
    """Per-axis columns as one flat list, axis by axis (the payload's order)."""
    return [v for row in zip(*(np.asarray(c).tolist() for c in columns)) for v in row]


def encode_command(c: Command) -> bytes:
    n = len(c.target)
    payload = _payload(VERSION, COMMAND, n).pack(*_interleave(c.controlword, c.mode, np.zeros(n, int), c.target))
    return _pack(COMMAND, c.sequence, c.timestamp_ns, c.ack, n, payload)


def encode_feedback(f: Feedback) -> bytes:
    """Version 2 where ``f`` carries the measured currents, else version 1."""
    n = len(f.position)
    columns = [f.statusword, f.mode, np.zeros(n, int), f.position, f.velocity, f.torque]
    version = 1 if f.current is None else 2
    payload = _payload(version, FEEDBACK, n).pack(
        *_interleave(*columns, *([] if f.current is None else [f.current])), *np.asarray(f.platform).tolist()
    )
    return _pack(FEEDBACK, f.sequence, f.timestamp_ns, f.ack, n, payload, version)


def decode(data: bytes, kind: int | None = None, n_axes: int | None = None) -> Command | Feedback:
    """The packet in ``data`` (of ``kind`` and ``n_axes`` axes, the session's, if given); :class:`ProtocolError` for
    anything malformed or of another axis count."""
    if not (_HEADER.size + _CRC.size <= len(data) <= MAX_PACKET):
        raise ProtocolError("size", f"expected {_HEADER.size + _CRC.size}..{MAX_PACKET} bytes, got {len(data)}")
    magic, version, k, n, _, seq, stamp, ack, length = _HEADER.unpack_from(data)
    if magic != MAGIC:
        raise ProtocolError("magic", f"expected {MAGIC!r}, got {magic!r}")
    if version not in LAYOUTS:
        raise ProtocolError("version", f"expected one of {sorted(LAYOUTS)}, got {version}")
    if k not in (COMMAND, FEEDBACK) or (kind is not None and k != kind):
        raise ProtocolError("kind", f"expected {kind or (COMMAND, FEEDBACK)}, got {k}")
    if not 1 <= n <= MAX_AXES or (n_axes is not None and n != n_axes):
        wanted = f"1..{MAX_AXES} axes" if n_axes is None else f"{n_axes} axes (the session's)"
        raise ProtocolError("axes", f"expected {wanted}, got {n}")
    layout = _payload(version, k, n)
    expected = layout.size
    if length != expected or len(data) != _HEADER.size + length + _CRC.size:
        raise ProtocolError(
            "length",
            f"expected a payload of {expected} bytes in a packet of "
            f"{_HEADER.size + expected + _CRC.size}, got {length} in {len(data)}",
        )
    (crc,) = _CRC.unpack_from(data, len(data) - _CRC.size)
    if crc != zlib.crc32(data[: -_CRC.size]):
        raise ProtocolError("crc", "the CRC-32 does not match the packet")
    v = layout.unpack_from(data, _HEADER.size)
    step = len(LAYOUTS[version][k][0])  # values per axis
    if k == COMMAND:
        return Command(
            seq, stamp, ack, np.array(v[0::step], np.uint16), np.array(v[1::step], np.int8), np.array(v[3::step], float)
        )
    end = step * n
    return Feedback(
        seq,
        stamp,
        ack,
        np.array(v[0:end:step], np.uint16),
        np.array(v[1:end:step], np.int8),
        np.array(v[3:end:step], float),
        np.array(v[4:end:step], float),
        np.array(v[5:end:step], float),
        np.array(v[end : end + 3], float),
        np.array(v[6:end:step], float) if version >= 2 else None,
    )


def newer(sequence: int, last: int | None) -> bool:
    """``sequence`` comes after ``last`` in u32 serial-number arithmetic (RFC 1982); a replay or a late packet does
    not."""
    return last is None or 0 < (sequence - last) % 2**32 < 2**31
