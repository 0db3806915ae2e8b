"""UDP endpoints of the protocol (:mod:`pusupu_jax.hw_bridge.protocol`): non-blocking sockets, every datagram checked
and counted.

:class:`Endpoint` receives packets of one kind and of the session's axis count and keeps the
newest valid one; malformed, truncated, oversized, wrong-version, other-axis-count and replayed
(or reordered: not newer than the last accepted from the same peer) packets are dropped and
counted by reason, and so is feedback from any address and port but the robot's.  Nothing a
peer sends can raise.  The robot's side follows the sender of the last valid command: a bridge
restarted on a new socket starts a new sequence.
"""

from __future__ import annotations

import enum
import ipaddress
import socket
import time
from collections import Counter
from urllib.parse import urlparse

from . import protocol


class Refusal(enum.StrEnum):
    """What an endpoint counts beside the decoder's reasons (:data:`pusupu_jax.hw_bridge.protocol.REASONS`)."""

    REPLAYED = "replayed"  # not newer than the last packet accepted from the same peer
    SENDER = "sender"  # feedback from an address or port other than the robot's
    SOCKET_ERROR = "socket error"  # e.g. ICMP port unreachable reported on the socket
    SEND_FAILED = "send failed"


def parse_url(url: str, scheme: str = "udp") -> tuple[str, int]:
    """``udp://HOST:PORT`` -> (host, port); ValueError naming what was expected."""
    u = urlparse(url)
    try:
        port = u.port
    except ValueError:
        port = None
    if u.scheme != scheme or not u.hostname or port is None:
        raise ValueError(f"expected {scheme}://HOST:PORT, got {url!r}")
    return u.hostname, port


def beyond_loopback(host: str) -> str | None:
    """Where a socket bound to ``host`` takes packets from, when that is more than this machine: 'every interface
    (0.0.0.0)' or the address ``host`` resolves to; None for a loopback address.  ``OSError`` when ``host`` does not
    resolve."""
    address = socket.getaddrinfo(host, None, socket.AF_INET, socket.SOCK_DGRAM)[0][4][0]
    ip = ipaddress.ip_address(address)
    if ip.is_loopback:
        return None
    return f"every interface ({address})" if ip.is_unspecified else f"the interface of {address}"


class Endpoint:
    """A UDP socket that sends packets and receives packets of kind ``kind`` (COMMAND or FEEDBACK) with ``n_axes`` axes.

    ``bind``: local address (default loopback, a free port); ``peer``: where to send (None: to
    whoever sent the last valid packet).  Feedback is taken from ``peer`` alone (its address
    resolved here), or, without one, from the first sender of a valid packet alone; a command
    from a new sender starts a new sequence (a restarted bridge).
    """

    def __init__(self, kind: int, *, n_axes: int, bind=("127.0.0.1", 0), peer=None):
        self.kind = kind
        self.n_axes = n_axes
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 1 << 20)
        self.sock.bind(bind)
        self.sock.setblocking(False)
        # as recvfrom names senders: a numeric address (a host name given here would never match one)
        self.peer = None if peer is None else socket.getaddrinfo(*peer, socket.AF_INET, socket.SOCK_DGRAM)[0][4]
        self.rejected: Counter = Counter()
        self.accepted = 0
        self.last_sequence = None
        self.received_at = 0.0  # s, monotonic: when the newest packet arrived
        self.arrived: list = []  # every valid packet the last poll accepted, oldest first (the newest: it returned)

    # the feedback's sequence numbers are the robot's own, one a packet it sent: a run's log keeps them, and the
    # feedback of every period the robot ran (:mod:`pusupu_jax.machine_fit` replays those periods)
    robot_sequence = True

    @property
    def address(self) -> tuple[str, int]:
        return self.sock.getsockname()

    def send(self, data: bytes) -> None:
        if self.peer is not None:
            try:
                self.sock.sendto(data, self.peer)
            except OSError:
                self.rejected[Refusal.SEND_FAILED] += 1

    def send_command(self, cmd: protocol.Command) -> None:
        self.send(protocol.encode_command(cmd))

    def poll(self, timeout: float = 0.0):
        """The newest valid packet received since the last call (None if none); waits up to ``timeout`` [s] for one."""
        newest = None
        self.arrived = []
        if timeout > 0:
            self.sock.settimeout(timeout)
        try:
            while True:
                try:
                    data, addr = self.sock.recvfrom(protocol.MAX_PACKET + 1)
                except (BlockingIOError, socket.timeout):
                    break
                except OSError:  # e.g. ICMP port unreachable reported on a connected peer
                    self.rejected[Refusal.SOCKET_ERROR] += 1
                    continue
                finally:
                    if timeout > 0:
                        self.sock.setblocking(False)
                        timeout = 0.0
                if self.kind == protocol.FEEDBACK and self.peer is not None and addr != self.peer:
                    self.rejected[Refusal.SENDER] += 1  # not decoded: only the robot's bytes are
                    continue
                try:
                    packet = protocol.decode(data, self.kind, self.n_axes)
                except protocol.ProtocolError as e:
                    self.rejected[e.reason] += 1
                    continue
                if self.kind == protocol.COMMAND and addr != self.peer:
                    self.last_sequence = None  # a new bridge (a new socket): its own sequence, from wherever it starts
                if not protocol.newer(packet.sequence, self.last_sequence):
                    self.rejected[Refusal.REPLAYED] += 1
                    continue
                self.last_sequence = packet.sequence
                self.accepted += 1
                self.received_at = time.monotonic()
                if self.peer is None or self.kind == protocol.COMMAND:
                    self.peer = addr
                newest = packet
                self.arrived.append(packet)
        finally:
            self.sock.setblocking(False)
        return newest

    def close(self) -> None:
        self.sock.close()
