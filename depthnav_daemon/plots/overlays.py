"""What the figures and the live viewer draw over a frame, as arrays (no matplotlib, no rerun).

Everything here reads a Result's fields (and the frame conventions of ``pipeline.geometry``); it
never runs a stage. Level frame at the sensor's foot: x forward, y left, metres.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import numpy as np
import numpy.typing as npt

from depthnav_daemon.pipeline.geometry import level_rays

if TYPE_CHECKING:
    from depthnav_daemon.pipeline import Result
    from depthnav_daemon.pipeline.scan import LaserScan

F64 = npt.NDArray[np.float64]
BREAK_JUMP_M = 0.25  # neighbouring readings further apart than this are not joined by a line
SOURCE_MATCH_M = 0.03  # an obstacle pixel this close to its bin's range produced the reading
DEFAULT_FOOTPRINT_M = (0.45, 0.40)  # length, width of the robot drawn when none is given


def scan_xy(scan: LaserScan) -> F64:
    """(K, 2) points (x forward, y left) of the scan's finite ranges, metres."""
    r = np.asarray(scan.ranges, dtype=np.float64)
    ok = np.isfinite(r)
    a = scan.angles[ok]
    return np.stack([r[ok] * np.cos(a), r[ok] * np.sin(a)], axis=1)


def scan_strips(scan: LaserScan, jump_m: float = BREAK_JUMP_M) -> list[F64]:
    """The scan as polylines: runs of neighbouring finite readings, broken at gaps and at jumps of
    more than ``jump_m`` (an object's edge), each (k, 2) x forward, y left; single points too."""
    r = np.asarray(scan.ranges, dtype=np.float64)
    a = scan.angles
    ok = np.isfinite(r)
    xy = np.stack([r * np.cos(a), r * np.sin(a)], axis=1)
    breaks = ~ok[1:] | ~ok[:-1]
    with np.errstate(invalid="ignore"):
        breaks |= np.abs(np.diff(r)) > jump_m
    strips: list[F64] = []
    start = 0
    for i in [*np.flatnonzero(breaks).tolist(), r.size - 1]:
        run = np.arange(start, i + 1)
        run = run[ok[run]]
        if run.size:
            strips.append(xy[run])
        start = i + 1
    return strips


def scan_source_pixels(depth_mm: np.ndarray, result: Result) -> npt.NDArray[np.int64]:
    """(K, 2) (row, col) of the obstacle pixel that produced each finite scan reading.

    Among the obstacle pixels (``result.obstacle_mask``, exact method) whose bearing falls in a
    bin, the nearest one when it lies within SOURCE_MATCH_M of that bin's range. Empty without a
    mask or for a float depth image.
    """
    mask, scan = result.obstacle_mask, result.scan
    if mask is None or depth_mm.dtype != np.uint16 or not mask.any():
        return np.empty((0, 2), dtype=np.int64)
    rows, cols = np.nonzero(mask)
    m = result.mount
    k = level_rays(result.intrinsics, m.tilt_rad, m.roll_rad)[rows, cols]
    z = depth_mm[rows, cols] * 1e-3
    rng = z * np.hypot(k[:, 0], k[:, 1])
    bins = np.rint((np.arctan2(k[:, 1], k[:, 0]) - scan.angle_min) / scan.angle_increment)
    n = scan.ranges.size
    inside = (bins >= 0) & (bins < n)
    rows, cols, rng, bins = rows[inside], cols[inside], rng[inside], bins[inside].astype(np.int64)
    order = np.lexsort((rng, bins))
    first = order[np.unique(bins[order], return_index=True)[1]]
    want = np.asarray(scan.ranges, dtype=np.float64)[bins[first]]
    with np.errstate(invalid="ignore"):
        hit = np.abs(rng[first] - want) <= SOURCE_MATCH_M
    return np.stack([rows[first][hit], cols[first][hit]], axis=1)


def footprint_xy(length_m: float, width_m: float) -> F64:
    """(5, 2) closed outline of a rectangular robot whose front centre carries the sensor."""
    w = width_m / 2
    return np.array([[0.0, w], [-length_m, w], [-length_m, -w], [0.0, -w], [0.0, w]])


def fov_xy(scan: LaserScan, reach_m: float) -> F64:
    """(N, 2) closed outline of the scan's horizontal field of view out to ``reach_m``."""
    a = np.linspace(scan.angle_min, scan.angle_max, 32)
    arc = np.stack([reach_m * np.cos(a), reach_m * np.sin(a)], axis=1)
    return np.vstack([[0.0, 0.0], arc, [0.0, 0.0]])


def cliff_cell_sizes_m(result: Result) -> F64:
    """(K,) side of the square drawn for each cliff point, metres: the width of its block on the
    floor (block_size pixels at that range), so neighbouring blocks tile."""
    cliff = result.cliff
    if cliff is None or len(cliff.points_m) == 0:
        return np.empty(0)
    pts = np.asarray(cliff.points_m, dtype=np.float64)
    r = np.hypot(pts[:, 0], pts[:, 1])
    return np.clip(cliff.block_size * r / result.intrinsics.fx, 0.02, 0.5)


def range_rings(reach_m: float, step_m: float = 1.0) -> list[tuple[float, F64]]:
    """(radius, (64, 2) arc) every ``step_m`` out to ``reach_m``, over the forward half-plane."""
    a = np.linspace(-0.6 * math.pi, 0.6 * math.pi, 64)
    return [
        (float(d), np.stack([d * np.cos(a), d * np.sin(a)], axis=1))
        for d in np.arange(step_m, reach_m + 1e-9, step_m)
    ]
