"""Odometry as JSON lines over UDP on loopback, for any robot software.

Spec: ``odom+udp://127.0.0.1:PORT[?clock=arrival|message]`` (the host must be a loopback address:
odometry steers the memory, so it is never taken from the network).

Each datagram holds one or more lines, each one JSON object::

    {"t_s": 12.50, "x_m": 1.204, "y_m": -0.031, "yaw_rad": 0.0523}

x, y in metres and yaw in radians (counter-clockwise) of the robot's base frame in its odometry
frame (REP 105 ``odom``). ``t_s`` is the pose's time in seconds: with ``clock=message`` it is
matched against the frames' timestamps (send the same clock as the depth frames); with
``clock=arrival`` (the default) the host's arrival time is used and ``t_s`` is optional (checked
when given). Values must be within the odometry limits (drivers.base: |x_m|, |y_m| <= 1e7 m,
|yaw_rad| <= 1e6 rad, |t_s| <= 1e10 s). Each line is handled in its own guard: a line that is not
such an object (not JSON, nested too deeply, a 400-digit number, NaN, ...) is refused, counted per
kind and reported (drivers.odometry.OdomRefusals), and the receiver goes on with the next line. If
the receiving loop itself fails (a bug), it says so and starts again.
"""

from __future__ import annotations

import ipaddress
import json
import logging
import socket
import threading
from typing import Any

from drivers.errors import DeviceOpenError, DeviceSpecError, OpenFailure
from drivers.odometry import OdomBuffer, OdomRefusal, OdomRefusals, check_sample, now_s
from drivers.spec import check_options, choice_option, parse_spec
from drivers.values import short_repr, short_text

log = logging.getLogger(__name__)

GRAMMAR = "odom+udp://127.0.0.1:PORT[?clock=arrival|message]"
MAX_DATAGRAM = 65535
POLL_S = 0.2
RESTART_PAUSE_S = 0.5  # after the receiving loop failed, before it starts again
RESTARTS_SAID, RESTARTS_SAID_EVERY = 3, 100  # the first restarts are said, then every 100th


class OdometryLineError(ValueError):
    """A line that is not an odometry sample; ``kind`` is one of ODOM_REFUSAL_KINDS."""

    def __init__(self, kind: str, reason: str) -> None:
        super().__init__(reason)
        self.kind = kind


def parse_odometry_line(line: bytes, need_time: bool) -> tuple[float | None, float, float, float]:
    """(t_s or None, x_m, y_m, yaw_rad) from one JSON line, checked against the odometry limits
    (yaw wrapped to [-pi, pi]).

    Raises:
        OdometryLineError: not a JSON object with numbers x_m, y_m, yaw_rad (and t_s when
            ``need_time``, or when given) within the limits; the message names the field and
            value, ``kind`` the class of problem.
    """
    try:
        obj: Any = json.loads(line)
    except RecursionError:  # [[[...]]] 60,000 deep: the parser's own recursion limit
        raise OdometryLineError("malformed", "not JSON (nested too deeply)") from None
    except ValueError as exc:  # JSONDecodeError, UnicodeDecodeError, over 4300 digits
        why = exc.msg if isinstance(exc, json.JSONDecodeError) else short_text(str(exc), 60)
        raise OdometryLineError("malformed", f"not JSON ({why})") from None
    if not isinstance(obj, dict):
        raise OdometryLineError("malformed", f"not a JSON object but {type(obj).__name__}")
    t = obj.get("t_s")
    # the values given first (a bad one is named even when another is missing), then the gaps
    sample = check_sample(
        0.0 if t is None else t, obj.get("x_m", 0.0), obj.get("y_m", 0.0), obj.get("yaw_rad", 0.0)
    )
    if isinstance(sample, OdomRefusal):
        raise OdometryLineError(sample.kind, sample.reason)
    for key in ("x_m", "y_m", "yaw_rad", "t_s"):
        if key not in obj and (key != "t_s" or need_time):
            raise OdometryLineError("malformed", f"{key} is missing")
    return (None if t is None else sample.t_s), sample.x_m, sample.y_m, sample.yaw_rad


class UdpJsonOdometry:
    """Receives JSON odometry lines on a loopback UDP port in a background thread."""

    def __init__(self, host: str, port: int, clock: str = "arrival", name: str = "") -> None:
        self.host, self.port = host, port
        self.uses_arrival_clock = clock == "arrival"
        self.name = name or f"odom+udp://{host}:{port}"
        self.buffer = OdomBuffer()
        self.refusals = OdomRefusals(self.name)
        self.restarts = 0  # times the receiving loop failed and started again
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
        self._thread = threading.Thread(
            target=self._serve, name=f"odometry {self.name}", daemon=True
        )
        self._thread.start()

    @property
    def bad_messages(self) -> int:
        """Lines refused so far, every kind."""
        return self.refusals.total

    def _serve(self) -> None:
        """The thread: the receiving loop, started again (after a pause) if it ever fails, so one
        bug costs a datagram, not the odometry."""
        while not self._stop.is_set():
            try:
                self._run()
                return
            except Exception as exc:  # a bug: every line has its own guard
                if self._stop.is_set():
                    return
                self.restarts += 1
                if self.restarts <= RESTARTS_SAID or self.restarts % RESTARTS_SAID_EVERY == 0:
                    log.error(
                        "odometry %s: the receiver failed (%s: %s); starting it again "
                        "[%d restarts]",
                        self.name,
                        type(exc).__name__,
                        short_text(str(exc), 80),
                        self.restarts,
                    )
                self._stop.wait(RESTART_PAUSE_S)

    def _run(self) -> None:
        while not self._stop.is_set():
            data = self._receive()
            if data is None:
                continue  # nothing within the poll interval, or stopped
            arrival = now_s()
            for line in data.splitlines():
                if not line.strip():
                    continue
                try:  # each line in its own guard: nothing a sender writes ends the receiver
                    self._take(line, arrival)
                except Exception as exc:
                    self.refusals.note(
                        OdomRefusal(
                            "malformed",
                            f"the line could not be read ({type(exc).__name__}): "
                            f"{short_repr(line[:40])}",
                        )
                    )

    def _receive(self) -> bytes | None:
        """One datagram, or None after the poll interval or once the socket is closed."""
        sock = self._sock
        if sock is None:
            return None
        try:
            return sock.recv(MAX_DATAGRAM)
        except TimeoutError:
            return None
        except OSError:
            if not self._stop.is_set():
                raise  # not closed by stop(): the loop reports it and starts again
            return None

    def _take(self, line: bytes, arrival: float) -> None:
        try:
            t, x, y, yaw = parse_odometry_line(line, need_time=not self.uses_arrival_clock)
        except OdometryLineError as exc:
            self.refusals.note(OdomRefusal(exc.kind, f"{exc}, in line {short_repr(line[:40])}"))
            return
        refused = self.buffer.offer(arrival if self.uses_arrival_clock else t, x, y, yaw)
        if refused is not None:
            self.refusals.note(refused)

    def stop(self) -> None:
        """Stop the thread and close the socket. Safe to call twice."""
        self._stop.set()
        if self._sock is not None:
            self._sock.close()
        if self._thread is not None:
            self._thread.join(timeout=2.0)
            self._thread = None
        self._sock = None
        self.refusals.flush()
