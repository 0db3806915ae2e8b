"""Run logs in MCAP, the container of ROS 2 bags, which Foxglove and PlotJuggler open (host-side).

A log holds channels of JSON messages, each channel with the JSON Schema of its messages (schema encoding
``jsonschema``, message encoding ``json``: what both viewers read without a plug-in), and a metadata record
``pusupu`` naming what ran: the package version, the gain file's checksum and mode, the machine's name and digest, the
path, the rate.  ``pusupu bridge --log FILE`` writes the bridge's run (:func:`pusupu_jax.hw_bridge.session.run_log`),
``pusupu sim --plant mjx --log FILE`` the simulated machine's (:func:`machine_channels`), so that a run and its
simulation open side by side; ``docs/logs.md`` lists every channel and field.

The file is written once, after the run, from the record the run keeps in memory: nothing is written inside a
cycle.  It is written atomically (:func:`pusupu_jax.files.write_atomic`), with the user's umask.
"""

from __future__ import annotations

import io
import json
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal, overload

import numpy as np
import numpy.typing as npt

from .files import write_atomic

PROFILE = "pusupu"
METADATA = "pusupu"  # the name of the metadata record
# the metadata's ``source`` of a log that ``pusupu sim --plant mjx --log`` wrote: the fitting model's own run, at the
# model's step (:func:`pusupu_jax.machine_fit.default_step_check`)
SIM_SOURCE = "pusupu sim --plant mjx"


def _array(n: int, unit: str, what: str) -> dict[str, Any]:
    return {
        "type": "array",
        "items": {"type": "number"},
        "minItems": n,
        "maxItems": n,
        "description": f"{what} [{unit}]",
    }


def _number(unit: str, what: str) -> dict[str, Any]:
    return {"type": "number", "description": f"{what} [{unit}]"}


@dataclass
class Channel:
    """One topic: its JSON Schema's title and properties, and its messages as ``(time [s], message)``."""

    topic: str
    title: str
    properties: dict[str, Any]
    messages: list[tuple[float, dict[str, Any]]] = field(default_factory=list)

    def schema(self) -> dict[str, Any]:
        return {"type": "object", "title": self.title, "properties": self.properties, "required": list(self.properties)}


def plain(value: Any) -> Any:
    """``value`` as JSON takes it: arrays as lists, numpy scalars as numbers, NaN and inf as None."""
    if isinstance(value, dict):
        return {str(k): plain(v) for k, v in value.items()}
    if isinstance(value, np.ndarray):
        value = value.tolist()
    if isinstance(value, (list, tuple)):
        return [plain(v) for v in value]
    if isinstance(value, np.integer):
        return int(value)
    if isinstance(value, (float, np.floating)):
        return float(value) if np.isfinite(value) else None
    return value


def write(path: str | os.PathLike[str], channels: list[Channel], metadata: dict[str, Any], start_ns: int) -> Path:
    """Write ``channels`` to the MCAP file ``path`` (atomically); a message at time ``t`` [s] is logged at
    ``start_ns + t`` [ns since the Unix epoch].  ``metadata``: the ``pusupu`` record (values written as text)."""
    from mcap.writer import Writer

    buffer = io.BytesIO()
    writer = Writer(buffer)
    writer.start(profile=PROFILE, library=f"pusupu_jax {metadata.get('package_version', '')}".strip())
    for channel in channels:
        schema = writer.register_schema(channel.title, "jsonschema", json.dumps(channel.schema()).encode())
        cid = writer.register_channel(channel.topic, "json", schema)
        for sequence, (t, message) in enumerate(channel.messages):
            stamp = start_ns + int(round(float(t) * 1e9))
            writer.add_message(cid, stamp, json.dumps(plain(message)).encode(), stamp, sequence)
    writer.add_metadata(
        METADATA, {str(k): v if isinstance(v, str) else json.dumps(plain(v)) for k, v in metadata.items()}
    )
    writer.finish()  # type: ignore[no-untyped-call]  # mcap leaves Writer.finish unannotated
    return write_atomic(path, buffer.getvalue())


def read(path: str | os.PathLike[str]) -> tuple[dict[str, tuple[Any, list[tuple[int, Any]]]], dict[str, str]]:
    """``({topic: (schema, [(log time [ns], message)])}, metadata)`` of an MCAP file written by :func:`write` (the
    ``mcap`` package's reader; for tests and notebooks)."""
    from mcap.reader import make_reader

    with open(path, "rb") as f:
        reader = make_reader(f)
        topics: dict[str, tuple[Any, list[tuple[int, Any]]]] = {}
        for schema, channel, message in reader.iter_messages():
            entry = topics.setdefault(channel.topic, (None if schema is None else json.loads(schema.data), []))
            entry[1].append((message.log_time, json.loads(message.data)))
        metadata: dict[str, str] = {}
        for record in reader.iter_metadata():
            if record.name == METADATA:
                metadata = dict(record.metadata)
    return topics, metadata


