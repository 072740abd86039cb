"""Depth image to planar laser scan: a level-frame method (``exact``) and the paper's eq. 1-5
(``paper``).

``exact`` back-projects every used pixel, rotates it by tilt and roll into the level frame, keeps
points whose height above the floor is in [min_obstacle_height_m, max_obstacle_height_m] and whose
horizontal range is in [range_min_m, range_max_m], and bins them by bearing. Each pixel covers the
bearings between its left and right edges, so no bin is empty because of the binning itself.

``paper`` is laserscan_kinect as the paper writes it: per-column minimum over a band of rows, ground
removal with margin e_g (eq. 5), tilt compensation factor (eq. 4) with eq. 3's linear row angle, and
the original's column-to-bin map (which leaves empty bins near the centre: kept for comparison). It
lives in ``scan_paper.py``.

Range semantics (REP 117): a finite value is the nearest obstacle; +inf = valid readings but no
obstacle within range_max; -inf = an obstacle closer than range_min; NaN = no valid reading.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from depthnav_daemon.errors import ConfigError
from depthnav_daemon.pipeline.geometry import (
    F32,
    F64,
    Mount,
    check_int,
    check_order,
    check_range,
    depth_to_mm,
)
from depthnav_daemon.pipeline.scan_kernels import (
    exact_scan_kernel,
)
from depthnav_daemon.pipeline.scan_table import exact_table
from drivers.base import Intrinsics

METHODS = ("exact", "paper")
MIN_ANGLE_INCREMENT_DEG = 0.001  # finer gives more bins than the kernels hold (scan_table.MAX_BINS)


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
        row_start, row_stop: exact: image rows [row_start, row_stop) used; row_stop -1 = to the
            bottom.
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
            raise ConfigError(
                f"scan.method={self.method!r} is not known (accepted: {', '.join(METHODS)})"
            )
        check_range("scan.range_min_m", self.range_min_m, 0.0, 100.0, " m")
        check_range("scan.range_max_m", self.range_max_m, 0.01, 100.0, " m")
        check_order("scan.range_min_m", self.range_min_m, "scan.range_max_m", self.range_max_m)
        check_range("scan.min_obstacle_height_m", self.min_obstacle_height_m, -10.0, 10.0, " m")
        check_range("scan.max_obstacle_height_m", self.max_obstacle_height_m, -10.0, 10.0, " m")
        check_order(
            "scan.min_obstacle_height_m",
            self.min_obstacle_height_m,
            "scan.max_obstacle_height_m",
            self.max_obstacle_height_m,
        )
        check_int("scan.row_start", self.row_start, 0, 8191)
        check_int("scan.row_stop", self.row_stop, -1, 8192)
        if self.row_stop != -1 and self.row_stop <= self.row_start:
            raise ConfigError(
                f"scan.row_stop ({self.row_stop}) must be above scan.row_start "
                f"({self.row_start}) or -1"
            )
        check_int("scan.row_step", self.row_step, 1, 64)
        check_int("scan.col_step", self.col_step, 1, 64)
        check_range("scan.angle_increment_deg", self.angle_increment_deg, 0.0, 10.0, " deg")
        if 0.0 < self.angle_increment_deg < MIN_ANGLE_INCREMENT_DEG:  # 5e-324: 0 rad, a / 0
            raise ConfigError(
                f"scan.angle_increment_deg={self.angle_increment_deg!r} is out of range "
                f"(accepted: 0 = the centre pixel's width, or {MIN_ANGLE_INCREMENT_DEG:g}..10 deg)"
            )
        check_int("scan.scan_height", self.scan_height, 1, 8192)
        check_int("scan.depth_img_row_step", self.depth_img_row_step, 1, 256)
        check_range("scan.ground_margin_m", self.ground_margin_m, 0.0, 10.0, " m")


@dataclass(frozen=True, slots=True)
class LaserScan:
    """A planar scan in the level frame at the sensor (x forward, y left), as sensor_msgs/LaserScan.

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


def depth_to_scan(
    depth: np.ndarray, intr: Intrinsics, mount: Mount, params: ScanParams
) -> LaserScan:
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
        # imported here: scan_paper builds on this module's ScanParams and LaserScan
        from depthnav_daemon.pipeline.scan_paper import paper_scan

        return paper_scan(depth, intr, mount, params)
    return _exact_scan(depth_to_mm(depth, intr), intr, mount, params)


def scan_layout(intr: Intrinsics, mount: Mount, params: ScanParams) -> tuple[float, float, int]:
    """(angle_min, angle_increment, number of bins) of the exact scan for this camera and mount."""
    t = exact_table(intr, mount, params)
    return t.angle_min, t.angle_increment, t.n_bins


def obstacle_pixels(
    depth: np.ndarray, intr: Intrinsics, mount: Mount, params: ScanParams
) -> npt.NDArray[np.bool_]:
    """(H, W) mask of the pixels the exact scan counts as obstacles (for display)."""
    mm = depth_to_mm(depth, intr)
    t = exact_table(intr, mount, params)
    cols = slice(t.col0, intr.width, t.col_step)
    d = mm[t.rows][:, cols]
    out = np.zeros(mm.shape, dtype=bool)
    out[np.ix_(t.rows, np.arange(intr.width)[cols])] = (d >= t.zlo_mm) & (d <= t.zhi_mm)
    return out


def _exact_scan(
    depth_mm: npt.NDArray[np.uint16], intr: Intrinsics, mount: Mount, params: ScanParams
) -> LaserScan:
    t = exact_table(intr, mount, params)
    out = np.empty(t.n_bins + 1, dtype=np.float32)  # + a scratch slot for runs feeding no bin
    acc = np.empty(t.zlo_mm.shape[1], dtype=np.float32)
    exact_scan_kernel(
        depth_mm[:, t.col0 :: t.col_step],
        t.rows,
        t.k_lo,
        t.k_mid,
        t.k_hi,
        t.kr_m_per_mm,
        t.blk,
        t.fl_blk,
        t.fl_code,
        t.probe_start,
        t.probe,
        t.spans,
        acc,
        out,
    )
    ranges = out[:-1]
    n = ranges.size
    return LaserScan(
        t.angle_min,
        t.angle_min + (n - 1) * t.angle_increment,
        t.angle_increment,
        params.range_min_m,
        params.range_max_m,
        ranges,
    )
