"""Odometry as JSON lines over UDP on loopback, for any robot software.

Spec: ``odom+udp://127.0.0.1:PORT[?clock=arrival|message]`` (the host must be a loopback address:
odometry steers the memory, so it is never taken from the network).

Each datagram holds one or more lines, each one JSON object::

    {"t_s": 12.50, "x_m": 1.204, "y_m": -0.031, "yaw_rad": 0.0523}

x, y in metres and yaw in radians (counter-clockwise) of the robot's base frame in its odometry
frame (REP 105 ``odom``). ``t_s`` is the pose's time in seconds: with ``clock=message`` it is
matched against the frames' timestamps (send the same clock as the depth frames); with
``clock=arrival`` (the default) the host's arrival time is used and ``t_s`` is optional. A line
that is not such an object is counted and reported (the first one, then every 100th), never fatal.
"""

from __future__ import annotations

import ipaddress
import json
import logging
import math
import socket
import threading
from typing import Any

from drivers.errors import DeviceOpenError, DeviceSpecError, OpenFailure
from drivers.odometry import OdomBuffer, now_s
from drivers.spec import check_options, choice_option, parse_spec

log = logging.getLogger(__name__)

GRAMMAR = "odom+udp://127.0.0.1:PORT[?clock=arrival|message]"
MAX_DATAGRAM = 65535
POLL_S = 0.2
REPORT_EVERY = 100


def parse_odometry_line(line: bytes, need_time: bool) -> tuple[float | None, float, float, float]:
    """(t_s or None, x_m, y_m, yaw_rad) from one JSON line.

    Raises:
        ValueError: not a JSON object with finite numbers x_m, y_m, yaw_rad (and t_s when
            ``need_time``); the message says which.
    """
    try:
        obj: Any = json.loads(line)
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise ValueError(f"not JSON ({exc.msg if hasattr(exc, 'msg') else exc})") from None
    if not isinstance(obj, dict):
        raise ValueError("not a JSON object")
    values = []
    for key in ("x_m", "y_m", "yaw_rad", "t_s"):
        v = obj.get(key)
        if v is None and key == "t_s" and not need_time:
            values.append(None)
            continue
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
            raise ValueError(f"{key}={v!r} is not a finite number")
        values.append(float(v))
    x, y, yaw, t = values
    return t, x, y, yaw  # type: ignore[return-value]


class UdpJsonOdometry:
    """Receives JSON odometry lines on a loopback UDP port in a background thread."""

    def __init__(self, host: str, port: int, clock: str = "arrival", name: str = "") -> None:
        self.host, self.port = host, port
        self.uses_arrival_clock = clock == "arrival"
        self.name = name or f"odom+udp://{host}:{port}"
        self.buffer = OdomBuffer()
        self.bad_messages = 0
        self._sock: socket.socket | None = None
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    @classmethod
    def from_spec(cls, text: str) -> UdpJsonOdometry:
        spec = parse_spec(text, "odometry")
        check_options(spec, ("clock",), GRAMMAR)
        host, _, port_text = spec.target.rpartition(":")
        host = host.strip("[]") or "127.0.0.1"
        try:
            port = int(port_text)
        except ValueError:
            port = -1
        if not 1 <= port <= 65535:  # noqa: PLR2004
            raise DeviceSpecError(f"odometry spec {text!r} needs a port 1..65535", hint=GRAMMAR)
        try:
            loopback = host == "localhost" or ipaddress.ip_address(host).is_loopback
        except ValueError:
            loopback = False
        if not loopback:
            raise DeviceSpecError(
                f"odometry spec {text!r}: {host} is not a loopback address",
                hint="odometry is only taken from this machine: use 127.0.0.1",
            )
        clock = choice_option(spec, "clock", ("arrival", "message"), "arrival")
        return cls(host, port, clock, text)

    def start(self) -> None:
        """Bind the port and start the reader thread.

        Raises:
            DeviceOpenError: the port cannot be bound (in use, no permission).
        """
        family = socket.AF_INET6 if ":" in self.host else socket.AF_INET
        sock = socket.socket(family, socket.SOCK_DGRAM)
        try:
            sock.bind((self.host, self.port))
        except OSError as exc:
            sock.close()
            raise DeviceOpenError(
                f"odometry {self.name}: cannot listen on {self.host}:{self.port}: {exc.strerror}",
                hint="choose a free port",
                reason=OpenFailure.BUSY,
            ) from None
        sock.settimeout(POLL_S)
        self._sock = sock
        self._stop.clear()
        self._thread = threading.Thread(target=self._run, name=f"odometry {self.name}", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        assert self._sock is not None
        while not self._stop.is_set():
            try:
                data = self._sock.recv(MAX_DATAGRAM)
            except TimeoutError:
                continue
            except OSError:
                return  # closed by stop()
            arrival = now_s()
            for line in data.splitlines():
                if line.strip():
                    self._take(line, arrival)

    def _take(self, line: bytes, arrival: float) -> None:
        try:
            t, x, y, yaw = parse_odometry_line(line, need_time=not self.uses_arrival_clock)
            ok = self.buffer.add(arrival if self.uses_arrival_clock else t, x, y, yaw)  # type: ignore[arg-type]
            if not ok:
                raise ValueError("t_s goes back in time")
        except ValueError as exc:
            self.bad_messages += 1
            if self.bad_messages % REPORT_EVERY == 1:
                log.warning(
                    "odometry %s: ignoring a line (%s): %r [%d bad so far]",
                    self.name,
                    exc,
                    line[:80],
                    self.bad_messages,
                )

    def stop(self) -> None:
        """Stop the thread and close the socket. Safe to call twice."""
        self._stop.set()
        if self._sock is not None:
            self._sock.close()
        if self._thread is not None:
            self._thread.join(timeout=2.0)
            self._thread = None
        self._sock = None
