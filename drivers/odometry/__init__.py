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

Every sample is checked by :func:`check_sample` (drivers.base: |x_m|, |y_m| <= 1e7 m, |yaw_rad| <=
1e6 rad, |t_s| <= 1e10 s, all finite numbers); a refused one is counted per kind by the source's
:class:`OdomRefusals`, which warns once per kind and then sums up at most every minute.
"""

from __future__ import annotations

import collections
import importlib
import logging
import math
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Protocol

from drivers.base import (
    ODOM_POSITION_LIMIT_M,
    ODOM_REFUSAL_KINDS,
    ODOM_TIME_LIMIT_S,
    ODOM_YAW_LIMIT_RAD,
    OdomRefusal,
    check_odom_pose,
    check_odom_time,
)
from drivers.errors import DeviceSpecError
from drivers.spec import parse_spec

log = logging.getLogger(__name__)

ODOMETRY_SOURCES: dict[str, tuple[str, str]] = {  # scheme -> (module, class); imported when used
    "odom+udp": ("drivers.odometry.udp", "UdpJsonOdometry"),
    "mavlink+udp": ("drivers.odometry.mavlink", "MavlinkOdometry"),
    "mavlink": ("drivers.odometry.mavlink", "MavlinkOdometry"),
}
BUFFER_SAMPLES = 512  # ~5 s at 100 Hz; bounded whatever the sender does
SUMMARY_EVERY_S = 60.0  # after the first warning of each kind, refusals are summed up this often


@dataclass(frozen=True, slots=True)
class OdomSample:
    """One pose: time (seconds, the source's clock), x, y (metres), yaw (radians, unwrapped)."""

    t_s: float
    x_m: float
    y_m: float
    yaw_rad: float


def check_sample(t_s: Any, x_m: Any, y_m: Any, yaw_rad: Any) -> OdomSample | OdomRefusal:
    """One sample checked against the odometry limits (drivers.base): the sample (floats, yaw
    wrapped to [-pi, pi]) or why it is refused. Never raises, whatever the values are."""
    t = check_odom_time(t_s)
    if isinstance(t, OdomRefusal):
        return t
    pose = check_odom_pose(x_m, y_m, yaw_rad)
    if isinstance(pose, OdomRefusal):
        return pose
    return OdomSample(t, *pose)


class OdomBuffer:
    """The latest samples of a source, thread-safe; interpolates a pose at any time between them.

    Yaw is stored wrapped to [-pi, pi]; interpolation turns the short way across +-pi.
    """

    def __init__(self, maxlen: int = BUFFER_SAMPLES) -> None:
        self._samples: collections.deque[OdomSample] = collections.deque(maxlen=maxlen)
        self._lock = threading.Lock()
        self.count = 0  # samples ever added

    def offer(self, t_s: Any, x_m: Any, y_m: Any, yaw_rad: Any) -> OdomRefusal | None:
        """Add a sample; None when taken, else why not (outside the limits, time going back)."""
        sample = check_sample(t_s, x_m, y_m, yaw_rad)
        if isinstance(sample, OdomRefusal):
            return sample
        with self._lock:
            if self._samples and sample.t_s < self._samples[-1].t_s:
                return OdomRefusal(
                    "out_of_order",
                    f"t_s={sample.t_s:.6g} is before the previous sample's "
                    f"{self._samples[-1].t_s:.6g}",
                )
            self._samples.append(sample)
            self.count += 1
        return None

    def add(self, t_s: Any, x_m: Any, y_m: Any, yaw_rad: Any) -> bool:
        """Add a sample; False (and dropped) when :meth:`offer` refuses it."""
        return self.offer(t_s, x_m, y_m, yaw_rad) is None

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
            a.yaw_rad + f * math.remainder(b.yaw_rad - a.yaw_rad, 2 * math.pi),  # the short way
        )
        return pose, 0.0


