"""Odometry sources: the robot's planar pose (x_m, y_m, yaw_rad) in its odometry frame, for the
obstacle memory. Not depth drivers: the daemon asks for the pose at each frame's time.

Frame (REP 103 / REP 105 ``odom``): x forward at the start, y left, yaw counter-clockwise, radians.

Specs (each a spec like the devices'):
- ``odom+udp://127.0.0.1:PORT[?clock=arrival|message]``: JSON lines over UDP on loopback,
  ``{"t_s": 12.5, "x_m": 1.0, "y_m": 0.2, "yaw_rad": 0.1}`` (``drivers.odometry.udp``);
- ``mavlink+udp://HOST:PORT`` or ``mavlink:SERIALPORT[?baud=N]``: an autopilot's
  LOCAL_POSITION_NED + ATTITUDE, or ODOMETRY (``drivers.odometry.mavlink``).
Recordings carry their own (``Frame.odom``, one row per frame): no source is needed to replay them.

Samples are kept in a bounded buffer and interpolated to the time asked for
(:class:`OdomBuffer`); by default a sample's time is the host's monotonic clock when it arrived.
"""

from __future__ import annotations

import collections
import importlib
import math
import threading
import time
from dataclasses import dataclass
from typing import Protocol

from drivers.errors import DeviceSpecError
from drivers.spec import parse_spec

ODOMETRY_SOURCES: dict[str, tuple[str, str]] = {  # scheme -> (module, class); imported when used
    "odom+udp": ("drivers.odometry.udp", "UdpJsonOdometry"),
    "mavlink+udp": ("drivers.odometry.mavlink", "MavlinkOdometry"),
    "mavlink": ("drivers.odometry.mavlink", "MavlinkOdometry"),
}
BUFFER_SAMPLES = 512  # ~5 s at 100 Hz; bounded whatever the sender does


@dataclass(frozen=True, slots=True)
class OdomSample:
    """One pose: time (seconds, the source's clock), x, y (metres), yaw (radians, unwrapped)."""

    t_s: float
    x_m: float
    y_m: float
    yaw_rad: float


class OdomBuffer:
    """The latest samples of a source, thread-safe; interpolates a pose at any time between them.

    Yaw is stored unwrapped (each sample within pi of the previous), so interpolating across
    +-pi turns the short way.
    """

    def __init__(self, maxlen: int = BUFFER_SAMPLES) -> None:
        self._samples: collections.deque[OdomSample] = collections.deque(maxlen=maxlen)
        self._lock = threading.Lock()
        self.count = 0  # samples ever added

    def add(self, t_s: float, x_m: float, y_m: float, yaw_rad: float) -> bool:
        """Add a sample; returns False (and drops it) for non-finite values or time going back."""
        if not all(math.isfinite(v) for v in (t_s, x_m, y_m, yaw_rad)):
            return False
        with self._lock:
            if self._samples:
                last = self._samples[-1]
                if t_s < last.t_s:
                    return False
                yaw_rad = last.yaw_rad + math.remainder(yaw_rad - last.yaw_rad, 2 * math.pi)
            self._samples.append(OdomSample(t_s, x_m, y_m, yaw_rad))
            self.count += 1
        return True

    def latest(self) -> OdomSample | None:
        with self._lock:
            return self._samples[-1] if self._samples else None

    def pose_at(self, t_s: float) -> tuple[tuple[float, float, float], float] | None:
        """(pose interpolated at ``t_s``, age of the newest sample used, seconds), or None when
        ``t_s`` is before every sample or there is none. After the newest sample the newest pose
        is held (never extrapolated) and the age says how old it is."""
        with self._lock:
            samples = list(self._samples)
        if not samples or t_s < samples[0].t_s:
            return None
        last = samples[-1]
        if t_s >= last.t_s:
            return (last.x_m, last.y_m, last.yaw_rad), t_s - last.t_s
        lo, hi = 0, len(samples) - 1
        while hi - lo > 1:
            mid = (lo + hi) // 2
            if samples[mid].t_s <= t_s:
                lo = mid
            else:
                hi = mid
        a, b = samples[lo], samples[hi]
        f = 0.0 if b.t_s == a.t_s else (t_s - a.t_s) / (b.t_s - a.t_s)
        pose = (
            a.x_m + f * (b.x_m - a.x_m),
            a.y_m + f * (b.y_m - a.y_m),
            a.yaw_rad + f * (b.yaw_rad - a.yaw_rad),
        )
        return pose, 0.0


class OdometrySource(Protocol):
    """A background reader of odometry. Constructing it does no I/O; ``start`` opens it.

    Attributes:
        name: the spec, for messages.
        uses_arrival_clock: True when samples are timed by the host's monotonic clock on arrival
            (ask with ``time.monotonic()``); False when by the sender's ``t_s`` (ask with the
            frame's timestamp).
    """

    name: str
    uses_arrival_clock: bool
    buffer: OdomBuffer
    bad_messages: int

    def start(self) -> None:
        """Open the source and start reading (raises DeviceOpenError)."""

    def stop(self) -> None:
        """Stop reading and close; safe to call twice."""


def create_odometry(text: str) -> OdometrySource:
    """Build (but do not start) the odometry source named by a spec.

    Raises:
        DeviceSpecError: an unknown scheme or a bad option.
    """
    scheme = parse_spec(text, "odometry", "odom+udp://127.0.0.1:5700, mavlink+udp://:14550").scheme
    if scheme not in ODOMETRY_SOURCES:
        raise DeviceSpecError(
            f"unknown odometry source {text!r}",
            hint=f"use one of: {', '.join(sorted(ODOMETRY_SOURCES))}",
        )
    module_name, class_name = ODOMETRY_SOURCES[scheme]
    return getattr(importlib.import_module(module_name), class_name).from_spec(text)


def now_s() -> float:
    """The arrival clock (host monotonic seconds)."""
    return time.monotonic()