def machine_channels(arrays: dict[str, Any]) -> list[Channel]:
    """The simulated machine's run (the arrays of :func:`pusupu_jax.machine.simulate_scenarios`, one sample per position
    period): ``/sim/platform`` (the platform's reference and position), ``/sim/branch`` (each branch's force) and
    ``/sim/drive`` (per axis the motor's reference, angle, speed, torque and current: the fields of the bridge's
    ``/bridge/feedback`` of the same names)."""
    platform = Channel(
        "/sim/platform",
        "pusupu.SimPlatform",
        {
            "reference_m": _array(3, "m", "the platform's reference position"),
            "platform_m": _array(3, "m", "the platform's position"),
            "error_mm": _number("mm", "the platform's position error"),
        },
    )
    branch = Channel(
        "/sim/branch", "pusupu.SimBranch", {"force_n": _array(6, "N", "each branch's force along its rod")}
    )
    ref, pos = np.asarray(arrays["reference"]), np.asarray(arrays["platform"])
    for k, t in enumerate(np.asarray(arrays["t"])):
        platform.messages.append(
            (t, {"reference_m": ref[k], "platform_m": pos[k], "error_mm": float(np.linalg.norm(pos[k] - ref[k]) * 1e3)})
        )
        branch.messages.append((t, {"force_n": np.asarray(arrays["branch_force"])[k]}))
    drive = {name: np.asarray(v) for name, v in arrays["drive"].items()}
    n = drive["position_rad"].shape[-1]
    motor = Channel(
        "/sim/drive",
        "pusupu.SimDrive",
        {
            "path_time_s": _number("s", "the time along the path of the sample's reference"),
            "reference_rad": _array(n, "rad", "per axis: the motor angle followed"),
            "position_rad": _array(n, "rad", "per axis: the motor angle"),
            "velocity_rad_s": _array(n, "rad/s", "per axis: the motor speed"),
            "torque_nm": _array(n, "N m", "per axis: the motor torque"),
            "current_a": _array(n, "A", "per axis: the motor current"),
        },
    )
    for k, t in enumerate(np.asarray(arrays["t"])):
        motor.messages.append((t, {"path_time_s": t} | {name: v[k] for name, v in drive.items()}))
    return [platform, branch, motor]


@dataclass(frozen=True)
class BridgeTiming:
    """How a bridge's run went, cycle by cycle, where its log says (over UDP): what a replay of it needs besides the
    samples (:func:`pusupu_jax.machine_fit.bridge_commands`).  Per command of the run, in order ``(M,)``: the time
    along the path of the reference row it was computed from [s] (``path_time``; a cycle the bridge skipped sent no
    command, so rows can be stepped over), its sequence number (``sequence``) and the sequence number of the feedback
    packet it was computed from (``feedback``; 0: none).  Per sample of the :class:`DriveLog` ``(N,)``: the robot's
    sequence number of its packet (``sample_sequence``) and the command's it answers (``sample_ack``: the command the
    robot ran in that period).  The log keeps every packet that came, so the commands no sample answers are the ones
    the robot did not run."""

    path_time: np.ndarray
    sequence: np.ndarray
    feedback: np.ndarray
    sample_sequence: np.ndarray
    sample_ack: np.ndarray


LOG_LIMIT = 1 << 30  # bytes: the largest log read (an hour at 1 kHz of six axes is about 0.5 GiB of JSON messages)
DRIVE_TOPICS = ("/sim/drive", "/bridge/feedback")  # the channels that carry each axis's drive samples


@dataclass(frozen=True)
class DriveLog:
    """The drive samples of one run log (:func:`drive_log`): what a log holds for identification.

    ``path_time`` ``(N,)`` [s] along the path; per sample and axis ``(N, n_axes)``: ``reference`` [rad] (the motor
    angle followed), ``position`` [rad], ``velocity`` [rad/s], ``torque`` [N m] and ``current`` [A] (None where the
    log has none: protocol version 1, CANopen).  ``mode``, ``trajectory`` (the path's name or file) and ``rate_hz``
    come from the log's metadata, with ``gain_checksum`` (the gain file's, where the log names it: the bridge's);
    ``digest`` is the file's SHA-256.  ``timing``: the run's cycles, where a bridge log over UDP has them (None: a
    simulation's log, which takes every row in turn, a CSV table, a log over CANopen or of an older bridge)."""

    path: str
    digest: str
    source: str
    gain_checksum: str | None
    mode: str
    trajectory: str
    rate_hz: float
    path_time: np.ndarray
    reference: np.ndarray
    position: np.ndarray
    velocity: np.ndarray
    torque: np.ndarray
    current: np.ndarray | None
    timing: BridgeTiming | None = None


COMMAND_TOPIC = "/bridge/command"
COMMAND_FIELDS = ("path_time_s", "sequence", "feedback")  # what a replay takes of each command of a run