class OdomRefusals:
    """Refused samples of one source, counted per kind (thread-safe).

    The first refusal of each kind is a warning naming the value; after that, a summary of what
    was refused since is logged at most every ``every_s`` seconds (on the next refusal, or by
    :meth:`flush`), so a flood of bad lines is a few lines a minute.

    Args:
        name: the source, for messages.
        clock: monotonic seconds (injectable for tests).
        every_s: the shortest time between two summaries.
    """

    def __init__(
        self,
        name: str,
        clock: Callable[[], float] = time.monotonic,
        every_s: float = SUMMARY_EVERY_S,
    ) -> None:
        self.name = name
        self._clock = clock
        self._every_s = every_s
        self._lock = threading.Lock()
        self._counts = dict.fromkeys(ODOM_REFUSAL_KINDS, 0)
        self._unsaid = dict.fromkeys(ODOM_REFUSAL_KINDS, 0)  # counted since the last message
        self._said_at: float | None = None

    def note(self, refusal: OdomRefusal, where: str = "") -> None:
        """Count one refused sample (``where``: e.g. "frame 12", for the first warning)."""
        now = self._clock()
        with self._lock:
            first = self._counts.get(refusal.kind, 0) == 0
            self._counts[refusal.kind] = self._counts.get(refusal.kind, 0) + 1
            if not first:
                self._unsaid[refusal.kind] = self._unsaid.get(refusal.kind, 0) + 1
                due = self._said_at is not None and now - self._said_at >= self._every_s
                summary = self._take_summary(now) if due else None
            else:
                self._said_at = now
                summary = None
        if first:
            log.warning(
                "odometry %s: refusing a sample (%s)%s: %s; such samples are counted "
                "(memory.odometry_rejected) and summed up at most every %g s",
                self.name,
                refusal.kind,
                f" at {where}" if where else "",
                refusal.reason,
                self._every_s,
            )
        elif summary:
            log.warning("odometry %s: %s", self.name, summary)

    def flush(self) -> None:
        """Log what was refused since the last message, if anything (e.g. when stopping)."""
        with self._lock:
            summary = self._take_summary(self._clock())
        if summary:
            log.warning("odometry %s: %s", self.name, summary)

    def _take_summary(self, now: float) -> str | None:
        """The summary line of the unsaid refusals, or None; resets them (lock held)."""
        unsaid = {k: v for k, v in self._unsaid.items() if v}
        if not unsaid:
            return None
        self._unsaid = dict.fromkeys(self._unsaid, 0)
        self._said_at = now
        parts = ", ".join(f"{v} {k}" for k, v in unsaid.items())
        return (
            f"refused {sum(unsaid.values())} more samples since the last report ({parts}); "
            f"{sum(self._counts.values())} in all"
        )

    def counts(self) -> dict[str, int]:
        """Refused samples per kind so far (every kind, zeros included)."""
        with self._lock:
            return dict(self._counts)

    @property
    def total(self) -> int:
        with self._lock:
            return sum(self._counts.values())


class OdometrySource(Protocol):
    """A background reader of odometry. Constructing it does no I/O; ``start`` opens it.

    Attributes:
        name: the spec, for messages.
        uses_arrival_clock: True when samples are timed by the host's monotonic clock on arrival
            (ask with ``time.monotonic()``); False when by the sender's ``t_s`` (ask with the
            frame's timestamp).
        buffer: the samples taken.
        refusals: the samples refused, per kind.
    """

    name: str
    uses_arrival_clock: bool
    buffer: OdomBuffer
    refusals: OdomRefusals

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
    module = importlib.import_module(module_name)
    try:
        return getattr(module, class_name).from_spec(text)
    except DeviceSpecError as exc:
        if exc.hint:
            raise
        raise DeviceSpecError(str(exc), hint=f"write {module.GRAMMAR}") from None


__all__ = [
    "ODOM_POSITION_LIMIT_M",
    "ODOM_REFUSAL_KINDS",
    "ODOM_TIME_LIMIT_S",
    "ODOM_YAW_LIMIT_RAD",
    "OdomBuffer",
    "OdomRefusal",
    "OdomRefusals",
    "OdomSample",
    "OdometrySource",
    "check_sample",
    "create_odometry",
    "now_s",
]


def now_s() -> float:
    """The arrival clock (host monotonic seconds)."""
    return time.monotonic()
