"""``mavlink``: OBSTACLE_DISTANCE (72 sectors) and HEARTBEAT for ArduPilot / PX4 avoidance.

Specs:
    ``mavlink:SERIALPORT[?baud=N&...]``      e.g. ``mavlink:/dev/ttyUSB0?baud=921600``
    ``mavlink+udp://HOST:PORT[?...]``        e.g. ``mavlink+udp://127.0.0.1:14550`` (the default)

Options (all optional):
    baud: serial only, bits per second (default 57600, ArduPilot's SERIALn_BAUD default).
    rate: OBSTACLE_DISTANCE messages per second, 1..50 (default 10). The newest scan is sent at this
        rate from a thread, decoupled from the frame rate; a scan older than ``stale`` is not
        repeated, so the autopilot times out (ArduPilot: 500 ms) instead of trusting old data.
    stale: seconds a scan may be repeated (default 0.5).
    sysid, compid: MAVLink source system / component (default 1 / 196,
        MAV_COMP_ID_OBSTACLE_AVOIDANCE).
    sensor: laser | ultrasound | infrared | radar | unknown (default infrared: structured light,
        ToF).
    cliff: 1 = also report drop-offs (the cliff scan) as obstacles, sector-wise minimum (default 0).
    untrusted_dropoffs: send | drop (default send). While the daemon does not trust the mount
        (the floor contradicts it, or the built-in default mount is unconfirmed), drop-offs may
        be the floor itself seen through a wrong mount. ``send`` still reports them (a real
        drop-off is never hidden: the vehicle stops rather than falls); ``drop`` leaves them out
        of OBSTACLE_DISTANCE until the mount is trusted again (obstacles are still sent).

Mount trust: a STATUSTEXT (MAV_SEVERITY_WARNING) is sent once when the mount becomes untrusted,
saying why and what happens to drop-offs, e.g. "depthnav: floor contradicts mount, cliffs sent",
and one (MAV_SEVERITY_INFO) "depthnav: mount trusted again" when it is trusted again.

An unconfirmed mount (nobody configured it and the floor has not given it yet: the daemon does not
know where the floor is): OBSTACLE_DISTANCE keeps going out at ``rate`` with every sector unknown
(UINT16_MAX), whatever ``cliff`` and ``untrusted_dropoffs`` say, and a STATUSTEXT says "depthnav:
mount unconfirmed, sectors unknown"; "depthnav: mount confirmed by the floor" when it is found.
Sent rather than withheld: a silent sensor looks to the autopilot like a sensor that is gone
(ArduPilot times it out after 500 ms, PX4 after its own timeout), while unknown sectors say on
each bearing that nothing is known, which PX4's collision prevention treats as blocked unless
CP_GO_NO_DATA is set; ArduPilot skips unknown sectors, as it would a missing sensor, and the
STATUSTEXT tells the operator why.

Memory: when the obstacle memory is on (odometry available, result.memory with a scan), the
message is built from the 360 deg memory scan instead: 72 sectors of 5 deg all around the robot,
so the autopilot also sees what is in the sensors' dead zones, beside and behind; the memory holds
obstacles and drop-offs alike (``cliff`` is then moot). Otherwise (no odometry, or the memory is
frozen) it is built from the live scan as above. The memory keeps drop-offs whatever the mount
trust: ``untrusted_dropoffs=drop`` only applies to the live cliff scan.

Sectors (pinned by tests/sinks/test_mavlink.py): the 72 sectors split the scan's field of view
evenly. Our scan is counter-clockwise from forward (left positive, index 0 = right-most); MAVLink's
element 0 is the left-most sector and bearings grow clockwise (MAV_FRAME_BODY_FRD), so
``angle_offset`` (the centre of element 0) = -degrees(left edge of the scan) + increment_f / 2.
Each sector is the minimum over every scan bin whose footprint overlaps it (no resampling, so a
one-bin obstacle is never lost and a coarse scan leaves no holes). Per bin: a finite range ->
floor(cm) clipped to [min_distance, max_distance]; -inf (closer than range_min) -> min_distance;
+inf (no obstacle) -> max_distance + 1; NaN (no data) is skipped; a sector without any data ->
65535 (UINT16_MAX, "unknown").
"""

from __future__ import annotations

import dataclasses
import logging
import os
import socket
import threading
import time
from typing import TYPE_CHECKING, Any

import numpy as np

from depthnav_daemon.errors import ConfigError, SinkError
from depthnav_daemon.sinks.base import (
    RateLimitedLog,
    SinkContext,
    SinkSpec,
    bool_option,
    check_options,
    number_option,
    parse_host_port,
)
from depthnav_daemon.sinks.mavlink.sectors import (
    MAV_SEVERITY_INFO,
    MAV_SEVERITY_WARNING,
    UNKNOWN,
    Schedule,
    sectors_for,
    trust_statustext,
)

