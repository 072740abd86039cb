"""Depth image to planar laser scan: the paper's eq. 1-5 (``paper``) and a level-frame method (``exact``).

``exact`` back-projects every used pixel, rotates it by tilt and roll into the level frame, keeps
points whose height above the floor is in [min_obstacle_height_m, max_obstacle_height_m] and whose
horizontal range is in [range_min_m, range_max_m], and bins them by bearing. Each pixel covers the
bearings between its left and right edges, so no bin is empty because of the binning itself.

``paper`` is laserscan_kinect as the paper writes it: per-column minimum over a band of rows, ground
removal with margin e_g (eq. 5), tilt compensation factor (eq. 4) with eq. 3's linear row angle, and
the original's column-to-bin map (which leaves empty bins near the centre: kept for comparison).

Range semantics (REP 117): a finite value is the nearest obstacle; +inf = valid readings but no
obstacle within range_max; -inf = an obstacle closer than range_min; NaN = no valid reading.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from depthnav_daemon.errors import ConfigError
from depthnav_daemon.pipeline.geometry import (
    F32,
    F64,
    Mount,
    cam_to_level,
    check_int,
    check_range,
    depth_to_m,
    depth_to_mm,
    paper_floor_depth_m,
    paper_row_angles_rad,
)
from drivers.base import Intrinsics

METHODS = ("exact", "paper")
MAX_SPAN_BINS = 64  # a pixel that looks almost straight down covers many bearings; cap its footprint


@dataclass(frozen=True, slots=True)
class ScanParams:
    """Scan parameters. Shared: method, range limits. ``exact``: height band, rows, bin width.
    ``paper``: the original laserscan_kinect parameters with its shipped params.yaml values.

    Attributes:
        method: "exact" (level-frame, the default) or "paper" (eq. 1-5 as published).
        range_min_m, range_max_m: accepted range, metres (horizontal range for exact, optical
            depth for paper, as in the original).
        min_obstacle_height_m: exact: points lower than this above the floor are floor (the
            height margin that plays the role of the paper's e_g).
        max_obstacle_height_m: exact: points higher than this are ignored (above the robot).
        row_start, row_stop: exact: image rows [row_start, row_stop) used; row_stop -1 = to the bottom.
        row_step, col_step: exact: pixel strides.
        angle_increment_deg: exact: bin width; 0 = the width of the centre pixel.
        scan_height: paper: rows in the band centred on cy.
        depth_img_row_step: paper: row stride in the band.
        ground_remove: paper: eq. 5 ground removal.
        ground_margin_m: paper: e_g, metres of optical depth.
        tilt_compensation: paper: eq. 4 depth scaling.
    """

    method: str = "exact"
    range_min_m: float = 0.4
    range_max_m: float = 5.0
    min_obstacle_height_m: float = 0.05
    max_obstacle_height_m: float = 2.0
    row_start: int = 0
    row_stop: int = -1
    row_step: int = 1
    col_step: int = 1
    angle_increment_deg: float = 0.0
    scan_height: int = 400
    depth_img_row_step: int = 1
    ground_remove: bool = True
    ground_margin_m: float = 0.05
    tilt_compensation: bool = True

    def __post_init__(self) -> None:
        if self.method not in METHODS:
            raise ConfigError(f"scan.method={self.method!r} is not known (accepted: {', '.join(METHODS)})")
        check_range("scan.range_min_m", self.range_min_m, 0.0, 100.0, " m")
        check_range("scan.range_max_m", self.range_max_m, 0.01, 100.0, " m")
        if self.range_min_m >= self.range_max_m:
            raise ConfigError(
                f"scan.range_min_m ({self.range_min_m}) must be below scan.range_max_m ({self.range_max_m})"
            )
        check_range("scan.min_obstacle_height_m", self.min_obstacle_height_m, -10.0, 10.0, " m")
        check_range("scan.max_obstacle_height_m", self.max_obstacle_height_m, -10.0, 10.0, " m")
        if self.min_obstacle_height_m >= self.max_obstacle_height_m:
            raise ConfigError(
                f"scan.min_obstacle_height_m ({self.min_obstacle_height_m}) must be below "
                f"scan.max_obstacle_height_m ({self.max_obstacle_height_m})"
            )
        check_int("scan.row_start", self.row_start, 0, 8191)
        check_int("scan.row_stop", self.row_stop, -1, 8192)
        if self.row_stop != -1 and self.row_stop <= self.row_start:
            raise ConfigError(f"scan.row_stop ({self.row_stop}) must be above scan.row_start ({self.row_start}) or -1")
        check_int("scan.row_step", self.row_step, 1, 64)
        check_int("scan.col_step", self.col_step, 1, 64)
        check_range("scan.angle_increment_deg", self.angle_increment_deg, 0.0, 10.0, " deg")
        check_int("scan.scan_height", self.scan_height, 1, 8192)
        check_int("scan.depth_img_row_step", self.depth_img_row_step, 1, 256)
        check_range("scan.ground_margin_m", self.ground_margin_m, 0.0, 10.0, " m")


@dataclass(frozen=True, slots=True)
class LaserScan:
    """A planar scan in the level frame at the sensor (x forward, y left), like sensor_msgs/LaserScan.

    ``ranges[i]`` is at bearing ``angle_min + i * angle_increment`` (radians, counter-clockwise from
    forward). Values follow REP 117 (see the module docstring).

    Attributes:
        ranges: (N,) float32 metres.
    """

    angle_min: float
    angle_max: float
    angle_increment: float
    range_min: float
    range_max: float
    ranges: F32

    @property
    def angles(self) -> F64:
        """(N,) bearing of every range, radians."""
        return self.angle_min + self.angle_increment * np.arange(self.ranges.size)


def depth_to_scan(depth: np.ndarray, intr: Intrinsics, mount: Mount, params: ScanParams) -> LaserScan:
    """Turn one depth image into a planar scan.

    Args:
        depth: (H, W) uint16 millimetres (0 = no reading) or float32 metres.
        intr: intrinsics of ``depth``.
        mount: sensor height, tilt (positive down) and roll.
        params: method and its parameters.

    Returns:
        The scan (REP 117 values).

    Raises:
        FrameError: wrong dtype or shape. ConfigError: parameters that do not fit this image.
    """
    if params.method == "paper":
        return _paper_scan(depth, intr, mount, params)
    return _exact_scan(depth_to_mm(depth, intr), intr, mount, params)


# --- exact ----------------------------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class _ExactTable:
    """Per-pixel tables for one (intrinsics, mount, params); pixels are the used grid (Hs, Ws)."""

    rows: slice
    cols: slice
    zlo_mm: npt.NDArray[np.uint16]   # (Hs, Ws) obstacle iff zlo <= d <= zhi (empty: zlo > zhi)
    zhi_mm: npt.NDArray[np.uint16]
    near_lo_mm: npt.NDArray[np.uint16]  # (Hs, Ws) obstacle height but closer than range_min iff
    near_hi_mm: npt.NDArray[np.uint16]  # near_lo <= d <= near_hi
    kr_m_per_mm: F32                 # (Hs, Ws) horizontal range per millimetre of depth
    src: npt.NDArray[np.intp]        # (M,) used-pixel flat index, grouped by bin
    offsets: npt.NDArray[np.intp]    # (N,) start of each bin's group in src
    covered: npt.NDArray[np.bool_]   # (N,) bins that some pixel covers
    angle_min: float
    angle_increment: float


def _used_rows(intr: Intrinsics, params: ScanParams) -> slice:
    stop = intr.height if params.row_stop == -1 else min(params.row_stop, intr.height)
    if params.row_start >= stop:
        raise ConfigError(
            f"scan.row_start ({params.row_start}) is outside this {intr.height}-row image "
            f"(accepted: 0..{intr.height - 1})"
        )
    return slice(params.row_start, stop, params.row_step)


def _bearing(intr: Intrinsics, rot: F64, u: F64, v: F64) -> F64:
    """Level-frame bearing (radians) of the rays through pixel coordinates (u, v), any equal shapes."""
    x = (u - intr.cx) / intr.fx
    y = (v - intr.cy) / intr.fy
    fwd = rot[0, 0] * x + rot[0, 1] * y + rot[0, 2]
    left = rot[1, 0] * x + rot[1, 1] * y + rot[1, 2]
    return np.arctan2(left, fwd)


def _depth_bounds_mm(k: F64, lo: float, hi: float) -> tuple[F64, F64]:
    """Depth interval (mm) where lo <= k * z_m <= hi, per pixel; empty intervals have lo > hi."""
    with np.errstate(divide="ignore", invalid="ignore"):
        a = lo / k * 1000.0
        b = hi / k * 1000.0
    zlo = np.where(k > 0, a, np.where(k < 0, b, np.where(lo <= 0 <= hi, 0.0, np.inf)))
    zhi = np.where(k > 0, b, np.where(k < 0, a, np.where(lo <= 0 <= hi, np.inf, -np.inf)))
    return zlo, zhi


@functools.lru_cache(maxsize=16)
def _exact_table(intr: Intrinsics, mount: Mount, params: ScanParams) -> _ExactTable:
    rows = _used_rows(intr, params)
    cols = slice(0, intr.width, params.col_step)
    v = np.arange(intr.height, dtype=np.float64)[rows][:, None]
    u = np.arange(intr.width, dtype=np.float64)[cols][None, :]
    rot = cam_to_level(mount.tilt_rad, mount.roll_rad)
    x = (u - intr.cx) / intr.fx
    y = (v - intr.cy) / intr.fy
    d = np.stack(np.broadcast_arrays(x, y, np.ones_like(x)), axis=-1) @ rot.T  # (Hs, Ws, 3) per metre
    kr = np.hypot(d[..., 0], d[..., 1])
    kh = d[..., 2]
    h = mount.height_m
    hlo, hhi = _depth_bounds_mm(kh, params.min_obstacle_height_m - h, params.max_obstacle_height_m - h)
    rlo, rhi = _depth_bounds_mm(kr, params.range_min_m, params.range_max_m)
    zlo = np.maximum(np.maximum(hlo, rlo), 1.0)
    zhi = np.minimum(hhi, rhi)
    zlo_mm = np.clip(np.ceil(zlo), 1, 65535).astype(np.uint16)
    zhi_mm = np.clip(np.floor(zhi), 0, 65535).astype(np.uint16)
    near_lo_mm = np.clip(np.ceil(np.maximum(hlo, 1.0)), 1, 65535).astype(np.uint16)
    near_hi_mm = np.clip(np.ceil(np.minimum(hhi, rlo)) - 1, 0, 65535).astype(np.uint16)

    half = params.col_step / 2.0
    b_left = _bearing(intr, rot, u - half, v)
    b_right = _bearing(intr, rot, u + half, v)
    lo_b = np.minimum(b_left, b_right)
    hi_b = np.maximum(b_left, b_right)
    centre = _bearing(intr, rot, np.array([intr.cx - 0.5, intr.cx + 0.5]), np.array([intr.cy, intr.cy]))
    inc = (
        math.radians(params.angle_increment_deg)
        if params.angle_increment_deg > 0
        else float(abs(centre[1] - centre[0]))
    )
    sane = (hi_b - lo_b) < math.pi  # footprints across the +-pi seam (looking backwards) are dropped
    angle_min = float(lo_b[sane].min())
    angle_max_edge = float(hi_b[sane].max())
    n = max(1, int(math.ceil((angle_max_edge - angle_min) / inc)))
    # bin i covers [angle_min + (i - 1/2) inc, angle_min + (i + 1/2) inc)
    angle_min = angle_min + inc / 2.0
    first = np.floor((lo_b - angle_min) / inc + 0.5).astype(np.int64)
    last = np.floor((hi_b - angle_min) / inc + 0.5).astype(np.int64)
    first = np.clip(first, 0, n - 1)
    last = np.clip(np.minimum(last, first + MAX_SPAN_BINS - 1), 0, n - 1)
    span = np.where(sane, last - first + 1, 0).ravel()
    pix = np.repeat(np.arange(span.size), span)
    within = np.arange(pix.size) - np.repeat(np.cumsum(span) - span, span)
    bins = first.ravel()[pix] + within
    order = np.argsort(bins, kind="stable")
    src = pix[order].astype(np.intp)
    counts = np.bincount(bins, minlength=n)
    offsets = (np.cumsum(counts) - counts).astype(np.intp)
    covered = counts > 0
    # reduceat needs in-bounds offsets; uncovered bins are masked to NaN afterwards
    offsets = np.minimum(offsets, max(src.size - 1, 0))
    for arr in (zlo_mm, zhi_mm, near_lo_mm, near_hi_mm, src, offsets, covered):
        arr.setflags(write=False)
    kr32 = (kr / 1000.0).astype(np.float32)
    kr32.setflags(write=False)
    return _ExactTable(rows, cols, zlo_mm, zhi_mm, near_lo_mm, near_hi_mm, kr32, src, offsets, covered, angle_min, inc)


def scan_layout(intr: Intrinsics, mount: Mount, params: ScanParams) -> tuple[float, float, int]:
    """(angle_min, angle_increment, number of bins) of the exact scan for this camera and mount."""
    t = _exact_table(intr, mount, params)
    return t.angle_min, t.angle_increment, int(t.covered.size)


def obstacle_pixels(depth: np.ndarray, intr: Intrinsics, mount: Mount, params: ScanParams) -> npt.NDArray[np.bool_]:
    """(H, W) mask of the pixels the exact scan counts as obstacles (for display)."""
    mm = depth_to_mm(depth, intr)
    t = _exact_table(intr, mount, params)
    d = mm[t.rows, t.cols]
    out = np.zeros(mm.shape, dtype=bool)
    out[t.rows, t.cols] = (d >= t.zlo_mm) & (d <= t.zhi_mm)
    return out


def _exact_scan(depth_mm: npt.NDArray[np.uint16], intr: Intrinsics, mount: Mount, params: ScanParams) -> LaserScan:
    t = _exact_table(intr, mount, params)
    d = depth_mm[t.rows, t.cols]                                   # (Hs, Ws) view
    obstacle = (d >= t.zlo_mm) & (d <= t.zhi_mm)
    vals = np.where(d > 0, np.float32(np.inf), np.float32(np.nan))  # valid reading, no obstacle
    vals[(d >= t.near_lo_mm) & (d <= t.near_hi_mm)] = -np.inf     # obstacle closer than range_min
    vals[obstacle] = d[obstacle] * t.kr_m_per_mm[obstacle]
    ranges = np.fmin.reduceat(vals.ravel()[t.src], t.offsets) if t.src.size else np.full(t.covered.size, np.nan)
    ranges = ranges.astype(np.float32, copy=False)
    ranges[~t.covered] = np.nan
    n = ranges.size
    return LaserScan(
        t.angle_min, t.angle_min + (n - 1) * t.angle_increment, t.angle_increment,
        params.range_min_m, params.range_max_m, ranges,
    )


# --- paper ----------------------------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class _PaperTable:
    rows: slice
    dist_to_ground_m: F32   # (B, 1) eq. 5 threshold minus e_g; +inf where the row misses the floor
    tilt_factor: F32        # (B, 1) eq. 4
    range_per_z: F32        # (W,) sqrt(1 + ((u - cx)/fx)^2): eq. 2's x folded into the range
    index: npt.NDArray[np.intp]  # (W,) column -> bin, the original's truncating map
    angle_min: float
    angle_max: float
    angle_increment: float


@functools.lru_cache(maxsize=16)
def _paper_table(intr: Intrinsics, mount: Mount, params: ScanParams) -> _PaperTable:
    half = params.scan_height / 2.0
    if half > intr.cy or half > intr.height - intr.cy:
        limit = int(2 * min(intr.cy, intr.height - intr.cy))
        raise ConfigError(
            f"scan.scan_height={params.scan_height} is too large for this {intr.height}-row image "
            f"with cy={intr.cy:g} (accepted: 1..{limit})"
        )
    offset = int(intr.cy - half)
    rows = slice(offset, offset + params.scan_height, params.depth_img_row_step)
    delta = paper_row_angles_rad(intr)[rows]
    alpha = mount.tilt_rad
    ground = paper_floor_depth_m(mount.height_m, alpha, delta) - params.ground_margin_m
    factor = np.sin(math.pi / 2 - alpha - delta) / np.sin(math.pi / 2 - delta)
    u = np.arange(intr.width, dtype=np.float64)
    angle_max = math.atan(intr.cx / intr.fx)
    angle_min = -math.atan((intr.width - 1 - intr.cx) / intr.fx)
    inc = (angle_max - angle_min) / (intr.width - 1)
    theta = -np.arctan((u - intr.cx) / intr.fx)
    index = np.clip(((theta - angle_min) / inc).astype(np.intp), 0, intr.width - 1)
    return _PaperTable(
        rows,
        ground.astype(np.float32)[:, None],
        factor.astype(np.float32)[:, None],
        np.sqrt(1.0 + ((u - intr.cx) / intr.fx) ** 2).astype(np.float32),
        index,
        angle_min,
        angle_max,
        inc,
    )


def _paper_scan(depth: np.ndarray, intr: Intrinsics, mount: Mount, params: ScanParams) -> LaserScan:
    t = _paper_table(intr, mount, params)
    z = depth_to_m(depth, intr)[t.rows]                           # (B, W) raw optical depth, NaN invalid
    with np.errstate(invalid="ignore"):
        ok = (z >= params.range_min_m) & (z <= params.range_max_m)
        if params.ground_remove:
            ok &= z < t.dist_to_ground_m                          # eq. 5 on raw depth
    zc = z * t.tilt_factor if params.tilt_compensation else z
    zmin = np.where(ok, zc, np.inf).min(axis=0)                   # eq. 1
    any_valid = np.isfinite(z).any(axis=0)
    col_range = np.where(np.isfinite(zmin), zmin * t.range_per_z, np.where(any_valid, np.inf, np.nan))
    ranges = np.full(intr.width, np.nan, dtype=np.float32)
    np.fmin.at(ranges, t.index, col_range.astype(np.float32))
    return LaserScan(t.angle_min, t.angle_max, t.angle_increment, params.range_min_m, params.range_max_m, ranges)
