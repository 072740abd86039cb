"""Odometry from an autopilot over MAVLink (ArduPilot, PX4), via pymavlink.

Specs: ``mavlink+udp://HOST:PORT`` (listen for the autopilot's UDP stream, e.g. from
mavlink-router; HOST defaults to 127.0.0.1) or ``mavlink:SERIALPORT[?baud=N]`` (default 57600).

Messages: ``ODOMETRY`` (331) in MAV_FRAME_LOCAL_NED (1), LOCAL_FRD (20) or LOCAL_FLU (21); or
``LOCAL_POSITION_NED`` (32) with the yaw of the latest ``ATTITUDE`` (30). The autopilot's local
frames are NED/FRD (x north or forward, y east or right, yaw clockwise); depthnav's odometry frame
is REP 103 (y left, yaw counter-clockwise), so y and yaw change sign (FLU is taken as is).
Samples are timed by their arrival on this host (the autopilot's boot clock is another clock).
A message with values outside the odometry limits (drivers.base: |x|, |y| <= 1e7 m, |yaw| <= 1e6
rad, finite), from another frame or that cannot be read is refused and counted per kind
(drivers.odometry.OdomRefusals); the reader goes on with the next message.
"""

from __future__ import annotations

import logging
import math
import threading
from typing import Any

from drivers.base import check_odom_pose
from drivers.errors import DeviceOpenError, DeviceSpecError, OpenFailure
from drivers.odometry import OdomBuffer, OdomRefusal, OdomRefusals, now_s
from drivers.spec import check_options, int_option, parse_spec
from drivers.values import short_repr, short_text

log = logging.getLogger(__name__)

GRAMMAR = "mavlink+udp://HOST:PORT or mavlink:SERIALPORT[?baud=N]"
MAV_FRAME_LOCAL_NED, MAV_FRAME_LOCAL_FRD, MAV_FRAME_LOCAL_FLU = 1, 20, 21
ATTITUDE_MAX_AGE_S = 0.5  # LOCAL_POSITION_NED uses an ATTITUDE yaw at most this old
POLL_S = 0.2


def quaternion_yaw(w: float, x: float, y: float, z: float) -> float:
    """Yaw (rotation about the frame's z axis) of a unit quaternion, radians."""
    return math.atan2(2.0 * (w * z + x * y), 1.0 - 2.0 * (y * y + z * z))


def ned_to_flu(x: float, y: float, yaw: float) -> tuple[float, float, float]:
    """A planar pose in a NED/FRD local frame -> REP 103 (y left, yaw counter-clockwise)."""
    return x, -y, -yaw


class MavlinkOdometry:
    """Reads an autopilot's local position and heading in a background thread."""

    uses_arrival_clock = True

    def __init__(self, connection: str, baud: int = 57600, name: str = "") -> None:
        self.connection = connection
        self.baud = baud
        self.name = name or connection
        self.buffer = OdomBuffer()
        self.refusals = OdomRefusals(self.name)
        self._yaw: tuple[float, float] | None = None  # (yaw NED rad, arrival s)
        self._conn: Any = None
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    @classmethod
    def from_spec(cls, text: str) -> MavlinkOdometry:
        spec = parse_spec(text, "odometry")
        if spec.scheme == "mavlink+udp":
            check_options(spec, (), GRAMMAR)
            host, _, port = spec.target.rpartition(":")
            if not port.isdigit() or not 1 <= int(port) <= 65535:  # noqa: PLR2004
                raise DeviceSpecError(f"odometry spec {text!r} needs a port 1..65535", hint=GRAMMAR)
            return cls(f"udpin:{host or '127.0.0.1'}:{port}", name=text)
        check_options(spec, ("baud",), GRAMMAR)
        if not spec.target:
            raise DeviceSpecError(f"odometry spec {text!r} names no serial port", hint=GRAMMAR)
        return cls(spec.target, int_option(spec, "baud", 57600, 50, 4_000_000), text)

    def start(self) -> None:
        """Open the link and start the reader thread.

        Raises:
            DeviceOpenError: pymavlink missing, or the port or address cannot be opened.
        """
        try:
            from pymavlink import mavutil
        except ModuleNotFoundError:
            raise DeviceOpenError(
                "MAVLink odometry needs the 'pymavlink' package", hint="pip install pymavlink"
            ) from None
        try:
            self._conn = mavutil.mavlink_connection(self.connection, baud=self.baud)
        except Exception as exc:  # serial.SerialException, OSError, ...: one line
            raise DeviceOpenError(
                f"odometry {self.name}: cannot open {self.connection}: {exc}",
                hint="check the address or port",
                reason=OpenFailure.NOT_FOUND,
            ) from None
        self._stop.clear()
        self._thread = threading.Thread(target=self._run, name=f"odometry {self.name}", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        types = ["ODOMETRY", "LOCAL_POSITION_NED", "ATTITUDE"]
        while not self._stop.is_set():
            try:
                msg = self._conn.recv_match(type=types, blocking=True, timeout=POLL_S)
            except Exception as exc:  # the port went away
                if not self._stop.is_set():
                    log.warning("odometry %s stopped: %s", self.name, exc)
                return
            if msg is None:
                continue
            try:  # each message in its own guard: nothing the autopilot sends ends the reader
                self.take(msg, now_s())
            except Exception as exc:
                self._refuse("malformed", f"cannot be read ({type(exc).__name__})", msg)

    @property
    def bad_messages(self) -> int:
        """Messages refused so far, every kind."""
        return self.refusals.total

    def take(self, msg: Any, arrival: float) -> None:
        """Fold one decoded message into the buffer."""
        kind = msg.get_type()
        if kind == "ATTITUDE":
            checked = check_odom_pose(0.0, 0.0, msg.yaw)
            if isinstance(checked, OdomRefusal):
                self._refuse(checked.kind, checked.reason, msg)
            else:
                self._yaw = (checked[2], arrival)
            return
        if kind == "ODOMETRY":
            if msg.frame_id not in (MAV_FRAME_LOCAL_NED, MAV_FRAME_LOCAL_FRD, MAV_FRAME_LOCAL_FLU):
                self._refuse("malformed", f"frame {short_repr(msg.frame_id)} is not local", msg)
                return
            yaw = quaternion_yaw(*msg.q)
            pose = (msg.x, msg.y, yaw)
            if msg.frame_id != MAV_FRAME_LOCAL_FLU:
                pose = ned_to_flu(*pose)
        else:  # LOCAL_POSITION_NED
            if self._yaw is None or arrival - self._yaw[1] > ATTITUDE_MAX_AGE_S:
                return  # no heading yet: wait for ATTITUDE
            pose = ned_to_flu(msg.x, msg.y, self._yaw[0])
        refused = self.buffer.offer(arrival, *pose)
        if refused is not None:
            self.refusals.note(OdomRefusal(refused.kind, f"{kind}: {refused.reason}"))

    def _refuse(self, kind: str, reason: str, msg: Any) -> None:
        try:
            name = short_text(str(msg.get_type()), 40)
        except Exception:  # a message that cannot even name itself
            name = "a message"
        self.refusals.note(OdomRefusal(kind, f"{name}: {reason}"))

    def stop(self) -> None:
        """Stop the thread and close the link. Safe to call twice."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=2.0)
            self._thread = None
        if self._conn is not None:
            try:
                self._conn.close()
            except Exception:  # closing must not raise
                log.debug("closing %s failed", self.name, exc_info=True)
            self._conn = None
        self.refusals.flush()
