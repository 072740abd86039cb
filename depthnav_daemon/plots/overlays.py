"""What the figures and the live viewer draw over a frame, as arrays (no matplotlib, no rerun).

Everything here reads a Result's fields (and the frame conventions of ``pipeline.geometry``); it
never runs a stage. Level frame at the sensor's foot: x forward, y left, metres.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
import numpy.typing as npt

from depthnav_daemon.pipeline.geometry import level_rays
from depthnav_daemon.pipeline.placement import points_to_base

if TYPE_CHECKING:
    from depthnav_daemon.pipeline import Result
    from depthnav_daemon.pipeline.params import ScanParams
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


DROP_MARGIN_M = 0.05  # a reading this far below the floor plane is lower floor (cliff's default)
BELOW_HORIZON = 1e-6  # rays pointing down by less than this never meet the floor
AREA_GAP_ROWS = 3  # lower-floor rows this far apart in a column (missing readings) stay one area
AREA_JOIN_COLS = 2  # edge points of columns this close (and within BREAK_JUMP_M) form one area


@dataclass(frozen=True, slots=True)
class DropoffAreas:
    """The drop-offs of one frame as areas of floor, as a costmap would mark them.

    Attributes:
        pixels: (H, W) bool, the lower-floor pixels seen in and under the detected blocks.
        areas: per drop-off, (near (k, 2), far (k, 2)) in the base frame (x forward, y left,
            metres), one pair per image column left to right: ``near`` the edge, the floor point
            of the pixel under the column's nearest lower-floor pixel (at most a pixel's
            footprint before the true edge, never beyond), ``far`` the farthest lower-floor point
            seen; the area is the polygon near + far reversed.
    """

    pixels: npt.NDArray[np.bool_]
    areas: list[tuple[F64, F64]]


def dropoff_areas(
    depth_mm: np.ndarray,
    result: Result,
    reach_m: float = math.inf,
    margin_m: float = DROP_MARGIN_M,
) -> DropoffAreas:
    """Where each detected drop-off's lower floor was seen, from its edge to its far end.

    Reads only the detected blocks, the block under each and the block columns either side (where
    the cliff stage looks for edges), so it costs little per frame. A pixel is lower floor when its
    reading lies more than ``margin_m`` below the floor plane of the frame's mount. The far ends
    are brought in to ``reach_m`` from the sensor (a view's range).
    """
    cliff = result.cliff
    depth = np.asarray(depth_mm)
    h, w = depth.shape
    none = DropoffAreas(np.zeros((h, w), dtype=bool), [])
    if cliff is None or depth.dtype != np.uint16 or len(cliff.blocks) == 0:
        return none
    bs = int(cliff.block_size)
    region = np.zeros((h, w), dtype=bool)
    for r, c in np.asarray(cliff.blocks).reshape(-1, 2):
        region[r : r + 2 * bs, max(0, c - bs) : c + 2 * bs] = True
    m = result.mount
    k = level_rays(result.intrinsics, m.tilt_rad, m.roll_rad)
    cols, rows = np.nonzero(region.T)  # by column, then row: no sort needed below
    kz = k[rows, cols, 2]
    d = depth[rows, cols] * 1e-3
    lower = (d > 0.0) & (kz < -BELOW_HORIZON) & (d * -kz > m.height_m + margin_m)
    # reversed: by column, bottom row first (going up each column from the robot)
    rows, cols, d = rows[lower][::-1], cols[lower][::-1], d[lower][::-1]
    if rows.size == 0:
        return none
    pixels = np.zeros((h, w), dtype=bool)
    new_col = np.r_[True, cols[1:] != cols[:-1]]
    starts = np.flatnonzero(new_col)  # each column's bottom-most (nearest) lower-floor pixel
    # the edge: the floor point of the pixel under it (nearer), as the cliff stage's edges: the
    # edge hiding the lower floor lies between the two rays, so this is at most a pixel's
    # footprint before it and never beyond
    under = np.minimum(rows[starts] + 1, h - 1)
    k_under = k[under, cols[starts]]
    near = (m.height_m / -np.minimum(k_under[:, 2], -BELOW_HORIZON))[:, None] * k_under[:, :2]
    # the nearest drop-off's lower floor: the run of lower-floor rows going up from there (a
    # floor reading ends it: a hole's far side, then the next drop-off's lower floor); its top
    # row sees farthest
    run_start = new_col | np.r_[True, rows[:-1] - rows[1:] > AREA_GAP_ROWS]
    run_starts = np.flatnonzero(run_start)
    ends = np.r_[run_starts, rows.size][np.searchsorted(run_starts, starts) + 1] - 1
    run = np.cumsum(run_start) - 1
    in_first = run == run[starts][np.cumsum(new_col) - 1]
    pixels[rows[in_first], cols[in_first]] = True
    far = (d[ends])[:, None] * k[rows[ends], cols[ends], :2]
    with np.errstate(divide="ignore"):
        far = far * np.minimum(1.0, reach_m / np.hypot(far[:, 0], far[:, 1]))[:, None]
    if m.placed:
        near = points_to_base(near, m).astype(np.float64)
        far = points_to_base(far, m).astype(np.float64)
    ucols = cols[starts][::-1]  # left to right in the image: columns ascending
    near, far = near[::-1], far[::-1]
    r_near = np.hypot(near[:, 0], near[:, 1])
    breaks = (np.diff(ucols) > AREA_JOIN_COLS) | (np.abs(np.diff(r_near)) > BREAK_JUMP_M)
    cuts = np.flatnonzero(breaks) + 1
    areas = [(n, f) for n, f in zip(np.split(near, cuts), np.split(far, cuts), strict=True)]
    return DropoffAreas(pixels, areas)


def area_polygon(near: F64, far: F64) -> F64:
    """(2k + 1, 2) closed outline of one drop-off area (near edge, then far edge back)."""
    return np.vstack([near, far[::-1], near[:1]])


def too_close_xy(scan: LaserScan, radius_m: float) -> F64:
    """(K, 2) points at ``radius_m`` on the bearings whose reading is -inf (too close to see)."""
    r = np.asarray(scan.ranges, dtype=np.float64)
    a = scan.angles[np.isneginf(r)]
    return np.stack([radius_m * np.cos(a), radius_m * np.sin(a)], axis=1)


def to_odom(xy: np.ndarray, pose: tuple[float, float, float]) -> F64:
    """Base-frame points (K, 2) into the odometry frame of ``pose`` (x_m, y_m, yaw_rad)."""
    p = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
    c, s = math.cos(pose[2]), math.sin(pose[2])
    return np.stack([pose[0] + c * p[:, 0] - s * p[:, 1], pose[1] + s * p[:, 0] + c * p[:, 1]], 1)


def memory_cells_odom(result: Result) -> tuple[F64, F64, float]:
    """The memory's remembered cells in the odometry frame: (obstacle centres (K, 2), drop-off
    centres (M, 2), cell side m); empty without a memory grid."""
    empty = np.empty((0, 2))
    mem = result.memory
    if mem is None or mem.grid is None:
        return empty, empty, 0.0
    snap = mem.grid
    out = []
    for kind in (1, 2):  # pipeline.memory's OBSTACLE, CLIFF
        i, j = np.nonzero(snap.grid == kind)
        out.append(
            np.stack(
                [
                    snap.origin_m[0] + (i + 0.5) * snap.cell_m,
                    snap.origin_m[1] + (j + 0.5) * snap.cell_m,
                ],
                axis=1,
            )
        )
    return out[0], out[1], snap.cell_m


SOURCE_NAMES = {
    "default": "default (not configured)",
    "config": "configured",
    "floor": "from the floor",
    "accel": "from the accelerometer",
    "serial": "from the serial IMU",
}


def untrusted(result: Result) -> bool:
    """Whether the frame's ranges and drop-offs rest on a mount that is not trusted (drawn
    amber): the floor contradicts it, or nothing configured or confirmed it yet."""
    trust = result.mount_trust
    return trust is not None and not trust.dropoffs_trusted


def trust_line(result: Result) -> str:
    """One short line on the mount's trust, for titles: where the mount came from and whether
    its drop-offs and scan are trusted."""
    trust = result.mount_trust
    source = SOURCE_NAMES.get(result.mount_source, result.mount_source)
    if trust is None:
        return f"mount {source}"
    source = SOURCE_NAMES.get(trust.source, trust.source) + (", pinned" if trust.pinned else "")
    if not trust.trusted:
        return f"mount {source}, not confirmed by the floor: ranges unknown, drop-offs NOT trusted"
    if not trust.dropoffs_trusted:
        if trust.floor_height_m is not None and trust.floor_tilt_deg is not None:
            return (
                f"mount {source} contradicted by the floor ({trust.floor_height_m:.2f} m, "
                f"{trust.floor_tilt_deg:.1f}°): drop-offs and scan NOT trusted"
            )
        return f"mount {source}: drop-offs and scan NOT trusted"
    return f"mount {source}, floor {trust.floor}: drop-offs and scan trusted"


def obstacle_pixels_of(
    depth_mm: np.ndarray, result: Result, scan_params: ScanParams | None = None
) -> tuple[npt.NDArray[np.bool_] | None, npt.NDArray[np.int64]]:
    """The pixels the scan counts as obstacles, (H, W) bool or None, and (K, 2) (row, col) of
    the pixel each reading came from.

    exact: the Result's mask and :func:`scan_source_pixels`. paper (no mask in the Result; needs
    ``scan_params``): every reading of the band's rows that eq. 5 keeps (in range, above the
    ground threshold), and per column the one that gives its range (the band's minimum).
    """
    depth = np.asarray(depth_mm)
    paper = scan_params is not None and scan_params.method == "paper"
    if result.obstacle_mask is not None or not paper or depth.dtype != np.uint16:
        return result.obstacle_mask, scan_source_pixels(depth, result)
    # the paper scan's own thresholds (per band row), so the pixels are exactly the ones it read
    from depthnav_daemon.pipeline.scan_paper import _paper_table

    assert scan_params is not None
    t = _paper_table(result.intrinsics, result.mount.level_part(), scan_params)
    rows = t.row0 + np.arange(t.lo_mm.size) * t.row_step
    band = depth[rows]  # (B, W)
    ok = (t.lo_mm[:, None] <= band) & (band <= t.hi_mm[:, None])
    mask = np.zeros(depth.shape, dtype=bool)
    mask[rows] = ok
    z = np.where(ok, band * t.factor[:, None], np.inf)
    best = np.argmin(z, axis=0)
    cols = np.flatnonzero(np.isfinite(z[best, np.arange(depth.shape[1])]))
    return mask, np.stack([rows[best[cols]], cols], axis=1).astype(np.int64)
