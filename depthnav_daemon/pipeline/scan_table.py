"""The exact scan's tables: for one camera, mount and parameters, which depths make each used pixel
an obstacle, and which bearing bins each pixel's footprint feeds (built once, cached)."""

from __future__ import annotations

import dataclasses
import functools
import math
import threading
from collections import OrderedDict
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, TypeVar

import numpy as np
import numpy.typing as npt

from depthnav_daemon.errors import ConfigError
from depthnav_daemon.pipeline.coverage import floor_extent, seen_to
from depthnav_daemon.pipeline.geometry import (
    F32,
    F64,
    Mount,
    cam_to_level,
    frozen_table,
    normalized_coords,
    pixel_rays,
)
from depthnav_daemon.pipeline.params import ScanParams
from depthnav_daemon.pipeline.scan_blocks import block_tables
from depthnav_daemon.pipeline.scan_kernels import CODE_BITS, MAX_CODE_INDEX
from depthnav_daemon.pipeline.table_kernels import (
    bin_map_kernel,
    exact_codes_kernel,
    reach_limits_kernel,
)
from drivers.base import Intrinsics

MAX_BINS = 32000  # bins fit the kernels' packed codes (below 32768), with a scratch slot
# The most memory the exact scan's and the cliff stage's tables take per pixel of the image at the
# peak of their building, kept tables and scratch (a pinhole camera, the default [cliff] band; a
# lens adds 16 B for the edge rays). Not counted: the camera rays they read, geometry.pixel_rays
# (24 B a pixel, made first, shared with the pose stage). `depthnav bench` measures both
TABLE_BUDGET_B_PER_PX = 64


