"""Several sensors' base-frame scans as one (the paper's answer to dead zones is "a higher number of
sensors", sec. 3.1).

The merged scan's bins have the finest of the sensors' widths and are centred on multiples of it
(bearing 0 is a bin centre); its extent is the union of the sensors' extents, the smallest arc
holding them all, up to a full turn (then -pi .. pi). Each sensor bin feeds the merged bins whose
centres its footprint covers (or the one holding its centre when it is narrower than a merged bin),
and each merged bin keeps the nearest over the sensors (REP 117 order: -inf, ranges, +inf, then no
data), so an obstacle either sensor sees is in it at its own range, and where both see it the
nearer reading wins. Which sensors take part (their data younger than a max age) is the daemon's
decision; this module is pure.
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
    first = np.ceil((rel - w / 2) / inc - 1e-9).astype(np.int64)
    last = np.floor((rel + w / 2) / inc + 1e-9).astype(np.int64)
    narrow = first > last
    mid = np.floor(rel / inc + 0.5).astype(np.int64)
    first = np.where(narrow, mid, first)
    last = np.where(narrow, mid, last)
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
    for s in scans:
        first, last = feed_map(layout_of(s), lay)
        merge_into(np.ascontiguousarray(s.ranges, dtype=np.float32), first, last, out)
    finish(out)
    rmin = min((s.range_min for s in scans), default=0.0)
    rmax = max((s.range_max for s in scans), default=0.0)
    return LaserScan(b0, b0 + (n - 1) * inc, inc, rmin, rmax, out)


@kernel
def merge_into(ranges, first, last, out):
    """out[j] = nearest of out[j] and every source bin feeding j (REP 117 codes, SEEN for +inf);
    indices past the end wrap (full turn)."""
    n = out.shape[0]
    inf = np.float32(np.inf)
    for i in range(ranges.shape[0]):
        v = ranges[i]
        if np.isnan(v):
            continue
        code = SEEN if v == inf else v
        for j in range(first[i], last[i] + 1):
            jj = j % n
            out[jj] = min(out[jj], code)


@kernel
def finish(out):
    """SEEN -> +inf, untouched (+inf) -> NaN."""
    for j in range(out.shape[0]):
        v = out[j]
        out[j] = np.inf if v == SEEN else (np.nan if v == np.inf else v)
