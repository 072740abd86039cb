"""Tilt and roll from an external IMU on a serial port, for sensors without an accelerometer.

Spec (for configs): ``serialtilt:PORT[?protocol=line|mavlink&baud=N]`` where PORT is a device path
(``/dev/ttyUSB0``) or any pyserial URL (``socket://host:port``, ``loop://``).

Protocols:
- ``line`` (default): NMEA-like ASCII lines ``$TILT,<tilt_deg>,<roll_deg>*HH\\r\\n``, where HH is
  the XOR of the bytes between ``$`` and ``*`` as two hex digits. The values use depthnav's signs:
  tilt positive = sensor pitched DOWN, roll positive = left side UP.
  Example: ``$TILT,15.0,-2.5*1B``.
- ``mavlink``: MAVLink 1/2 ``ATTITUDE`` (id 30) from an autopilot, via pymavlink. ATTITUDE is in
  radians in the vehicle's FRD body frame: pitch positive = nose UP, roll positive = right side
  down. So tilt_deg = -degrees(pitch) and roll_deg = +degrees(roll), for an IMU whose forward axis
  is the camera's optical axis; add the camera's mount pitch yourself.

Readings are host-timestamped (``time.monotonic()``) when the line or message arrives.
"""

from __future__ import annotations

import logging
import math
import re
import threading
import time
from types import TracebackType
from typing import Any

from drivers.errors import DeviceLost, DeviceOpenError, DeviceSpecError, DriverError, OpenFailure
from drivers.spec import check_options, choice_option, int_option, parse_spec
from drivers.tilt import TiltReading

log = logging.getLogger(__name__)

GRAMMAR = "serialtilt:PORT[?protocol=line|mavlink&baud=N]"
LINE = re.compile(rb"\$(TILT,([-+]?\d+(?:\.\d*)?),([-+]?\d+(?:\.\d*)?))\*([0-9A-Fa-f]{2})")
MAX_LINE = 128
MAVLINK_ATTITUDE = 30
MAX_TILT_DEG, MAX_ROLL_DEG = 90.0, 180.0  # a reading outside is garbled


def nmea_checksum(body: bytes) -> int:
    """XOR of the bytes between ``$`` and ``*``."""
    value = 0
    for byte in body:
        value ^= byte
    return value


def format_line(tilt_deg: float, roll_deg: float) -> bytes:
    """A ``$TILT`` line with its checksum, e.g. for a microcontroller test rig."""
    body = f"TILT,{tilt_deg:.2f},{roll_deg:.2f}".encode()
    return b"$" + body + b"*" + f"{nmea_checksum(body):02X}".encode() + b"\r\n"


def parse_line(line: bytes) -> tuple[float, float] | None:
    """(tilt_deg, roll_deg) from one ``$TILT`` line; None if malformed or the checksum is wrong."""
    match = LINE.fullmatch(line.strip())
    if match is None:
        return None
    if nmea_checksum(match.group(1)) != int(match.group(4), 16):
        return None
    tilt, roll = float(match.group(2)), float(match.group(3))
    if abs(tilt) > MAX_TILT_DEG or abs(roll) > MAX_ROLL_DEG:
        return None
    return tilt, roll


def attitude_to_tilt_roll(pitch_rad: float, roll_rad: float) -> tuple[float, float]:
    """MAVLink ATTITUDE (nose-up pitch, right-down roll, radians) to (tilt_deg, roll_deg)."""
    return -math.degrees(pitch_rad), math.degrees(roll_rad)


