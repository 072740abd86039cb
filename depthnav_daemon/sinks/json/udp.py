"""``udp``: the stdout JSON object (docs/json_schema.md) as one UDP datagram per frame.

Spec: ``udp://HOST:PORT[?max_bytes=N&content=all|scan&cliff_scan=0|1&ranges=m|mm&every=N&rate=HZ]``;
``udp://:PORT`` and ``udp:PORT`` mean 127.0.0.1 (a robot should not spray its scan over the LAN
unless asked). IPv6 as ``udp://[::1]:PORT``.

Options (a full message at 640x480 is ~12.5 KB: fragmented on Wi-Fi; these slim it):
    max_bytes: largest datagram, bytes (default 60000, 512..65507). A bigger message keeps only the
        nearest cliff points and says so in its ``message`` field; one that still does not fit is
        skipped. A max_bytes that no frame of the camera can fit (its scan ranges alone, each at
        its shortest, are more) fails the sink on the first frame, with the bytes needed.
    content: ``all`` (default, the stdout object) or ``scan``: seq, times, the scan, the mount
        (pose and trust) and the warning only.
    cliff_scan: 0 leaves out the cliff's polar scan (its floor points stay).
    ranges: ``mm`` sends every range as integer millimetres (``scan.ranges_unit`` says so;
        null / "Infinity" / "-Infinity" as in metres); default ``m``.
    every: send every Nth frame (default 1).
    rate: send at most this many datagrams per second of sensor time (default 0 = every frame),
        like the ROS nodes' ``rate``.

Sending never blocks and never raises: the socket is non-blocking and connected, so a receiver
that is gone shows up as ConnectionRefusedError (ICMP port unreachable) on a later send. Failures
are counted and logged at most once per 10 s; the frame loop goes on.
"""

from __future__ import annotations

import logging
import socket
import time
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import orjson

from depthnav_daemon.errors import SinkError
from depthnav_daemon.sinks.base import (
    RateLimitedLog,
    SinkContext,
    SinkSpec,
    bool_option,
    check_options,
    choice_option,
    number_option,
    parse_host_port,
)
from depthnav_daemon.sinks.json import line as json_line
from depthnav_daemon.sinks.json.message import frame_message

if TYPE_CHECKING:
    from depthnav_daemon.pipeline import Result
    from drivers.base import Frame

log = logging.getLogger(__name__)

