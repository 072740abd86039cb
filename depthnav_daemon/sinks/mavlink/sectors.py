"""OBSTACLE_DISTANCE payloads from depthnav's scans, and when to send them: the pure part of the
``mavlink`` sink (see its docstring for the sector layout and the value mapping)."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
import numpy.typing as npt

if TYPE_CHECKING:
    from depthnav_daemon.pipeline import MountTrust, Result
    from depthnav_daemon.pipeline.scan import LaserScan

SECTORS = 72
UNKNOWN = 65535  # UINT16_MAX: no data in this sector
HEARTBEAT_PERIOD_S = 1.0
MAV_SEVERITY_WARNING = 4
MAV_SEVERITY_INFO = 6
STATUSTEXT_CHARS = 50  # one STATUSTEXT's text field


@dataclass(frozen=True, slots=True)
class Sectors:
    """One OBSTACLE_DISTANCE payload.

    Attributes:
        distances_cm: (72,) uint16, element 0 = left-most sector (see the module docstring).
        increment_f_deg: sector width, degrees, clockwise.
        angle_offset_deg: bearing of element 0's centre, degrees clockwise from forward (FRD).
        min_cm, max_cm: the sensor's range limits, centimetres.
    """

    distances_cm: npt.NDArray[np.uint16]
    increment_f_deg: float
    angle_offset_deg: float
    min_cm: int
    max_cm: int


def range_limits_cm(scan: LaserScan) -> tuple[int, int]:
    """(min_distance, max_distance) in cm for a scan; min >= 1 because ArduPilot drops 0."""
    min_cm = max(1, round(scan.range_min * 100.0))
    max_cm = min(UNKNOWN - 2, max(min_cm + 1, round(scan.range_max * 100.0)))
    return min_cm, max_cm


def bins_to_cm(ranges: np.ndarray, min_cm: int, max_cm: int) -> npt.NDArray[np.float64]:
    """REP 117 ranges (N,) metres -> per-bin distances in cm (float, NaN = no data)."""
    r = np.asarray(ranges, dtype=np.float64)
    with np.errstate(invalid="ignore"):
        cm = np.clip(np.floor(r * 100.0), min_cm, max_cm)  # floor: report an obstacle slightly near
    cm[r == np.inf] = max_cm + 1
    cm[r == -np.inf] = min_cm
    cm[np.isnan(r)] = np.nan
    return cm


def _footprints_deg(scan: LaserScan) -> tuple[npt.NDArray[np.float64], npt.NDArray[np.float64]]:
    """Clockwise-degree footprint [lo, hi) of every bin of a CCW scan, (N,) each."""
    m = int(scan.ranges.size)
    inc = abs(float(scan.angle_increment)) if m > 1 else 0.0
    if inc == 0.0 or not math.isfinite(inc):
        inc = math.radians(1.0)  # a single bin: give it a nominal 1 degree footprint
    theta = scan.angle_min + float(scan.angle_increment) * np.arange(m)
    return -np.degrees(theta + inc / 2.0), -np.degrees(theta - inc / 2.0)


def _pool_min(
    out: npt.NDArray[np.float64],
    lo: np.ndarray,
    hi: np.ndarray,
    cm: np.ndarray,
    left: float,
    width: float,
) -> npt.NDArray[np.bool_]:
    """out[j] = min(out[j], cm of bins whose footprint [lo, hi) overlaps sector j), NaN skipped;
    returns (n,) whether a NaN (unknown) bin overlaps each sector."""
    n = out.size
    eps = 1e-6  # footprints that only touch a sector boundary do not count as overlapping
    first = np.floor((lo - left) / width + eps).astype(np.int64)
    last = np.ceil((hi - left) / width - eps).astype(np.int64) - 1
    last = np.maximum(last, first)
    inside = (last >= 0) & (first <= n - 1)
    first, last = np.clip(first, 0, n - 1), np.clip(last, 0, n - 1)
    unknown = np.zeros(n, dtype=bool)
    nan = np.isnan(cm)
    for keep, into in ((inside & ~nan, None), (inside & nan, unknown)):
        f, la, c = first[keep], last[keep], cm[keep]
        span = la - f + 1
        idx = np.repeat(f, span) + (
            np.arange(int(span.sum())) - np.repeat(np.cumsum(span) - span, span)
        )
        if into is None:
            np.minimum.at(out, idx, np.repeat(c, span))
        else:
            into[idx] = True
    return unknown


def _clear_only_if_known(out: npt.NDArray[np.float64], unknown: np.ndarray, max_cm: int) -> None:
    """A sector that found nothing (max_distance + 1, "no obstacle") but has an unknown part is
    unknown (UINT16_MAX): "no obstacle" makes a vehicle drive there (the safety contract)."""
    out[(out == max_cm + 1) & unknown] = UNKNOWN


def obstacle_sectors(scan: LaserScan, n: int = SECTORS) -> Sectors:
    """Pool a scan into ``n`` clockwise sectors over its field of view (module docstring).

    Args:
        scan: the REP 117 scan, counter-clockwise bearings (radians).
        n: number of sectors (72 for OBSTACLE_DISTANCE).

    Returns:
        The payload; every sector is the minimum over the scan bins overlapping it.
    """
    min_cm, max_cm = range_limits_cm(scan)
    out = np.full(n, float(UNKNOWN))
    if scan.ranges.size == 0:
        return Sectors(out.astype(np.uint16), 1.0, 0.0, min_cm, max_cm)
    lo, hi = _footprints_deg(scan)
    left = float(lo.min())
    width = (float(hi.max()) - left) / n
    unknown = _pool_min(out, lo, hi, bins_to_cm(scan.ranges, min_cm, max_cm), left, width)
    _clear_only_if_known(out, unknown, max_cm)
    return Sectors(out.astype(np.uint16), width, left + width / 2.0, min_cm, max_cm)


def merge_cliff(obstacles: Sectors, cliff_scan: LaserScan) -> Sectors:
    """Obstacle sectors with the drop-offs of a cliff scan folded in (sector-wise minimum).

    Detections count (finite ranges, and -inf = a drop-off closer than range_min); the cliff
    scan's "no drop-off" (+inf) leaves the obstacle scan's verdict unchanged, and its "unknown"
    (NaN: the floor there was not read) makes a "no obstacle" sector unknown (a drop-off may be
    there). Drop-offs outside the obstacle sectors' field of view or beyond max_distance are not
    reported.
    """
    out = obstacles.distances_cm.astype(np.float64)
    if cliff_scan.ranges.size:
        r = np.asarray(cliff_scan.ranges, dtype=np.float64)
        cm = bins_to_cm(r, obstacles.min_cm, obstacles.max_cm)
        cm[r == np.inf] = UNKNOWN  # no drop-off: never below what the obstacles say
        with np.errstate(invalid="ignore"):
            # a drop-off beyond the obstacle scan's max range is out of this message's range
            cm[np.floor(r * 100.0) > obstacles.max_cm] = UNKNOWN
        lo, hi = _footprints_deg(cliff_scan)
        left = obstacles.angle_offset_deg - obstacles.increment_f_deg / 2.0
        unknown = _pool_min(out, lo, hi, cm, left, obstacles.increment_f_deg)
        _clear_only_if_known(out, unknown, obstacles.max_cm)
    return Sectors(
        out.astype(np.uint16),
        obstacles.increment_f_deg,
        obstacles.angle_offset_deg,
        obstacles.min_cm,
        obstacles.max_cm,
    )


def sectors_for(result: Result, cliff: bool) -> Sectors:
    """The OBSTACLE_DISTANCE payload of a frame: from the 360 deg memory scan when the memory is on
    (it holds obstacles and drop-offs, around the whole robot), else from the live scan (and the
    cliff scan when ``cliff``)."""
    memory = result.memory
    if memory is not None and memory.scan is not None:
        return memory_sectors(memory.scan, hidden=memory.hidden)
    sectors = obstacle_sectors(result.scan)
    if cliff and result.cliff is not None:
        sectors = merge_cliff(sectors, result.cliff.scan)
    return sectors


def trust_statustext(trust: MountTrust | None, cliff: bool, untrusted: str) -> tuple[int, str]:
    """The STATUSTEXT (severity, text of at most 50 characters) for a change of mount trust.

    Args:
        trust: the new verdict (None or drop-offs trusted: "trusted again").
        cliff: the sink reports drop-offs at all.
        untrusted: the sink's untrusted_dropoffs option, "send" or "drop".
    """
    if trust is None or trust.dropoffs_trusted:
        return MAV_SEVERITY_INFO, "depthnav: mount trusted again"
    why = "floor contradicts mount" if trust.floor == "contradicted" else "mount not configured"
    what = "" if not cliff else ", cliffs sent" if untrusted == "send" else ", cliffs dropped"
    return MAV_SEVERITY_WARNING, f"depthnav: {why}{what}"[:STATUSTEXT_CHARS]


def memory_sectors(
    scan: LaserScan, n: int = SECTORS, hidden: npt.NDArray[np.bool_] | None = None
) -> Sectors:
    """72 sectors of 5 deg all around the robot from a 360 deg memory scan: element 0 centred
    straight behind (-180 deg clockwise), then clockwise. A sector is the nearest remembered
    point in it; max_distance + 1 (no obstacle) only where the memory knows all of it free;
    else unknown (UINT16_MAX). A sector with a ``hidden`` bin (MemoryScan.hidden: something may
    stand in front of its remembered point) is unknown."""
    min_cm = 1
    max_cm = min(UNKNOWN - 2, max(min_cm + 1, round(scan.range_max * 100.0)))
    out = np.full(n, float(UNKNOWN))
    lo, hi = _footprints_deg(scan)
    width = 360.0 / n
    left = -180.0 - width / 2.0
    # every bin's footprint into [left, left + 360): the scan's -180 deg bin is sector 0's
    shift = left + np.mod(lo - left, 360.0) - lo
    lo, hi = lo + shift, hi + shift
    cm = bins_to_cm(scan.ranges, min_cm, max_cm)
    unknown = _pool_min(out, lo, hi, cm, left, width)
    _clear_only_if_known(out, unknown, max_cm)
    if hidden is not None and hidden.any():
        flag = np.full(n, 0.0)
        _pool_min(flag, lo, hi, np.where(hidden, -1.0, np.nan), left, width)
        out[flag < 0] = UNKNOWN
    return Sectors(out.astype(np.uint16), width, left + width / 2.0, min_cm, max_cm)


def _advance(due: float, period: float, now: float) -> float:
    """Next due time: one period on (keeping the phase), or one period from now if that passed."""
    nxt = due + period
    return nxt if nxt > now else now + period


class Schedule:
    """When the sender thread sends: HEARTBEAT every second, OBSTACLE_DISTANCE every ``period_s``.

    A late tick (a slow machine, a blocked serial write) sends once and moves on; it never bursts
    to catch up, so the link never carries a backlog of stale scans.
    """

    def __init__(self, period_s: float, start_s: float) -> None:
        self.period_s = period_s
        self.next_heartbeat = start_s
        self.next_obstacles = start_s

    def due(self, now: float) -> tuple[bool, bool]:
        """(send a heartbeat, send obstacles) at monotonic time ``now``; advances the schedule."""
        heartbeat = now >= self.next_heartbeat
        if heartbeat:
            self.next_heartbeat = _advance(self.next_heartbeat, HEARTBEAT_PERIOD_S, now)
        obstacles = now >= self.next_obstacles
        if obstacles:
            self.next_obstacles = _advance(self.next_obstacles, self.period_s, now)
        return heartbeat, obstacles

    @property
    def next_wakeup(self) -> float:
        """Monotonic time of the next send."""
        return min(self.next_heartbeat, self.next_obstacles)