@dataclass(frozen=True, slots=True, kw_only=True)
class ExactTable:
    """Per-pixel tables for one (intrinsics, mount, params) over the used grid (Hs, Ws) of pixels.

    Binning: bin b is centred on ``angle_min + b * angle_increment`` (by default the angular width
    of the pixel at the principal point). In each row a bin takes the pixels whose centres fall in
    it, or, where pixels are wider than bins (the lower rows of a tilted camera), the pixel whose
    footprint covers the bin's centre. Every pixel is used and no bin is empty because of the
    binning.

    The kernel walks the image row by row and keeps a minimum per column while the column feeds the
    same bins (a "run"); the flush codes say where each run's minimum goes when it ends. The block
    tables let it skip the blocks of a row that cannot hold an obstacle (scan_blocks).
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
    blk: npt.NDArray[np.uint16]  # (4, Hs, nb) block bounds (scan_blocks.block_tables)
    fl_blk: npt.NDArray[np.int32]  # (Hs * nb + 1,) where each block's flushes of a row start
    probe_start: npt.NDArray[np.int32]  # (n + 1,) the runs feeding each bin: probe[:, s[b]:s[b+1]]
    probe_lim: npt.NDArray[np.int16]  # (P,) each run's last row looking to range_max (reach_limits)
    reach_start: npt.NDArray[np.int32]  # (Hs + 1,) the runs' range_max rows by row (reach_codes)
    reach_code: npt.NDArray[np.int32]  # (E,) col | bin << 15
    probe: npt.NDArray[np.int16]  # (3, P) column, first and last row of each run
    spans: npt.NDArray[np.int16]  # (2, n) first and last row of each bin's runs
    n_bins: int
    angle_min: float
    angle_increment: float
    # bins whose floor the read rows do not see out to range_max (coverage.floor_extent): a bin
    # there that found no obstacle is unknown (NaN), not clear (+inf); the safety contract
    short_view: npt.NDArray[np.intp] = field(default_factory=lambda: np.empty(0, np.intp))
    short: npt.NDArray[np.bool_] = field(default_factory=lambda: np.zeros(0, np.bool_))  # (n,)


# tables kept for mounts met before (a mount tracker returns to them): at most this many bytes
# of them, the newest two whatever their size (the one serving and the one being built)
TABLE_CACHE_BYTES = 256 << 20
KEEP_NEWEST = 2

_T = TypeVar("_T")


def table_bytes(table: object) -> int:
    """Bytes of the numpy arrays a table dataclass holds (its own or viewed: views of shared
    arrays count as their size, the safe side)."""
    return sum(
        v.nbytes
        for f in dataclasses.fields(table)  # type: ignore[arg-type]
        if isinstance(v := getattr(table, f.name), np.ndarray)
    )


def table_cache(max_entries: int, max_bytes: int = TABLE_CACHE_BYTES) -> Callable[..., Any]:
    """functools.lru_cache for table builders, bounded by bytes as well as entries: 16 cached
    tables of a 4096x8192 camera were 10 GB. Keeps ``cache_info()`` and ``cache_clear()``."""

    def wrap(build: Callable[..., _T]) -> Callable[..., _T]:
        tables: OrderedDict[tuple[Any, ...], tuple[_T, int]] = OrderedDict()
        lock = threading.Lock()
        counts = [0, 0]  # hits, misses

        @functools.wraps(build)
        def cached(*args: Any) -> _T:
            with lock:
                got = tables.get(args)
                if got is not None:
                    tables.move_to_end(args)
                    counts[0] += 1
                    return got[0]
                counts[1] += 1
            table = build(*args)  # outside the lock: builds of other keys run meanwhile
            with lock:
                tables[args] = (table, table_bytes(table))
                tables.move_to_end(args)
                while len(tables) > max_entries or (
                    len(tables) > KEEP_NEWEST and sum(b for _, b in tables.values()) > max_bytes
                ):
                    tables.popitem(last=False)
            return table

        def cache_info() -> functools._CacheInfo:
            return functools._CacheInfo(counts[0], counts[1], max_entries, len(tables))

        def cache_clear() -> None:
            with lock:
                tables.clear()
                counts[:] = [0, 0]

        cached.cache_info = cache_info  # type: ignore[attr-defined]
        cached.cache_clear = cache_clear  # type: ignore[attr-defined]
        return cached

    return wrap


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
    """Per row and bin, the interval of columns feeding the bin; per column, the bins it feeds:
    the bin map as the tests' reference reads it (exact_table calls the kernel directly and keeps
    only the per-column bins).

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


@dataclass(frozen=True, slots=True)
class _Grid:
    """Normalised coordinates of the used pixels (what a mount change does not change): views
    that hold no (Hs, Ws) memory of their own where the lens allows (``_grid``)."""

    x: F64  # (Hs, Ws) pixel centres
    y: F64
    xe: F64  # (Hs, Ws + 1) footprint edges: pixel j spans edges j and j + 1
    ye: F64
    principal: tuple[F64, F64]  # (2,) x and y of the principal pixel's two edges


@functools.lru_cache(maxsize=8)
def _grid(intr: Intrinsics, rows: tuple[int, int, int], col_step: int) -> _Grid:
    """The rays of the used pixels, per (intrinsics, rows, col_step): normalized_coords (a lens
    model's undistortion) runs once per camera, not once per mount.

    Memory (the tables' budget, TABLE_BUDGET_B_PER_PX): the centres are views of
    ``geometry.pixel_rays``, which the coverage and the pose stage hold anyway (made first, so
    its own building peak comes before the tables'); the edges of a pinhole are a row (x) and a
    column (y) broadcast, read-only views without memory; only through a lens do they take
    memory of their own (16 B a pixel). Either way the values are the full grids' bit for bit
    (normalized_coords works point by point)."""
    sel = slice(*rows)
    rays = pixel_rays(intr)[sel, ::col_step]
    v = np.arange(intr.height, dtype=np.float64)[sel][:, None]
    u = np.arange(intr.width, dtype=np.float64)[::col_step][None, :]
    half = col_step / 2.0
    # edge j + 1 of pixel j is u[j] + half = u[j + 1] - half exactly (integers and halves)
    ue = np.concatenate([u - half, u[:, -1:] + half], axis=1)
    xe, ye = edge_coords(intr, ue, v)
    px, py = normalized_coords(
        intr, np.array([intr.cx - half, intr.cx + half]), np.array([intr.cy, intr.cy])
    )
    return frozen_table(_Grid(rays[..., 0], rays[..., 1], xe, ye, (px, py)))