GRAMMAR = (
    "udp://HOST:PORT[?max_bytes=N&content=all|scan&cliff_scan=0|1&ranges=m|mm&every=N&rate=HZ]"
)
OPTIONS = ("max_bytes", "content", "cliff_scan", "ranges", "every", "rate")
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

    def __init__(
        self,
        name: str,
        host: str,
        port: int,
        max_bytes: int = DEFAULT_MAX_BYTES,
        content: Content | None = None,
    ) -> None:
        self.name = name
        self.host = host
        self.port = port
        self.max_bytes = max_bytes
        self.content = content or Content()
        # the common case's checks made once: every frame goes, and as the stdout line
        self._every_frame = self.content.every == 1 and self.content.rate_hz == 0
        self._whole = self.content.whole
        self._frames = 0
        self._last_sent_t: float | None = None
        self._sock: socket.socket | None = None
        self._version = "unknown"
        self._send_errors = RateLimitedLog(log)
        self._oversize = RateLimitedLog(log)
        self._fits_some: set[tuple[int, int]] = set()  # scan layouts some frame of can fit
        self._range_min_m = 0.0
        self.sent = 0

    @property
    def send_errors(self) -> int:
        """Send errors since open: receiver gone (each ICMP report), buffer full, network down."""
        return self._send_errors.count

    @classmethod
    def from_spec(cls, spec: SinkSpec) -> UdpSink:
        """Build from a parsed spec (no I/O). Raises ConfigError for a bad address or option."""
        check_options(spec, OPTIONS, GRAMMAR)
        host, port = parse_host_port(spec, DEFAULT_HOST, None)
        max_bytes = int(
            number_option(spec, "max_bytes", DEFAULT_MAX_BYTES, 512, MAX_UDP_PAYLOAD, integer=True)
        )
        content = Content(
            scan_only=choice_option(spec, "content", ("all", "scan"), "all") == "scan",
            cliff_scan=bool_option(spec, "cliff_scan", True),
            ranges_mm=choice_option(spec, "ranges", ("m", "mm"), "m") == "mm",
            every=int(number_option(spec, "every", 1, 1, 1_000_000, integer=True)),
            rate_hz=number_option(spec, "rate", 0.0, 0.0, 1000.0),
        )
        return cls(spec.text, host, port, max_bytes, content)

    def open(self, context: SinkContext) -> None:
        """Resolve the address and make a connected, non-blocking UDP socket.

        Raises:
            SinkError: the host does not resolve or the socket cannot be made.
        """
        self._version = context.version
        self._range_min_m = max(float(context.scan_params.range_min_m), 0.0)
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
        sock = self._sock
        if sock is None:
            raise SinkError(f"sink {self.name!r} is not open")
        if not self._every_frame and not self._due(result.timestamp_s):
            return
        data: bytes | memoryview | None
        if self._whole:
            # the whole object: the line the stdout sink writes too, made once (frame_line),
            # without its newline (a view: no copy)
            data = memoryview(json_line.frame_line(frame, result, self._version, time.time()))[:-1]
            if len(data) > self.max_bytes:
                data = json_line.fit_message(
                    frame, result, self._version, time.time(), self.max_bytes
                )
        else:
            data = json_line.fit_message(
                frame, result, self._version, time.time(), self.max_bytes, self.content.shape
            )
        if data is None:
            self._refuse_if_nothing_fits(frame, result)
            self._oversize.failed(
                "udp sink: frame %d does not fit one %d-byte datagram; skipped (raise max_bytes, "
                "or slim it with content=scan or cliff_scan=0)",
                result.seq,
                self.max_bytes,
            )
            return
        try:
            try:
                sock.send(data)
            except ConnectionRefusedError:
                # the ICMP error belongs to an earlier datagram and was reported instead of sending
                # this one: count it and try once more, so a receiver that came back gets this frame
                self._send_errors.failed(
                    "udp sink: %s:%d is not receiving (ConnectionRefusedError)",
                    self.host,
                    self.port,
                )
                sock.send(data)
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

    def _refuse_if_nothing_fits(self, frame: Frame, result: Result) -> None:
        """Raise when no frame of this scan layout can fit ``max_bytes`` (checked once a layout,
        on the first frame that does not fit): every frame would be skipped, quietly useless.

        Raises:
            SinkError: with the bytes this frame needs and the least any frame needs.
        """
        msg = frame_message(frame, result, self._version, time.time(), max_cliff_points=0)
        msg = self.content.shape(msg)
        layout = (len(result.scan.ranges), None if result.cliff is None else result.cliff.scan)
        key = (layout[0], 0 if layout[1] is None else len(layout[1].ranges))
        if key in self._fits_some:
            return
        least = len(orjson.dumps(self._least_message(msg)))
        if least <= self.max_bytes:
            self._fits_some.add(key)
            return
        raise SinkError(
            f"udp sink: max_bytes={self.max_bytes} is too small for any frame of this camera: "
            f"this one needs {len(orjson.dumps(msg))} bytes without its cliff points, and even "
            f"its {key[0]} scan ranges with every value at its shortest (a range_min reading) "
            f"take {least}",
            hint="raise max_bytes (up to 65507), or slim the datagram with content=scan, "
            "cliff_scan=0 or ranges=mm",
        )

    def _least_message(self, msg: dict[str, Any]) -> dict[str, Any]:
        """``msg`` as the fewest bytes a frame of its scan layout can take: every text empty,
        every number 0, every scan range the shortest it can be written (null, or range_min:
        ``0.5`` takes 3 bytes in metres, 450 mm 3), the lists as long."""
        least = _least(msg)
        if self.content.ranges_mm:
            shortest = 10 ** (min(len(str(int(self._range_min_m * 1000))), 4) - 1)
        else:
            shortest = 0.5  # any finite range in metres takes 3 bytes or more ("1.0")
        scan = least.get("scan")
        if isinstance(scan, dict) and isinstance(scan.get("ranges"), list):
            scan["ranges"] = [shortest] * len(scan["ranges"])
        return least

    def _due(self, t_s: float) -> bool:
        """Whether this frame goes out under ``every`` and ``rate`` (sensor time, seconds)."""
        self._frames += 1
        if (self._frames - 1) % self.content.every:
            return False
        rate = self.content.rate_hz
        if rate > 0 and self._last_sent_t is not None:
            # a little slack: frames 33.3 ms apart still make 10 Hz out of 30
            if 0 <= t_s - self._last_sent_t < 1.0 / rate - 1e-3:
                return False
        self._last_sent_t = t_s
        return True

    def close(self) -> None:
        """Close the socket. Safe to call twice."""
        sock, self._sock = self._sock, None
        if sock is not None:
            sock.close()
            too_big = self._oversize.count
            if too_big:
                # every skipped frame was also logged (rate-limited); the summary says how many
                log.warning(
                    "udp sink %s: %d frames sent, %d skipped as larger than max_bytes=%d",
                    self.name,
                    self.sent,
                    too_big,
                    self.max_bytes,
                )
            if self.send_errors:
                log.info(
                    "udp sink %s: %d sent, %d send errors", self.name, self.sent, self.send_errors
                )


