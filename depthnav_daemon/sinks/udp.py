"""``udp``: the stdout JSON object (docs/json_schema.md) as one UDP datagram per frame.

Spec: ``udp://HOST:PORT[?max_bytes=N]``; ``udp://:PORT`` and ``udp:PORT`` mean 127.0.0.1 (a robot
should not spray its scan over the LAN unless asked). IPv6 as ``udp://[::1]:PORT``.

Options:
    max_bytes: largest datagram, bytes (default 60000, 512..65507). A bigger message keeps only the
        nearest cliff points and says so in its ``message`` field; one that still does not fit is
        skipped.

Sending never blocks and never raises: the socket is non-blocking and connected, so a receiver
that is gone shows up as ConnectionRefusedError (ICMP port unreachable) on a later send. Failures
are counted and logged at most once per 10 s; the frame loop goes on.
"""

from __future__ import annotations

import logging
import socket
import time
from typing import TYPE_CHECKING

from depthnav_daemon.errors import SinkError
from depthnav_daemon.sinks import jsonmsg
from depthnav_daemon.sinks.base import (
    RateLimitedLog,
    SinkContext,
    SinkSpec,
    check_options,
    number_option,
    parse_host_port,
)

if TYPE_CHECKING:
    from depthnav_daemon.pipeline import Result
    from drivers.base import Frame

log = logging.getLogger(__name__)

GRAMMAR = "udp://HOST:PORT[?max_bytes=N]"
DEFAULT_HOST = "127.0.0.1"
DEFAULT_MAX_BYTES = 60000
MAX_UDP_PAYLOAD = 65507  # IPv4: 65535 - 20 (IP header) - 8 (UDP header)


class UdpSink:
    """Sends one JSON datagram per frame to HOST:PORT.

    Args:
        name: the spec, for messages.
        host, port: destination.
        max_bytes: largest datagram to send, bytes.
    """

    def __init__(self, name: str, host: str, port: int, max_bytes: int = DEFAULT_MAX_BYTES) -> None:
        self.name = name
        self.host = host
        self.port = port
        self.max_bytes = max_bytes
        self._sock: socket.socket | None = None
        self._version = "unknown"
        self._send_errors = RateLimitedLog(log)
        self._oversize = RateLimitedLog(log)
        self.sent = 0

    @property
    def send_errors(self) -> int:
        """Send errors since open: receiver gone (each ICMP report), buffer full, network down."""
        return self._send_errors.count

    @classmethod
    def from_spec(cls, spec: SinkSpec) -> UdpSink:
        """Build from a parsed spec (no I/O). Raises ConfigError for a bad address or option."""
        check_options(spec, ("max_bytes",), GRAMMAR)
        host, port = parse_host_port(spec, DEFAULT_HOST, None)
        max_bytes = int(
            number_option(spec, "max_bytes", DEFAULT_MAX_BYTES, 512, MAX_UDP_PAYLOAD, integer=True)
        )
        return cls(spec.text, host, port, max_bytes)

    def open(self, context: SinkContext) -> None:
        """Resolve the address and make a connected, non-blocking UDP socket.

        Raises:
            SinkError: the host does not resolve or the socket cannot be made.
        """
        self._version = context.version
        try:
            infos = socket.getaddrinfo(self.host, self.port, type=socket.SOCK_DGRAM)
        except socket.gaierror as exc:
            raise SinkError(
                f"udp sink: cannot resolve {self.host!r}: {exc}",
                hint="give an IP address or a resolvable host name",
            ) from exc
        family, kind, proto, _, addr = infos[0]
        sock = socket.socket(family, kind, proto)
        try:
            if family == socket.AF_INET and addr[0].endswith(".255"):
                sock.setsockopt(socket.SOL_SOCKET, socket.SO_BROADCAST, 1)
            sock.setblocking(False)
            # connect() fixes the destination, so ICMP "port unreachable" shows on a later send
            sock.connect(addr)
        except OSError as exc:
            sock.close()
            raise SinkError(f"udp sink: cannot send to {self.host}:{self.port}: {exc}") from exc
        self._sock = sock
        log.info("udp sink sending JSON datagrams to %s:%d", addr[0], addr[1])

    def write(self, frame: Frame, result: Result) -> None:
        """Send the frame's datagram; failures are counted and logged, never raised."""
        if self._sock is None:
            raise SinkError(f"sink {self.name!r} is not open")
        data = jsonmsg.fit_message(frame, result, self._version, time.time(), self.max_bytes)
        if data is None:
            self._oversize.failed(
                "udp sink: frame %d does not fit one %d-byte datagram; skipped",
                result.seq,
                self.max_bytes,
            )
            return
        try:
            try:
                self._sock.send(data)
            except ConnectionRefusedError:
                # the ICMP error belongs to an earlier datagram and was reported instead of sending
                # this one: count it and try once more, so a receiver that came back gets this frame
                self._send_errors.failed(
                    "udp sink: %s:%d is not receiving (ConnectionRefusedError)",
                    self.host,
                    self.port,
                )
                self._sock.send(data)
        except (BlockingIOError, ConnectionRefusedError) as exc:
            # socket buffer full, or the receiver refused again: drop this frame, keep going
            self._send_errors.failed(
                "udp sink: datagram to %s:%d dropped: %s", self.host, self.port, type(exc).__name__
            )
        except OSError as exc:  # network unreachable, message too long for this route, ...
            self._send_errors.failed(
                "udp sink: datagram to %s:%d dropped: %s", self.host, self.port, exc
            )
        else:
            self.sent += 1

    def close(self) -> None:
        """Close the socket. Safe to call twice."""
        sock, self._sock = self._sock, None
        if sock is not None:
            sock.close()
            if self.send_errors:
                log.info(
                    "udp sink %s: %d sent, %d send errors", self.name, self.sent, self.send_errors
                )