class SerialTiltSource:
    """Reads attitude from a serial port in a background thread.

    Args:
        port: device path or pyserial URL.
        protocol: "line" or "mavlink".
        baudrate: serial speed (ignored by ptys and sockets).
    """

    def __init__(self, port: str, protocol: str = "line", baudrate: int = 115200) -> None:
        if protocol not in ("line", "mavlink"):
            raise DeviceSpecError(f"serial tilt protocol {protocol!r} is not line or mavlink")
        self.port = port
        self.protocol = protocol
        self.baudrate = baudrate
        self.bad_messages = 0
        self._latest: TiltReading | None = None
        self._error: DriverError | None = None
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._serial: Any = None

    @classmethod
    def from_spec(cls, text: str) -> SerialTiltSource:
        """Build from ``serialtilt:PORT?protocol=..&baud=..``."""
        spec = parse_spec(text)
        if spec.scheme != "serialtilt" or not spec.target:
            raise DeviceSpecError(f"{text!r} is not a serial tilt spec", hint=f"write {GRAMMAR}")
        check_options(spec, ("protocol", "baud"), GRAMMAR)
        return cls(
            spec.target,
            choice_option(spec, "protocol", ("line", "mavlink"), "line"),
            int_option(spec, "baud", 115200, 50, 4_000_000),
        )

    def start(self) -> None:
        """Open the port and start the reader thread.

        Raises:
            DeviceOpenError: the port cannot be opened.
        """
        import serial

        try:
            self._serial = serial.serial_for_url(self.port, baudrate=self.baudrate, timeout=0.1)
        except (serial.SerialException, ValueError, OSError) as exc:
            raise DeviceOpenError(
                f"cannot open serial port {self.port}: {exc}",
                hint="check the port name and that you are in group dialout",
                reason=OpenFailure.NOT_FOUND,
            ) from None
        self._stop.clear()
        self._thread = threading.Thread(
            target=self._run, name=f"serial-tilt {self.port}", daemon=True
        )
        self._thread.start()

    def _publish(self, tilt_deg: float, roll_deg: float) -> None:
        with self._lock:
            self._latest = TiltReading(tilt_deg, roll_deg, time.monotonic())

    def _run(self) -> None:
        import serial

        feed = self._line_feeder() if self.protocol == "line" else self._mavlink_feeder()
        try:
            while not self._stop.is_set():
                data = self._serial.read(256)
                if data:
                    feed(data)
        except (serial.SerialException, OSError) as exc:
            if not self._stop.is_set():
                with self._lock:
                    self._error = DeviceLost(
                        f"serial tilt source {self.port} stopped: {exc}",
                        hint="check the cable and the IMU's power",
                    )
                log.warning("serial tilt source %s stopped: %s", self.port, exc)

    def _line_feeder(self) -> Any:
        buffer = bytearray()

        def feed(data: bytes) -> None:
            buffer.extend(data)
            while b"\n" in buffer:
                line, _, rest = bytes(buffer).partition(b"\n")
                buffer[:] = rest
                parsed = parse_line(line)
                if parsed is None:
                    if line.strip():
                        self.bad_messages += 1
                        log.debug("ignoring serial tilt line %r", line[:MAX_LINE])
                    continue
                self._publish(*parsed)
            if len(buffer) > MAX_LINE:  # no newline in sight: noise, drop it
                self.bad_messages += 1
                del buffer[:-MAX_LINE]

        return feed

    def _mavlink_feeder(self) -> Any:
        from pymavlink.dialects.v20 import common as mavlink2

        parser = mavlink2.MAVLink(None)
        parser.robust_parsing = True  # bad bytes become MAVLink_bad_data instead of exceptions

        def feed(data: bytes) -> None:
            try:
                messages = parser.parse_buffer(data) or []
            except mavlink2.MAVError as exc:
                self.bad_messages += 1
                log.debug("bad MAVLink data: %s", exc)
                return
            for msg in messages:
                if msg.get_msgId() == MAVLINK_ATTITUDE:
                    # the same bounds as the line protocol: a pitch beyond +-90 deg or a roll
                    # beyond +-180 deg is a corrupt or misconfigured message, not an attitude
                    if (
                        math.isfinite(msg.pitch)
                        and math.isfinite(msg.roll)
                        and abs(msg.pitch) <= math.pi / 2
                        and abs(msg.roll) <= math.pi
                    ):
                        self._publish(*attitude_to_tilt_roll(msg.pitch, msg.roll))
                    else:
                        self.bad_messages += 1
                elif msg.get_type() == "BAD_DATA":
                    self.bad_messages += 1

        return feed

    def latest(self, max_age_s: float | None = None) -> TiltReading | None:
        """The newest reading, or None if there is none (or it is older than ``max_age_s``).

        Raises:
            DeviceLost: the reader thread stopped because the port failed.
        """
        with self._lock:
            if self._error is not None:
                raise self._error
            reading = self._latest
        if (
            reading is not None
            and max_age_s is not None
            and time.monotonic() - reading.timestamp_s > max_age_s
        ):
            return None
        return reading

    def stop(self) -> None:
        """Stop the thread and close the port. Safe to call twice."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=2.0)
            self._thread = None
        if self._serial is not None:
            try:
                self._serial.close()
            except Exception:  # closing must not raise
                log.debug("closing %s failed", self.port, exc_info=True)
            self._serial = None

    def __enter__(self) -> SerialTiltSource:
        self.start()
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.stop()