@dataclass(frozen=True, slots=True, kw_only=True)
class Content:
    """What each datagram holds and how often one goes out (see the module docstring)."""

    scan_only: bool = False
    cliff_scan: bool = True
    ranges_mm: bool = False
    every: int = 1
    rate_hz: float = 0.0

    @property
    def whole(self) -> bool:
        """Whether each datagram holds the whole stdout object (``shape`` changes nothing)."""
        return not self.scan_only and self.cliff_scan and not self.ranges_mm

    def shape(self, msg: dict[str, Any]) -> dict[str, Any]:
        """The stdout object cut down to this content (the object is made anew per frame)."""
        if self.scan_only:
            msg = {k: msg[k] for k in SCAN_ONLY_KEYS if k in msg}
            if isinstance(msg.get("pose"), dict):
                msg["pose"] = {k: v for k, v in msg["pose"].items() if k != "estimate"}
        cliff = msg.get("cliff")
        if isinstance(cliff, dict) and not self.cliff_scan:
            cliff.pop("scan", None)
        if self.ranges_mm:
            for scan in (msg.get("scan"), (cliff or {}).get("scan") if cliff else None):
                if isinstance(scan, dict):
                    scan["ranges"] = [_mm(r) for r in scan["ranges"]]
                    scan["ranges_unit"] = "mm"
        return msg


SCAN_ONLY_KEYS = (
    "v",
    "version",
    "seq",
    "t_s",
    "wall_s",
    "scan",
    "pose",
    "mount",
    "warning",
    "message",
)


def _least(value: Any) -> Any:
    """A message with every value at its shortest JSON form, its lists as long (a frame of the
    same scan layout can take no fewer bytes): numbers and null 0, texts empty."""
    if isinstance(value, dict):
        return {k: _least(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_least(v) for v in value]
    if isinstance(value, str):
        return ""
    if isinstance(value, bool):
        return value
    return 0


def _mm(r: float | str | None) -> int | str | None:
    """A JSON range in metres (or its REP 117 marker) as integer millimetres."""
    return round(r * 1000) if isinstance(r, float | int) else r