def drive_log(path: str | os.PathLike[str]) -> DriveLog:
    """The drive samples of the MCAP log ``path`` written by ``pusupu sim --plant mjx --log`` (``/sim/drive``) or
    ``pusupu bridge --log`` (``/bridge/feedback``); :class:`~pusupu_jax.params.ParameterError` with one line for a file
    that is not such a log."""
    import hashlib

    from mcap.exceptions import McapError
    from mcap.reader import make_reader

    from .inputs import read_bytes
    from .params import ParameterError

    data = read_bytes(path, "MCAP run log", ParameterError, limit=LOG_LIMIT)
    try:
        reader = make_reader(io.BytesIO(data))
        metadata = next((dict(r.metadata) for r in reader.iter_metadata() if r.name == METADATA), None)
        samples: list[Any] = []
        commands: list[Any] = []
        for _, channel, m in reader.iter_messages(topics=[*DRIVE_TOPICS, COMMAND_TOPIC]):
            (commands if channel.topic == COMMAND_TOPIC else samples).append(json.loads(m.data))
    except (McapError, ValueError, KeyError, EOFError) as e:
        raise ParameterError(f"{path}: expected an MCAP run log, got a file that does not read as one ({e})") from None
    if metadata is None or not {"mode", "trajectory", "rate_hz"} <= set(metadata):
        raise ParameterError(
            f"{path}: expected a log of pusupu sim or pusupu bridge (a '{METADATA}' metadata record with mode, "
            "trajectory and rate_hz), found none"
        )
    if not samples:
        raise ParameterError(f"{path}: expected drive samples on {' or '.join(DRIVE_TOPICS)}, found none")

    @overload
    def column(name: str, optional: Literal[False] = False) -> npt.NDArray[np.float64]: ...

    @overload
    def column(name: str, optional: bool) -> npt.NDArray[np.float64] | None: ...

    def column(name: str, optional: bool = False) -> npt.NDArray[np.float64] | None:
        values = [m.get(name) for m in samples]
        if optional and all(v is None or (isinstance(v, list) and None in v) for v in values):
            return None
        try:
            out = np.asarray(values, dtype=float)
        except (TypeError, ValueError):
            raise ParameterError(f"{path}: {name}: expected numbers in every sample") from None
        if not np.isfinite(out).all():
            raise ParameterError(f"{path}: {name}: expected finite numbers in every sample, found NaN or inf")
        return out

    timing = _timing(path, commands, column("sequence", optional=True), column("ack", optional=True))
    try:
        rate = float(json.loads(metadata["rate_hz"]))
    except ValueError:
        rate = float("nan")
    if not (np.isfinite(rate) and rate > 0):
        raise ParameterError(f"{path}: metadata rate_hz: expected a positive number, got {metadata['rate_hz']!r}")
    return DriveLog(
        path=str(path),
        digest=hashlib.sha256(data).hexdigest(),
        source=metadata.get("source", ""),
        gain_checksum=metadata.get("gain_file_checksum"),
        mode=metadata["mode"],
        trajectory=metadata["trajectory"],
        rate_hz=rate,
        path_time=column("path_time_s"),
        reference=column("reference_rad"),
        position=column("position_rad"),
        velocity=column("velocity_rad_s"),
        torque=column("torque_nm"),
        current=column("current_a", optional=True),
        timing=timing,
    )


def _timing(
    path: Any, commands: list[Any], sample_sequence: np.ndarray | None, sample_ack: np.ndarray | None
) -> BridgeTiming | None:
    """The :class:`BridgeTiming` of a log's ``/bridge/command`` messages and its samples' sequence numbers and acks
    (None where no sample has them); None where the log does not say."""
    from .params import ParameterError

    run = [c for c in commands if isinstance(c, dict) and c.get("path_time_s") is not None]
    if sample_sequence is None or sample_ack is None or not run:
        return None
    try:
        path_time, sequence, feedback = (np.asarray([c[k] for c in run], dtype=float) for k in COMMAND_FIELDS)
    except (KeyError, TypeError, ValueError):
        raise ParameterError(
            f"{path}: {COMMAND_TOPIC}: expected numbers {', '.join(COMMAND_FIELDS)} in every command of the run"
        ) from None
    for name, x in (
        ("sequence", sample_sequence),
        ("ack", sample_ack),
        (f"{COMMAND_TOPIC} sequence", sequence),
        (f"{COMMAND_TOPIC} feedback", feedback),
    ):
        if ((x != np.round(x)) | (x < 0) | (x >= 2**32)).any():
            raise ParameterError(f"{path}: {name}: expected whole numbers in [0, 2^32), found another")
    if not np.isfinite(path_time).all() or (np.diff(path_time) < 0).any():
        raise ParameterError(f"{path}: {COMMAND_TOPIC} path_time_s: expected finite times that never fall")
    whole = (x.astype(np.int64) for x in (sequence, feedback, sample_sequence, sample_ack))
    return BridgeTiming(path_time, *whole)