def edge_coords(intr: Intrinsics, ue: F64, v: F64) -> tuple[F64, F64]:
    """normalized_coords of the grid ue (1, C) x v (R, 1) as (R, C) arrays: a pinhole's as a row
    and a column broadcast (read-only views: x depends on the column only, y on the row only),
    a lens's as C arrays."""
    if intr.has_distortion:
        x, y = normalized_coords(intr, ue, v)
        return np.ascontiguousarray(x), np.ascontiguousarray(y)
    shape = (v.shape[0], ue.shape[1])
    xe = normalized_coords(intr, ue, v[:1])[0]
    ye = normalized_coords(intr, ue[:, :1], v)[1]
    return np.broadcast_to(xe, shape), np.broadcast_to(ye, shape)


# how far beyond range_max (a fraction of it) the floor point of a run's asked row lies: covers
# depth rounding and a structured-light sensor's noise at 5 m (sigma ~1 %)
REACH_MARGIN = 0.02


def reach_limits(
    probe: npt.NDArray[np.int16], g: _Grid, rot: F64, height_m: float, reach_m: float
) -> npt.NDArray[np.int16]:
    """(P,) int16 per run (column, first row, last row): its last row, from the first on, whose
    floor point (the used pixel's ray from a sensor ``height_m`` up, rotated by ``rot``) lies at
    or beyond ``reach_m``; first - 1 where even the first row's lies nearer. The +inf question
    looks at these rows only (scan_kernels). Compiled (table_kernels.reach_limits_kernel): the
    numpy form walked a (P,) vector once per row of the longest run (1.3 s at 1024x1024) over
    an (Hs, Ws) float64 array of floor ranges (40 B a pixel at its peak)."""
    return reach_limits_kernel(probe, g.x, g.y, rot, float(height_m), float(reach_m))


