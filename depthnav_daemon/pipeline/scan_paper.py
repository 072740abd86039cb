"""The paper's scan (laserscan_kinect, eq. 1-5), the ``paper`` method of ``scan.depth_to_scan``.

Per-column minimum over a band of rows, ground removal with margin e_g (eq. 5), the tilt
compensation factor (eq. 4) with eq. 3's linear row angle, and the original's column-to-bin map
(which leaves empty bins near the centre: kept for comparison with the ``exact`` method).
Pinhole on purpose: it ignores the intrinsics' lens coefficients, as the original C++ does, so
it reproduces the original exactly (the ``exact`` method undistorts its rays).
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
    Mount,
    depth_to_mm,
    paper_floor_depth_m,
    paper_row_angles_rad,
)
from depthnav_daemon.pipeline.laser_scan import LaserScan
from depthnav_daemon.pipeline.params import ScanParams
from depthnav_daemon.pipeline.scan_kernels import paper_scan_kernel
from depthnav_daemon.pipeline.scan_table import scan_rows
from drivers.base import UINT16_MAX, Intrinsics


@dataclass(frozen=True, slots=True, kw_only=True)
class _PaperTable:
    row0: int
    row_step: int
    lo_mm: npt.NDArray[np.uint16]  # (B,) a reading counts iff lo <= d <= hi: range_min ..
    hi_mm: npt.NDArray[np.uint16]  # (B,) .. min(range_max, eq. 5 ground threshold minus e_g)
    factor: F32  # (B,) metres per mm times eq. 4's tilt factor
    range_per_z: F32  # (W,) sqrt(1 + ((u - cx)/fx)^2): eq. 2's x folded into the range
    index: npt.NDArray[np.int64]  # (W,) column -> bin, the original's truncating map
    angle_min: float
    angle_max: float
    angle_increment: float


@functools.lru_cache(maxsize=16)
def _paper_table(intr: Intrinsics, mount: Mount, params: ScanParams) -> _PaperTable:
    if intr.width < 2:  # noqa: PLR2004 - the bins span the first to the last column
        raise ConfigError(
            f"scan.method='paper' needs an image at least 2 pixels wide, this one is {intr.width}",
            hint="use scan.method = 'exact' for this sensor",
        )
    rows = scan_rows(intr, params)
    delta = paper_row_angles_rad(intr)[rows]
    alpha = mount.tilt_rad
    b = delta.size
    # z = d / 1000 m: range_min <= z <= range_max and (eq. 5) z < ground - e_g, as whole millimetres
    lo = max(1, math.ceil(params.range_min_m * 1000.0 - 1e-6))
    hi = np.full(b, min(65535, math.floor(params.range_max_m * 1000.0 + 1e-6)), dtype=np.float64)
    if params.ground_remove:
        ground = paper_floor_depth_m(mount.height_m, alpha, delta) - params.ground_margin_m
        with np.errstate(invalid="ignore"):
            hi = np.minimum(hi, np.where(np.isfinite(ground), np.ceil(ground * 1000.0) - 1, 65535))
    factor = np.full(b, 0.001)
    if params.tilt_compensation:
        factor = factor * np.sin(math.pi / 2 - alpha - delta) / np.sin(math.pi / 2 - delta)  # eq. 4
    u = np.arange(intr.width, dtype=np.float64)
    angle_max = math.atan(intr.cx / intr.fx)
    angle_min = -math.atan((intr.width - 1 - intr.cx) / intr.fx)
    inc = (angle_max - angle_min) / (intr.width - 1)
    theta = -np.arctan((u - intr.cx) / intr.fx)
    index = np.clip(((theta - angle_min) / inc).astype(np.int64), 0, intr.width - 1)
    return _PaperTable(
        row0=rows.start,
        row_step=params.depth_img_row_step,
        lo_mm=np.full(b, lo, dtype=np.uint16),
        hi_mm=np.clip(hi, 0, UINT16_MAX).astype(np.uint16),
        factor=factor.astype(np.float32),
        range_per_z=np.sqrt(1.0 + ((u - intr.cx) / intr.fx) ** 2).astype(np.float32),
        index=index,
        angle_min=angle_min,
        angle_max=angle_max,
        angle_increment=inc,
    )


def paper_scan(depth: np.ndarray, intr: Intrinsics, mount: Mount, params: ScanParams) -> LaserScan:
    """The paper's scan of one (H, W) uint16 mm or float32 m frame (REP 117 values)."""
    t = _paper_table(intr, mount, params)
    ranges = np.empty(intr.width, dtype=np.float32)
    scratch = np.empty((2, intr.width), dtype=np.float32)
    paper_scan_kernel(
        depth_to_mm(depth, intr),
        t.row0,
        t.row_step,
        t.lo_mm,
        t.hi_mm,
        t.factor,
        t.range_per_z,
        t.index,
        scratch,
        ranges,
    )
    return LaserScan(
        t.angle_min, t.angle_max, t.angle_increment, params.range_min_m, params.range_max_m, ranges
    )
