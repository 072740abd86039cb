"""The exact scan's tables: for one camera, mount and parameters, which depths make each used pixel
an obstacle, and which bearing bins each pixel's footprint feeds (built once, cached)."""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
import numpy.typing as npt

from depthnav_daemon.errors import ConfigError
from depthnav_daemon.pipeline.geometry import (
    F32,
    F64,
    Mount,
    cam_to_level,
    frozen_table,
    normalized_coords,
)
from depthnav_daemon.pipeline.scan_kernels import (
    MAX_CODE_INDEX,
    bin_map_kernel,
    run_flush_codes,
)
from drivers.base import Intrinsics

if TYPE_CHECKING:
    from depthnav_daemon.pipeline.scan import ScanParams

MAX_BINS = 32000  # bins fit the kernels' packed codes (below 32768), with a scratch slot


@dataclass(frozen=True, slots=True, kw_only=True)
class ExactTable:
    """Per-pixel tables for one (intrinsics, mount, params) over the used grid (Hs, Ws) of pixels.

    Binning: bin b is centred on ``angle_min + b * angle_increment`` (by default the angular width
    of the pixel at the principal point). In each row a bin takes the pixels whose centres fall in
    it, or, where pixels are wider than bins (the lower rows of a tilted camera), the pixel whose
    footprint covers the bin's centre. Every pixel is used and no bin is empty because of the
    binning.

    The kernel walks the image row by row and keeps a minimum per column while the column feeds the
    same bins (a "run"); the flush codes say where each run's minimum goes when it ends.
    """

    rows: npt.NDArray[np.int32]  # (Hs,) image rows
    col0: int
    col_step: int
    zlo_mm: npt.NDArray[np.uint16]  # (Hs, Ws) obstacle iff zlo <= d <= zhi (empty: zlo > zhi)
    zhi_mm: npt.NDArray[np.uint16]
    near_lo_mm: npt.NDArray[np.uint16]  # (Hs, Ws) obstacle height but closer than range_min iff
    near_hi_mm: npt.NDArray[np.uint16]  # near_lo <= d <= near_hi
    k_lo: npt.NDArray[np.uint16]  # (Hs, Ws) the kernel's form: close iff k_lo <= d <= k_mid,
    k_mid: npt.NDArray[np.uint16]  # obstacle iff k_mid < d <= k_hi (2 bytes a pixel less to read)
    k_hi: npt.NDArray[np.uint16]
    kr_m_per_mm: F32  # (Hs, Ws) horizontal range per millimetre of depth
    fl_start: npt.NDArray[np.int32]  # (Hs + 1,) flushes after row i: fl_start[i]:fl_start[i + 1]
    fl_code: npt.NDArray[np.int32]  # (F,) column | run ends << 15 | bin << 16 (run_flush_codes)
    n_bins: int
    angle_min: float
    angle_increment: float


def scan_rows(intr: Intrinsics, params: ScanParams) -> slice:
    """The image rows the scan reads (start, stop, step), for either method.

    Raises:
        ConfigError: a row band that does not fit this image.
    """
    if params.method == "paper":
        half = params.scan_height / 2.0
        if half > intr.cy or half > intr.height - intr.cy:
            limit = int(2 * min(intr.cy, intr.height - intr.cy))
            raise ConfigError(
                f"scan.scan_height={params.scan_height} is too large for this {intr.height}-row "
                f"image with cy={intr.cy:g} (accepted: 1..{limit})"
            )
        offset = int(intr.cy - half)  # the original's truncation
        return slice(offset, offset + params.scan_height, params.depth_img_row_step)
    stop = intr.height if params.row_stop == -1 else min(params.row_stop, intr.height)
    if params.row_start >= stop:
        raise ConfigError(
            f"scan.row_start ({params.row_start}) is outside this {intr.height}-row image "
            f"(accepted: 0..{intr.height - 1})"
        )
    return slice(params.row_start, stop, params.row_step)


def _bearing(intr: Intrinsics, rot: F64, u: F64, v: F64) -> F64:
    """Level-frame bearing (radians) of the rays through pixel coordinates (u, v), equal shapes."""
    x, y = normalized_coords(intr, u, v)
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


def _bin_map(
    centre: F64,
    lo_b: F64,
    hi_b: F64,
    sane: npt.NDArray[np.bool_],
    angle_min: float,
    inc: float,
    n: int,
) -> tuple[
    npt.NDArray[np.int16], npt.NDArray[np.int16], npt.NDArray[np.int16], npt.NDArray[np.int16]
]:
    """Per row and bin, the interval of columns feeding the bin; per column, the bins it feeds.

    Args:
        centre, lo_b, hi_b: (Hs, Ws) bearing of each pixel's centre and footprint edges, radians.
        sane: (Hs, Ws) pixels to use.
        angle_min, inc, n: bin b is centred on angle_min + b * inc.

    Returns:
        g_lo, g_hi: (Hs, n) first and last column feeding each bin (Ws, Ws where none);
        cb_lo, cb_hi: (Hs, Ws) first and last bin a column feeds (n, -1 where none).
    """
    hs, ws = centre.shape
    g_lo = np.empty((hs, n), dtype=np.int64)
    g_hi = np.empty((hs, n), dtype=np.int64)
    cb_lo = np.empty((hs, ws), dtype=np.int64)
    cb_hi = np.empty((hs, ws), dtype=np.int64)
    # compiled: a mount change rebuilds this table on the frame path (numpy took ~40 ms a frame)
    bin_map_kernel(
        np.ascontiguousarray(centre, dtype=np.float64),
        np.ascontiguousarray(lo_b, dtype=np.float64),
        np.ascontiguousarray(hi_b, dtype=np.float64),
        np.ascontiguousarray(sane),
        float(angle_min),
        float(inc),
        g_lo,
        g_hi,
        cb_lo,
        cb_hi,
    )
    g_hi = np.where(g_hi < 0, ws, g_hi)
    return (
        g_lo.astype(np.int16),
        g_hi.astype(np.int16),
        cb_lo.astype(np.int16),
        cb_hi.astype(np.int16),
    )


