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

import numpy as np
import numpy.typing as npt

from depthnav_daemon.pipeline.geometry import Mount, depth_to_mm

# LaserScan and ScanParams live apart for scan_paper and scan_table; importable here as before
from depthnav_daemon.pipeline.laser_scan import LaserScan
from depthnav_daemon.pipeline.params import ScanParams
from depthnav_daemon.pipeline.scan_kernels import (
    exact_scan_kernel,
)
from depthnav_daemon.pipeline.scan_paper import paper_scan
from depthnav_daemon.pipeline.scan_table import exact_table
from drivers.base import Intrinsics


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
    far = np.empty_like(out)
    acc_far = np.empty_like(acc)
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
        t.reach_start,
        t.reach_code,
        t.short,
        np.float32(params.range_max_m),
        acc,
        out,
        acc_far,
        far,
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
        far[:-1],
    )
