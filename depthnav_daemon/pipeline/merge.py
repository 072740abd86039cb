"""Several sensors' base-frame scans as one (the paper's answer to dead zones is "a higher number of
sensors", sec. 3.1).

The merged scan's bins have the finest of the sensors' widths and are centred on multiples of it
(bearing 0 is a bin centre); its extent is the union of the sensors' extents, the smallest arc
holding them all, up to a full turn (then -pi .. pi). Each sensor bin feeds every merged bin
its footprint overlaps; per sensor a merged bin takes the nearest reading of the bins feeding it,
and is clear (+inf) for that sensor only if none of them is unknown (NaN); over the sensors the
nearest wins (REP 117 order: -inf, ranges, +inf, then no data). So an obstacle either sensor sees
is in it at its own range, where both see it the nearer reading wins, and a bin is clear only where
one sensor saw all of it clear (the safety contract). Which sensors take part (their data younger
than a max age) is the daemon's decision; this module is pure.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
import numpy.typing as npt

from depthnav_daemon.pipeline._jit import kernel
from depthnav_daemon.pipeline.scan import LaserScan

if TYPE_CHECKING:
    from depthnav_daemon.pipeline import Result

SEEN = np.float32(1e30)  # "valid readings, no obstacle": between ranges and no data (+inf)
TWO_PI = 2.0 * math.pi
Layout = tuple[float, float, int]  # angle_min, angle_increment, bins


@dataclass(frozen=True, slots=True)
class SensorState:
    """One sensor of a multi-sensor daemon, as it goes out with a merged Result.

    Attributes:
        name: the sensor's name ([[sensor]] name).
        status: "ok" (in the merge), "stale" (no frame for longer than the max age: left out),
            "lost" (the device is gone for good) or "ended" (its recording ended).
        age_s: seconds since its latest result arrived, or None before the first.
        result: its latest Result (base frame), or None before the first.
    """

    name: str
    status: str
    age_s: float | None
    result: Result | None


def layout_of(scan: LaserScan) -> Layout:
    return float(scan.angle_min), float(scan.angle_increment), int(scan.ranges.size)


@functools.lru_cache(maxsize=64)
def merged_layout(layouts: tuple[Layout, ...]) -> Layout:
    """The merged scan's layout for these sensor layouts (module docstring)."""
    inc = min(lay[1] for lay in layouts)
    spans = sorted(
        ((lo % TWO_PI), (lo % TWO_PI) + (n * w))
        for lo, w, n in ((a0 - w / 2, w, n) for a0, w, n in layouts)
    )
    # the largest uncovered gap on the circle; the merged arc is everything else
    start, end = spans[0]
    best_gap, arc_start = 0.0, spans[0][0]
    for lo, hi in spans[1:]:
        if lo > end and lo - end > best_gap:
            best_gap, arc_start = lo - end, lo
        end = max(end, hi)
    wrap_gap = start + TWO_PI - end
    if wrap_gap >= best_gap:
        best_gap, arc_start = wrap_gap, start
    if best_gap <= inc:
        n = round(TWO_PI / inc)
        return -math.pi, TWO_PI / n, n
    width = TWO_PI - best_gap
    lo = arc_start if arc_start < math.pi else arc_start - TWO_PI
    k0 = math.floor(lo / inc + 0.5)
    k1 = math.ceil((lo + width) / inc - 0.5)
    return k0 * inc, inc, int(k1 - k0 + 1)


@functools.lru_cache(maxsize=64)
def feed_map(src: Layout, dst: Layout) -> tuple[npt.NDArray[np.int64], npt.NDArray[np.int64]]:
    """(first, last) merged bin each source bin feeds ((M,) each; first > last: none); indices
    may exceed the merged bins for a full-turn layout (the kernel wraps them)."""
    a0, w, m = src
    b0, inc, n = dst
    full = n * inc >= TWO_PI - 1e-9
    centre = a0 + w * np.arange(m)
    # each bearing as the turn nearest the merged arc's middle
    c = (n - 1) * inc / 2.0
    rel = np.mod(centre - b0 - c + math.pi, TWO_PI) - math.pi + c
    # every merged bin the source bin overlaps (by more than a thousandth of a bin), so a merged
    # bin hears of everything in its width: the nearest reading wins, and one part of it unknown
    # to a sensor keeps that sensor from calling it clear (merge_into)
    eps = 1e-3 * min(inc, w)
    first = (np.floor((rel - w / 2 + eps) / inc - 0.5) + 1).astype(np.int64)
    last = (np.ceil((rel + w / 2 - eps) / inc + 0.5) - 1).astype(np.int64)
    if not full:
        first = np.maximum(first, 0)
        last = np.minimum(last, n - 1)
    first.setflags(write=False)
    last.setflags(write=False)
    return first, last


def merge_scans(scans: Sequence[LaserScan], layout: Layout | None = None) -> LaserScan:
    """The nearest over several base-frame scans per merged bin (module docstring).

    Args:
        scans: the sensors' base-frame scans (REP 117).
        layout: the merged layout, or None for :func:`merged_layout` of the scans.
    """
    lay = layout or merged_layout(tuple(layout_of(s) for s in scans))
    b0, inc, n = lay
    out = np.full(n, np.inf, dtype=np.float32)
    part = np.empty(n, dtype=np.float32)
    for s in scans:
        first, last = feed_map(layout_of(s), lay)
        merge_into(np.ascontiguousarray(s.ranges, dtype=np.float32), first, last, part, out)
    finish(out)
    rmin = min((s.range_min for s in scans), default=0.0)
    rmax = max((s.range_max for s in scans), default=0.0)
    return LaserScan(b0, b0 + (n - 1) * inc, inc, rmin, rmax, out)


@kernel
def merge_into(ranges, first, last, part, out):
    """out[j] = nearest of out[j] and this sensor's word on j (REP 117 codes, SEEN for +inf):
    the nearest reading of the source bins feeding j; clear (SEEN) only if none of them is
    unknown (NaN). Indices past the end wrap (full turn); ``part`` is scratch (n,)."""
    n = out.shape[0]
    inf = np.float32(np.inf)
    unknown = np.float32(-1.0)  # a part of the bin this sensor did not see
    for j in range(n):
        part[j] = inf
    for i in range(ranges.shape[0]):
        v = ranges[i]
        for j in range(first[i], last[i] + 1):
            jj = j % n
            p = part[jj]
            if np.isnan(v):
                if p >= SEEN:  # +inf (nothing yet) or SEEN
                    part[jj] = unknown
            elif v == inf:
                if p == inf:
                    part[jj] = SEEN
            elif v < p or p == unknown or p == SEEN:  # noqa: PLR1714 (compiled: no tuple)
                part[jj] = v
    for j in range(n):
        p = part[j]
        if p != unknown:
            out[j] = min(out[j], p)


@kernel
def finish(out):
    """SEEN -> +inf, untouched (+inf) -> NaN."""
    for j in range(out.shape[0]):
        v = out[j]
        out[j] = np.inf if v == SEEN else (np.nan if v == np.inf else v)
