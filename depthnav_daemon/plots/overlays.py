"""What the figures and the live viewer draw over a frame, as arrays (no matplotlib, no rerun).

Everything here reads a Result's fields (and the frame conventions of ``pipeline.geometry``); it
never runs a stage. Level frame at the sensor's foot: x forward, y left, metres.
"""

from __future__ import annotations

import functools
import math
from typing import TYPE_CHECKING

import numpy as np
import numpy.typing as npt

from depthnav_daemon.pipeline.geometry import level_rays

if TYPE_CHECKING:
    from depthnav_daemon.pipeline import Result
    from depthnav_daemon.pipeline.scan import LaserScan
    from drivers.base import Intrinsics

F64 = npt.NDArray[np.float64]
BREAK_JUMP_M = 0.25  # neighbouring readings further apart than this are not joined by a line
RANGE_SPAN_M = 1024.0  # larger than any range: bin * this + range sorts by bin, then range
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


@functools.lru_cache(maxsize=4)
def _bin_table(
    intr: Intrinsics, tilt_rad: float, roll_rad: float, angle_min: float, inc: float, n: int
) -> tuple[npt.NDArray[np.int32], npt.NDArray[np.float32]]:
    """Per pixel: the scan bin of its bearing (-1 outside the scan) and its horizontal range per
    millimetre of depth, metres; (H, W) each, read-only."""
    k = level_rays(intr, tilt_rad, roll_rad)
    bins = np.rint((np.arctan2(k[..., 1], k[..., 0]) - angle_min) / inc)
    bins = np.where((bins >= 0) & (bins < n), bins, -1).astype(np.int32)
    per_mm = (np.hypot(k[..., 0], k[..., 1]) * 1e-3).astype(np.float32)
    bins.setflags(write=False)
    per_mm.setflags(write=False)
    return bins, per_mm


def scan_source_pixels(depth_mm: np.ndarray, result: Result) -> npt.NDArray[np.int64]:
    """(K, 2) (row, col) of the obstacle pixel that produced each finite scan reading.

    Among the obstacle pixels (``result.obstacle_mask``, exact method) whose bearing falls in a
    bin, the nearest one when it lies within SOURCE_MATCH_M of that bin's range. Empty without a
    mask or for a float depth image.
    """
    mask, scan, m = result.obstacle_mask, result.scan, result.mount
    if mask is None or depth_mm.dtype != np.uint16:
        return np.empty((0, 2), dtype=np.int64)
    table, per_mm = _bin_table(
        result.intrinsics,
        m.tilt_rad,
        m.roll_rad,
        scan.angle_min,
        scan.angle_increment,
        scan.ranges.size,
    )
    flat = np.flatnonzero(mask)  # flat indexing: 4x faster than (rows, cols) here
    bins = table.ravel()[flat]
    rng = depth_mm.ravel()[flat] * per_mm.ravel()[flat]
    want = np.append(np.asarray(scan.ranges, dtype=np.float32), np.nan)[bins]  # -1: NaN
    with np.errstate(invalid="ignore"):
        near = np.abs(rng - want) <= SOURCE_MATCH_M
    flat, rng, bins = flat[near], rng[near], bins[near]
    order = np.argsort(bins * RANGE_SPAN_M + rng)  # by bin, then by range (lexsort: 10x slower)
    first = flat[order[np.unique(bins[order], return_index=True)[1]]]
    return np.stack(np.divmod(first, mask.shape[1]), axis=1).astype(np.int64)


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


def memory_cells_xy(result: Result) -> tuple[F64, F64, float]:
    """The obstacle memory's remembered cells in the base frame: (obstacle centres (K, 2),
    drop-off centres (M, 2), cell side m), x forward, y left; empty without a memory grid."""
    empty = np.empty((0, 2))
    mem = result.memory
    if mem is None or mem.grid is None or mem.pose is None:
        return empty, empty, 0.0
    snap = mem.grid
    x, y, yaw = mem.pose
    c, s = math.cos(yaw), math.sin(yaw)
    out = []
    for kind in (1, 2):  # pipeline.memory's OBSTACLE, CLIFF
        i, j = np.nonzero(snap.grid == kind)
        ox = snap.origin_m[0] + (i + 0.5) * snap.cell_m - x  # odometry frame, robot at origin
        oy = snap.origin_m[1] + (j + 0.5) * snap.cell_m - y
        out.append(np.stack([c * ox + s * oy, -s * ox + c * oy], axis=1))  # into the base frame
    return out[0], out[1], snap.cell_m