@functools.lru_cache(maxsize=16)
def exact_table(intr: Intrinsics, mount: Mount, params: ScanParams) -> ExactTable:
    rows = scan_rows(intr, params)
    cols = slice(0, intr.width, params.col_step)
    v = np.arange(intr.height, dtype=np.float64)[rows][:, None]
    u = np.arange(intr.width, dtype=np.float64)[cols][None, :]
    if u.size > MAX_CODE_INDEX:
        raise ConfigError(
            f"the exact scan uses {u.size} columns of this {intr.width}-pixel-wide image "
            f"(accepted: up to {MAX_CODE_INDEX}); raise scan.col_step"
        )
    rot = cam_to_level(mount.tilt_rad, mount.roll_rad)
    x, y = normalized_coords(intr, u, v)
    d = np.stack((x, y, np.ones_like(x)), axis=-1) @ rot.T  # (Hs, Ws, 3) per metre
    kr = np.hypot(d[..., 0], d[..., 1])
    kh = d[..., 2]
    h = mount.height_m
    hlo, hhi = _depth_bounds_mm(
        kh, params.min_obstacle_height_m - h, params.max_obstacle_height_m - h
    )
    rlo, rhi = _depth_bounds_mm(kr, params.range_min_m, params.range_max_m)
    zlo = np.maximum(np.maximum(hlo, rlo), 1.0)
    zhi = np.minimum(hhi, rhi)
    zlo_mm = np.clip(np.ceil(zlo), 1, 65535).astype(np.uint16)
    zhi_mm = np.clip(np.floor(zhi), 0, 65535).astype(np.uint16)
    near_lo_mm = np.clip(np.ceil(np.maximum(hlo, 1.0)), 1, 65535).astype(np.uint16)
    near_hi_mm = np.clip(np.ceil(np.minimum(hhi, rlo)) - 1, 0, 65535).astype(np.uint16)
    # the kernel's three thresholds: close iff k_lo <= d <= k_mid, obstacle iff k_mid < d <= k_hi.
    # Z = [zlo, zhi] and N = [near_lo, near_hi] adjoin whenever both are non-empty (N holds the
    # depths below range_min, zlo = ceil(rlo) = near_hi + 1; with clipping at 65535 N covers Z),
    # and "close" wins over "obstacle", so Z minus N is (near_hi, zhi]; with N empty it is
    # (zlo - 1, zhi]; with Z empty, (k_mid, 0] is empty
    near = near_lo_mm <= near_hi_mm
    k_lo = np.where(near, near_lo_mm, zlo_mm).astype(np.uint16)
    k_mid = np.where(near, near_hi_mm, zlo_mm.astype(np.int64) - 1).astype(np.uint16)
    k_hi = np.where(zlo_mm <= zhi_mm, zhi_mm, 0).astype(np.uint16)

    half = params.col_step / 2.0
    b_left = _bearing(intr, rot, u - half, v)
    b_right = _bearing(intr, rot, u + half, v)
    lo_b = np.minimum(b_left, b_right)
    hi_b = np.maximum(b_left, b_right)
    sane = (
        hi_b - lo_b
    ) < math.pi  # footprints across the +-pi seam (looking backwards) are dropped
    principal = _bearing(
        intr, rot, np.array([intr.cx - half, intr.cx + half]), np.array([intr.cy, intr.cy])
    )
    inc = (
        math.radians(params.angle_increment_deg)
        if params.angle_increment_deg > 0
        else float(abs(principal[1] - principal[0]))
    )
    edge_min = float(lo_b[sane].min())
    n = max(1, math.ceil((float(hi_b[sane].max()) - edge_min) / inc))
    if n > MAX_BINS:
        raise ConfigError(
            f"scan.angle_increment_deg={params.angle_increment_deg} gives {n} bins "
            f"(accepted: up to {MAX_BINS})"
        )
    angle_min = edge_min + inc / 2.0
    centre = _bearing(intr, rot, u + 0.0 * v, v + 0.0 * u)
    _, _, cb_lo, cb_hi = _bin_map(centre, lo_b, hi_b, sane, angle_min, inc, n)
    fl_start, fl_code = run_flush_codes(cb_lo, cb_hi, n)
    kr32 = (kr / 1000.0).astype(np.float32)
    row_idx = np.arange(intr.height, dtype=np.int32)[rows]
    table = ExactTable(
        rows=row_idx,
        col0=0,
        col_step=params.col_step,
        zlo_mm=zlo_mm,
        zhi_mm=zhi_mm,
        near_lo_mm=near_lo_mm,
        near_hi_mm=near_hi_mm,
        k_lo=k_lo,
        k_mid=k_mid,
        k_hi=k_hi,
        kr_m_per_mm=kr32,
        fl_start=fl_start,
        fl_code=fl_code,
        n_bins=n,
        angle_min=angle_min,
        angle_increment=inc,
    )
    return frozen_table(table)  # cached and shared between calls