def reach_codes(
    probe_start: npt.NDArray[np.int32],
    probe: npt.NDArray[np.int16],
    probe_lim: npt.NDArray[np.int16],
    n_rows: int,
) -> tuple[npt.NDArray[np.int32], npt.NDArray[np.int32]]:
    """The range_max rows (``probe_lim``, where it is not before the run) of up to three runs a
    bin as the kernel's codes ``col | bin << 15``, grouped by kernel row: (start (n_rows + 1,),
    code (E,))."""
    bins = np.repeat(np.arange(probe_start.size - 1), np.diff(probe_start))
    ok = probe_lim >= probe[1]
    # at most three runs a bin (its first, middle and last such, as listed): a bin has ~10,
    # and asking every one cost ~25 % of the kernel on the fixture; a bin's runs are its
    # neighbouring columns, so three still see past one pixel without a reading
    idx = np.flatnonzero(ok)
    first = np.searchsorted(bins[idx], bins[idx], side="left")
    count = np.bincount(bins[idx], minlength=probe_start.size - 1)[bins[idx]]
    k = np.arange(idx.size) - first
    pick = (k == 0) | (k == count - 1) | (k == count // 2)
    ok = np.zeros_like(ok)
    ok[idx[pick]] = True
    row = probe_lim[ok].astype(np.int64)
    code = probe[0][ok].astype(np.int64) | (bins[ok].astype(np.int64) << CODE_BITS)
    by_row = np.argsort(row, kind="stable")
    start = np.zeros(n_rows + 1, np.int32)
    np.cumsum(np.bincount(row, minlength=n_rows), out=start[1:])
    return start, code[by_row].astype(np.int32)


@table_cache(16)
def exact_table(intr: Intrinsics, mount: Mount, params: ScanParams) -> ExactTable:
    """The exact scan's tables for this camera, mount and parameters (cached).

    Raises:
        ConfigError: parameters that do not fit this image.
    """
    rows = scan_rows(intr, params)
    n_cols = len(range(0, intr.width, params.col_step))
    if n_cols > MAX_CODE_INDEX:
        raise ConfigError(
            f"the exact scan uses {n_cols} columns of this {intr.width}-pixel-wide image "
            f"(accepted: up to {MAX_CODE_INDEX}); raise scan.col_step"
        )
    g = _grid(intr, (rows.start, rows.stop, rows.step or 1), params.col_step)
    rot = cam_to_level(mount.tilt_rad, mount.roll_rad)
    shape = g.x.shape
    u16 = np.empty((7, *shape), dtype=np.uint16)
    zlo_mm, zhi_mm, near_lo_mm, near_hi_mm, k_lo, k_mid, k_hi = u16
    kr32 = np.empty(shape, dtype=np.float32)
    px, py = g.principal
    fwd = rot[0, 0] * px + rot[0, 1] * py + rot[0, 2]
    left = rot[1, 0] * px + rot[1, 1] * py + rot[1, 2]
    principal = np.arctan2(left, fwd)
    inc = (
        math.radians(params.angle_increment_deg)
        if params.angle_increment_deg > 0
        else float(abs(principal[1] - principal[0]))
    )
    limits = np.array(
        [
            mount.height_m,
            params.min_obstacle_height_m,
            params.max_obstacle_height_m,
            params.range_min_m,
            params.range_max_m,
        ],
        dtype=np.float64,
    )
    # compiled: numpy took ~50 ms at 640x480, on the frame path of a mount change; one call, so
    # that its large temporaries are freed without the interpreter lock (exact_codes_kernel)
    used, n, angle_min, fl_start, fl_code = exact_codes_kernel(
        g.x, g.y, g.xe, g.ye, rot, limits, u16, kr32, inc, MAX_BINS
    )
    if used == 0:
        raise ConfigError(
            f"no pixel of this image looks at a bearing for this mount (tilt {mount.tilt_deg:g} "
            f"deg, roll {mount.roll_deg:g} deg); check the mount"
        )
    if n > MAX_BINS:
        raise ConfigError(
            f"scan.angle_increment_deg={params.angle_increment_deg} gives {n} bins "
            f"(accepted: up to {MAX_BINS})"
        )
    blk, fl_blk, probe_start, probe, spans = block_tables(k_lo, k_mid, k_hi, fl_start, fl_code, n)
    # the asked row's floor lies a margin beyond range_max: a reading of a floor at range_max
    # itself falls short half the time by depth rounding and noise (a 640x480 fixture bin read
    # 4.99 m there and was unknown)
    reach_m = params.range_max_m * (1.0 + REACH_MARGIN)
    probe_lim = reach_limits(probe, g, rot, mount.height_m, reach_m)
    reach_start, reach_code = reach_codes(probe_start, probe, probe_lim, shape[0])
    row_idx = np.arange(intr.height, dtype=np.int32)[rows]
    _, far = floor_extent(intr, mount, angle_min, inc, n, (rows.start, rows.stop, rows.step or 1))
    short_view = np.flatnonzero(~seen_to(far, params.range_max_m)).astype(np.intp)
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
        blk=blk,
        fl_blk=fl_blk,
        probe_start=probe_start,
        probe=probe,
        probe_lim=probe_lim,
        reach_start=reach_start,
        reach_code=reach_code,
        spans=spans,
        n_bins=n,
        angle_min=angle_min,
        short_view=short_view,
        short=np.ascontiguousarray(~seen_to(far, params.range_max_m)),
        angle_increment=inc,
    )
    return frozen_table(table)  # cached and shared between calls