if TYPE_CHECKING:
    from depthnav_daemon.pipeline import MountTrust, Result
    from depthnav_daemon.sinks.mavlink.sectors import Sectors
    from drivers.base import Frame

log = logging.getLogger(__name__)

GRAMMAR = (
    "mavlink:SERIALPORT[?baud=N&rate=HZ&stale=S&sysid=N&compid=N&sensor=KIND&cliff=0|1"
    "&untrusted_dropoffs=send|drop] or "
    "mavlink+udp://HOST:PORT[?rate=HZ&stale=S&sysid=N&compid=N&sensor=KIND&cliff=0|1"
    "&untrusted_dropoffs=send|drop]"
)
COMMON_OPTIONS = ("rate", "stale", "sysid", "compid", "sensor", "cliff", "untrusted_dropoffs")
UNTRUSTED_DROPOFFS = ("send", "drop")
SENSOR_TYPES = {  # option value -> MAV_DISTANCE_SENSOR
    "laser": 0,
    "ultrasound": 1,
    "infrared": 2,
    "radar": 3,
    "unknown": 4,
}
MAV_COMP_ID_OBSTACLE_AVOIDANCE = 196
MAV_FRAME_BODY_FRD = 12
DEFAULT_UDP = ("127.0.0.1", 14550)
WRITE_TIMEOUT_S = 0.25  # serial write; a blocked port drops a message instead of stalling
JOIN_TIMEOUT_S = 0.8  # close(): WRITE_TIMEOUT_S plus margin, inside the daemon's 1 s stop
MESSAGE_BYTES = 180  # a packed MAVLink 2 OBSTACLE_DISTANCE, for the baud-rate check


class _SerialLink:
    """A serial port through pyserial; write failures other than timeouts are fatal."""

    def __init__(self, port: str, baud: int) -> None:
        try:
            import serial  # lazy: only this sink needs pyserial
        except ModuleNotFoundError as exc:
            raise SinkError(
                "the mavlink serial sink needs the 'pyserial' package", hint="pip install pyserial"
            ) from exc
        self._serial_mod = serial
        try:
            # a message takes ~30 ms at 57600 baud; waiting longer means the far end stopped reading
            # (drop it), and close() must still stop the thread within the daemon's 1 s budget
            self._port = serial.Serial(
                port, baudrate=baud, timeout=0, write_timeout=WRITE_TIMEOUT_S
            )
        except (serial.SerialException, OSError, ValueError) as exc:
            # pyserial repeats the path twice in its message: the errno's words say it all
            errno = getattr(exc, "errno", None)
            reason = os.strerror(errno) if isinstance(errno, int) and errno > 0 else str(exc)
            raise SinkError(
                f"mavlink sink: cannot open serial port {port!r}: {reason}",
                hint="check the port name and that your user is in the dialout group",
            ) from exc
        self._timeouts = RateLimitedLog(log)
        self.describe = f"serial {port} at {baud} baud"

    def write(self, data: bytes) -> None:
        try:
            self._port.write(data)
        except self._serial_mod.SerialTimeoutException:
            # the autopilot is not reading (flow control): drop, the next message is fresher anyway
            self._timeouts.failed("mavlink sink: serial write timed out on %s", self.describe)

    def close(self) -> None:
        self._port.close()


class _UdpLink:
    """A connected non-blocking UDP socket; send failures are counted, never raised."""

    def __init__(self, host: str, port: int) -> None:
        try:
            family, kind, proto, _, addr = socket.getaddrinfo(host, port, type=socket.SOCK_DGRAM)[0]
            self._sock = socket.socket(family, kind, proto)
            self._sock.setblocking(False)
            self._sock.connect(addr)
        except OSError as exc:
            raise SinkError(f"mavlink sink: cannot send to {host}:{port}: {exc}") from exc
        self._errors = RateLimitedLog(log)
        self.describe = f"udp {host}:{port}"

    def write(self, data: bytes) -> None:
        try:
            self._sock.send(data)
        except OSError as exc:  # receiver gone (ICMP), buffer full, network down
            self._errors.failed(
                "mavlink sink: datagram to %s dropped: %s", self.describe, type(exc).__name__
            )

    def close(self) -> None:
        self._sock.close()


class MavlinkSink:
    """Sends OBSTACLE_DISTANCE at a fixed rate and HEARTBEAT at 1 Hz from a background thread.

    ``write()`` only pools the scan into sectors and hands them over; the thread does the I/O, so a
    slow serial link never blocks the frame loop. A fatal link error in the thread is raised as
    SinkError by the next ``write()``.
    """

    def __init__(
        self,
        name: str,
        *,
        serial_port: str | None = None,
        baud: int = 57600,
        udp: tuple[str, int] | None = None,
        rate_hz: float = 10.0,
        stale_s: float = 0.5,
        sysid: int = 1,
        compid: int = MAV_COMP_ID_OBSTACLE_AVOIDANCE,
        sensor_type: int = SENSOR_TYPES["infrared"],
        cliff: bool = False,
        untrusted_dropoffs: str = "send",
    ) -> None:
        self.name = name
        self.serial_port, self.baud, self.udp = serial_port, baud, udp
        self.rate_hz, self.stale_s = rate_hz, stale_s
        self.sysid, self.compid, self.sensor_type, self.cliff = sysid, compid, sensor_type, cliff
        self.untrusted_dropoffs = untrusted_dropoffs
        # the last frame's (mount known, drop-offs trusted), None before the first frame
        self._trusted: tuple[bool, bool] | None = None
        self._texts: list[tuple[int, str]] = []  # STATUSTEXT (severity, text) for the thread
        self.sent_text = 0
        self._link: _SerialLink | _UdpLink | None = None
        self._mav: Any = None
        self._lock = threading.Lock()
        self._latest: tuple[Sectors, int, float] | None = (
            None  # sectors, time_usec, arrival (monotonic)
        )
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._error: BaseException | None = None
        self.sent_obstacle = 0
        self.sent_heartbeat = 0

    @classmethod
    def from_spec(cls, spec: SinkSpec) -> MavlinkSink:
        """Build from a parsed spec (no I/O). Raises ConfigError for bad targets or options."""
        kw: dict[str, Any] = {}
        if spec.scheme == "mavlink":
            check_options(spec, ("baud", *COMMON_OPTIONS), GRAMMAR)
            if not spec.target:
                raise ConfigError(
                    f"sink spec {spec.text!r} names no serial port",
                    hint="write mavlink:/dev/ttyUSB0?baud=57600 or mavlink+udp://HOST:PORT",
                )
            kw["serial_port"] = spec.target
            kw["baud"] = int(number_option(spec, "baud", 57600, 50, 4_000_000, integer=True))
        else:
            check_options(spec, COMMON_OPTIONS, GRAMMAR)
            kw["udp"] = parse_host_port(
                spec, DEFAULT_UDP[0], DEFAULT_UDP[1] if not spec.target else None
            )
        sensor = spec.options.get("sensor", "infrared").strip().lower()
        if sensor not in SENSOR_TYPES:
            raise ConfigError(
                f"option sensor={sensor!r} in {spec.text!r} is not one of {', '.join(SENSOR_TYPES)}"
            )
        untrusted = spec.options.get("untrusted_dropoffs", "send").strip().lower()
        if untrusted not in UNTRUSTED_DROPOFFS:
            raise ConfigError(
                f"option untrusted_dropoffs={untrusted!r} in {spec.text!r} is not one of "
                f"{', '.join(UNTRUSTED_DROPOFFS)}",
                hint="send: report drop-offs even while the mount is not trusted (the default); "
                "drop: leave them out then",
            )
        return cls(
            spec.text,
            **kw,
            rate_hz=number_option(spec, "rate", 10.0, 1.0, 50.0),
            stale_s=number_option(spec, "stale", 0.5, 0.05, 10.0),
            sysid=int(number_option(spec, "sysid", 1, 1, 255, integer=True)),
            compid=int(
                number_option(spec, "compid", MAV_COMP_ID_OBSTACLE_AVOIDANCE, 1, 255, integer=True)
            ),
            sensor_type=SENSOR_TYPES[sensor],
            cliff=bool_option(spec, "cliff", False),
            untrusted_dropoffs=untrusted,
        )

    def open(self, context: SinkContext) -> None:
        """Open the link, send a first HEARTBEAT and start the sender thread.

        Raises:
            SinkError: pymavlink missing, or the port / address cannot be opened.
        """
        try:
            from pymavlink.dialects.v20 import common as mavlink2  # lazy: a large generated module
        except ModuleNotFoundError as exc:
            raise SinkError(
                "the mavlink sink needs the 'pymavlink' package", hint="pip install pymavlink"
            ) from exc
        if self.serial_port is not None:
            self._link = _SerialLink(self.serial_port, self.baud)
            need = (self.rate_hz * MESSAGE_BYTES + 20) * 10  # 10 bits per byte on the wire
            if need > 0.8 * self.baud:
                log.warning(
                    "mavlink sink: %.0f Hz of OBSTACLE_DISTANCE needs about %.0f baud; "
                    "%d is too slow",
                    self.rate_hz,
                    need / 0.8,
                    self.baud,
                )
        else:
            assert self.udp is not None
            self._link = _UdpLink(*self.udp)
        self._mav = mavlink2.MAVLink(self._link, srcSystem=self.sysid, srcComponent=self.compid)
        self._stop.clear()
        self._thread = threading.Thread(target=self._run, name=f"sink {self.name}", daemon=True)
        self._thread.start()
        log.info(
            "mavlink sink: OBSTACLE_DISTANCE at %g Hz on %s (sysid %d, compid %d)",
            self.rate_hz,
            self._link.describe,
            self.sysid,
            self.compid,
        )

    def write(self, frame: Frame, result: Result) -> None:
        """Pool the scan into sectors and hand them to the sender thread.

        Raises:
            SinkError: the link failed in the sender thread.
        """
        if self._error is not None:
            raise SinkError(
                f"mavlink sink: {self._link.describe if self._link else self.name} failed: "
                f"{self._error}",
                hint="check the cable / port; the other sinks go on",
            )
        if self._thread is None:
            raise SinkError(f"sink {self.name!r} is not open")
        trust = result.mount_trust
        known = trust is None or trust.trusted
        trusted = trust is None or trust.dropoffs_trusted
        text = self._trust_text(trust, known, trusted)
        self._trusted = (known, trusted)
        cliff = self.cliff and (trusted or self.untrusted_dropoffs == "send")
        sectors = sectors_for(result, cliff)
        if not known:  # nothing is known where the floor is not: every sector unknown
            sectors = dataclasses.replace(
                sectors, distances_cm=np.full_like(sectors.distances_cm, UNKNOWN)
            )
        now = time.monotonic()
        with self._lock:
            self._latest = (sectors, int(now * 1e6), now)
            if text is not None:
                self._texts.append(text)

    def _trust_text(
        self, trust: MountTrust | None, known: bool, trusted: bool
    ) -> tuple[int, str] | None:
        """The STATUSTEXT for this frame's change of mount trust, or None (no change, or a
        trusted first frame)."""
        last = self._trusted
        if last == (known, trusted) or (last is None and trusted):
            return None
        if not known:
            return MAV_SEVERITY_WARNING, "depthnav: mount unconfirmed, sectors unknown"
        if trusted and (last is None or not last[0]):
            return MAV_SEVERITY_INFO, "depthnav: mount confirmed by the floor"
        return trust_statustext(trust, self.cliff, self.untrusted_dropoffs)

    def latest_for(self, now: float) -> tuple[Sectors, int] | None:
        """Sectors to send at monotonic time ``now``: the newest unless older than ``stale_s``."""
        with self._lock:
            latest = self._latest
        if latest is None or now - latest[2] > self.stale_s:
            return None
        return latest[0], latest[1]

    def _send_heartbeat(self) -> None:
        # MAV_TYPE_ONBOARD_CONTROLLER, MAV_AUTOPILOT_INVALID, base/custom mode 0, MAV_STATE_ACTIVE
        self._mav.heartbeat_send(18, 8, 0, 0, 4)
        self.sent_heartbeat += 1

    def _send_texts(self) -> None:
        with self._lock:
            texts, self._texts = self._texts, []
        for severity, text in texts:
            self._mav.statustext_send(severity, text.encode())
            self.sent_text += 1

    def _send_obstacles(self, sectors: Sectors, time_usec: int) -> None:
        inc_f = sectors.increment_f_deg
        self._mav.obstacle_distance_send(
            time_usec,
            self.sensor_type,
            sectors.distances_cm.tolist(),
            max(1, min(255, round(inc_f))),  # legacy integer field; ignored since increment_f != 0
            sectors.min_cm,
            sectors.max_cm,
            inc_f,
            sectors.angle_offset_deg,
            MAV_FRAME_BODY_FRD,
        )
        self.sent_obstacle += 1

    def _run(self) -> None:
        clock = Schedule(1.0 / self.rate_hz, time.monotonic())
        try:
            while not self._stop.is_set():
                now = time.monotonic()
                heartbeat, obstacles = clock.due(now)
                if heartbeat:
                    self._send_heartbeat()
                if self._texts:
                    self._send_texts()
                if obstacles:
                    pending = self.latest_for(now)
                    if pending is not None:
                        self._send_obstacles(*pending)
                self._stop.wait(max(0.0, clock.next_wakeup - time.monotonic()))
        except Exception as exc:  # a dead port: reported by the next write()
            log.debug("mavlink sender thread failed", exc_info=True)
            self._error = exc

    def close(self) -> None:
        """Stop the thread (joined, at most JOIN_TIMEOUT_S), close the link. Safe to call twice."""
        self._stop.set()
        thread, self._thread = self._thread, None
        if thread is not None:
            thread.join(timeout=JOIN_TIMEOUT_S)
            if thread.is_alive():
                log.warning(
                    "mavlink sink: sender thread did not stop within %.1f s", JOIN_TIMEOUT_S
                )
        link, self._link = self._link, None
        if link is not None:
            try:
                link.close()
            except Exception:  # closing a port that already went away
                log.debug("closing the mavlink link failed", exc_info=True)
