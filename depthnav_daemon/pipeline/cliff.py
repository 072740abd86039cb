"""Negative obstacles (steps down, holes): the paper's eq. 6-8 with an exact per-pixel floor depth.

A *drop-off sample* is a pixel that sees farther than the floor should be: its ray goes below the
floor plane. Samples are taken on a grid (``row_step`` x ``col_step``) inside square blocks of
``block_size`` pixels over the bottom ``used_depth_height`` rows (eq. 7); a block with at least
``block_points_thresh`` samples is a negative obstacle (eq. 8).

``exact`` (the default, the fix): a sample counts when its reading lies more than
``ground_margin_m`` *below the floor plane*, with tilt AND roll (as ``level_rays``): the floor
depth of a pixel is ``h / -kz`` (kz = level-frame z per metre of optical depth), so the test is
``depth > (h + margin) / -kz``. A vertical margin keeps Kinect quantisation (centimetres of depth
at 4 m, but millimetres of height along a grazing ray) from faking drops. Only pixels whose ray
meets the floor within [range_min_m, range_max_m] of horizontal range are used; rays at or above
the horizon never count.

``paper``: eq. 6 as published: per-row floor depth with the linear row angle (eq. 3), no roll,
margin in optical depth, ``range_min_m < depth < range_max_m`` (ROS 1 cliff_detector).

With either method a 0/NaN reading never counts, every detected block is reported once at the point
where the ray through its centre meets the floor plane (tilt and roll included: that is where the
drop begins or the hole is), and the cliff scan holds, per bearing of the given scan layout, the
nearest horizontal range of the floor point of a drop-off sample inside a detected block (REP 117:
+inf = valid readings but no drop-off, NaN = no valid reading).
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from depthnav_daemon.errors import ConfigError
from depthnav_daemon.pipeline.cliff_kernels import CODE_BITS, CODE_MASK, cliff_kernel
from depthnav_daemon.pipeline.geometry import (
    F32,
    F64,
    Mount,
    cam_to_level,
    check_int,
    check_order,
    check_range,
    depth_to_mm,
    frozen_table,
    paper_floor_depth_m,
    paper_row_angles_rad,
)
from depthnav_daemon.pipeline.scan import LaserScan
from depthnav_daemon.pipeline.scan_kernels import MAX_CODE_INDEX, run_flush_codes
from drivers.base import Intrinsics

METHODS = ("exact", "paper")
MAX_SPAN_BINS = 64  # a sample looking almost straight down covers many bearings; cap its footprint
NEVER_MM = 65535  # a lower bound no uint16 reading exceeds: the sample never counts


@dataclass(frozen=True, slots=True)
class CliffParams:
    """Cliff detector parameters; defaults are cliff_detector's shipped params.yaml values.

    Attributes:
        method: "exact" (per-pixel floor with tilt and roll, the default) or "paper" (eq. 6).
        range_min_m, range_max_m: exact: horizontal range of the pixel's floor point, metres;
            paper: optical depth of the reading, metres (as the original).
        used_depth_height: rows used, counted from the image bottom (clamped to the image height).
        block_size: side of the square blocks, pixels.
        block_points_thresh: drop-off samples a block needs to be a negative obstacle (eq. 8).
        row_step, col_step: sample strides inside a block, pixels.
        ground_margin_m: e_g; exact: metres below the floor plane; paper: metres of optical depth.
    """

    method: str = "exact"
    range_min_m: float = 0.5
    range_max_m: float = 5.0
    used_depth_height: int = 400
    block_size: int = 16
    block_points_thresh: int = 3
    row_step: int = 8
    col_step: int = 8
    ground_margin_m: float = 0.05

    def __post_init__(self) -> None:
        if self.method not in METHODS:
            raise ConfigError(
                f"cliff.method={self.method!r} is not known (accepted: {', '.join(METHODS)})"
            )
        check_range("cliff.range_min_m", self.range_min_m, 0.0, 100.0, " m")
        check_range("cliff.range_max_m", self.range_max_m, 0.01, 100.0, " m")
        check_order("cliff.range_min_m", self.range_min_m, "cliff.range_max_m", self.range_max_m)
        check_int("cliff.used_depth_height", self.used_depth_height, 1, 8192)
        check_int("cliff.block_size", self.block_size, 1, 256)
        check_int("cliff.row_step", self.row_step, 1, self.block_size)
        check_int("cliff.col_step", self.col_step, 1, self.block_size)
        check_int("cliff.block_points_thresh", self.block_points_thresh, 1, self.samples_per_block)
        check_range("cliff.ground_margin_m", self.ground_margin_m, 0.0, 10.0, " m")

    @property
    def samples_per_block(self) -> int:
        """Samples one block holds: ceil(bs / row_step) * ceil(bs / col_step)."""
        return -(-self.block_size // self.row_step) * -(-self.block_size // self.col_step)


@dataclass(frozen=True, slots=True)
class CliffResult:
    """Drop-offs found in one frame.

    Attributes:
        points_m: (K, 2) float32 floor points (x forward, y left), metres, in the level frame at the
            sensor's foot: where each detected block's centre ray meets the floor.
        blocks: (K, 2) int64 (row, col) of each detected block's top-left pixel (for drawing).
        block_size: block side in pixels (for drawing).
        scan: nearest drop-off per bearing, in the layout the caller asked for (REP 117).
    """

    points_m: F32
    blocks: npt.NDArray[np.int64]
    block_size: int
    scan: LaserScan


@dataclass(frozen=True, slots=True, kw_only=True)
class _CliffTable:
    """Sample grid and thresholds for one (intrinsics, mount, params, layout); read-only arrays.

    Index lists are packed into int32 codes (``cliff_kernels.cliff_kernel`` says how): one load
    per entry in the kernel's loops instead of two or three.
    """

    rows: npt.NDArray[np.intp]  # (nbr * nj,) image row of every sample row, ascending (top first)
    cols: npt.NDArray[np.intp]  # (nbc * ni,) image column of every sample column
    shape4: tuple[int, int, int, int]  # (nbr, nj, nbc, ni)
    lo_mm: npt.NDArray[np.uint16]  # (nbr * nj, nbc * ni) sample counts iff lo < d < hi
    hi_mm: int  # the same upper bound for every sample (the range limit or none)
    range_m: F32  # (nbr * nj, nbc * ni) horizontal range of the floor point, +inf none
    block_xy_m: F32  # (nbr, nbc, 2) floor point of each block's centre ray, NaN none
    block_ok: npt.NDArray[np.bool_]  # (nbr, nbc) the block's centre ray meets the floor
    col_step: int  # sample columns are col0 + k * col_step (0: unevenly spaced, gather them)
    ev_block: npt.NDArray[np.int64]  # (R, nbc + 1) flushes per sample row and block column ..
    ev_code: npt.NDArray[np.int32]  # (E,) .. col | run ends << 15 | bin << 16
    cov_start: npt.NDArray[np.int64]  # (N + 1,) samples covering bin b: cov_start[b]:cov_start[b+1]
    cov_code: npt.NDArray[np.int32]  # (M,) col | sample row << 15, top rows first
    probe_start: npt.NDArray[np.int64]  # (R + 1,) probes (a bin's lowest sample) by sample row
    probe_code: npt.NDArray[np.int32]  # (P,) col | bin << 15


def _floor_hits(intr: Intrinsics, rot: F64, u: F64, v: F64) -> tuple[F64, F64, F64]:
    """Level-frame ray per metre of optical depth through pixel coordinates (u, v): (kx, ky, kz)."""
    x = (u - intr.cx) / intr.fx
    y = (v - intr.cy) / intr.fy
    return (
        rot[0, 0] * x + rot[0, 1] * y + rot[0, 2],
        rot[1, 0] * x + rot[1, 1] * y + rot[1, 2],
        rot[2, 0] * x + rot[2, 1] * y + rot[2, 2],
    )


def _sample_bins(
    lo_b: F64, hi_b: F64, angle_min: float, inc: float, n: int
) -> tuple[npt.NDArray[np.int32], npt.NDArray[np.int32]]:
    """First and last scan bin each item's bearing interval [lo_b, hi_b] (radians) overlaps.

    Bin i covers [angle_min + (i - 1/2) inc, angle_min + (i + 1/2) inc); an item covers at most
    MAX_SPAN_BINS bins. Items with a NaN interval, one that crosses the +-pi seam, or one outside
    the scan get first > last (no bin).

    Returns:
        (first, last): int32 arrays shaped like ``lo_b``.
    """
    with np.errstate(invalid="ignore"):
        sane = np.isfinite(lo_b) & np.isfinite(hi_b) & ((hi_b - lo_b) < math.pi)
        first = np.floor((np.where(sane, lo_b, angle_min) - angle_min) / inc + 0.5)
        last = np.floor((np.where(sane, hi_b, angle_min) - angle_min) / inc + 0.5)
    sane &= (last >= 0) & (first <= n - 1)
    first = np.clip(first, 0, n - 1).astype(np.int64)
    last = np.clip(np.minimum(last, first + MAX_SPAN_BINS - 1), 0, n - 1).astype(np.int64)
    return np.where(sane, first, 1).astype(np.int32), np.where(sane, last, 0).astype(np.int32)


def _covering_samples(
    first: npt.NDArray[np.int32], last: npt.NDArray[np.int32], n: int
) -> tuple[npt.NDArray[np.int64], npt.NDArray[np.int32], npt.NDArray[np.int32]]:
    """For every bin, the samples covering it, in sample order (top rows first).

    Args:
        first, last: (R, C) first and last bin of every sample (first > last: none).
        n: bins.

    Returns:
        cov_start (n + 1,), cov_row and cov_col (M,): bin b's samples are
            cov_start[b]:cov_start[b + 1].
    """
    span = np.maximum(last.astype(np.int64) - first + 1, 0).ravel()
    item = np.repeat(np.arange(span.size), span)
    bins = first.ravel()[item] + (np.arange(item.size) - np.repeat(np.cumsum(span) - span, span))
    order = np.argsort(bins, kind="stable")
    start = np.zeros(n + 1, dtype=np.int64)
    np.cumsum(np.bincount(bins, minlength=n), out=start[1:])
    r, c = np.divmod(item[order], first.shape[1])
    return start, r.astype(np.int32), c.astype(np.int32)


def _probes(
    cov_start: npt.NDArray[np.int64],
    cov_row: npt.NDArray[np.int32],
    cov_col: npt.NDArray[np.int32],
    n_rows: int,
) -> tuple[npt.NDArray[np.int64], npt.NDArray[np.int32], npt.NDArray[np.int32]]:
    """Every covered bin's last covering sample (the lowest in the image), grouped by sample row.

    Returns:
        (start (R + 1,), bin, col): the probes of sample row i are start[i]:start[i + 1].
    """
    bins = np.flatnonzero(np.diff(cov_start) > 0)
    probe = cov_start[bins + 1] - 1
    row = cov_row[probe]
    order = np.argsort(row, kind="stable")
    start = np.zeros(n_rows + 1, dtype=np.int64)
    np.cumsum(np.bincount(row, minlength=n_rows), out=start[1:])
    return start, bins[order].astype(np.int32), cov_col[probe][order]


@functools.lru_cache(maxsize=16)
def _cliff_table(
    intr: Intrinsics, mount: Mount, params: CliffParams, angle_min: float, inc: float, n_bins: int
) -> _CliffTable:
    bs = params.block_size
    used = min(params.used_depth_height, intr.height)
    nbr, nbc = used // bs, intr.width // bs
    if nbr == 0 or nbc == 0:
        raise ConfigError(
            f"cliff.block_size={bs} does not fit the used {used}x{intr.width} pixels of this image "
            f"(accepted: 1..{min(used, intr.width)})"
        )
    j = np.arange(0, bs, params.row_step)
    i = np.arange(0, bs, params.col_step)
    if nbc * i.size > MAX_CODE_INDEX:
        raise ConfigError(
            f"cliff samples {nbc * i.size} columns of this {intr.width}-pixel-wide image "
            f"(accepted: up to {MAX_CODE_INDEX}); raise cliff.col_step"
        )
    # blocks counted from the image bottom, as the original (block row 0 is the lowest), but the
    # sample rows stored top to bottom: the kernel then walks memory upwards, which the hardware
    # prefetcher follows better (~1.5-2x on a frame that is not in cache)
    rows = (intr.height - 1 - (np.arange(nbr)[:, None] * bs + j[None, :]))[::-1, ::-1].ravel()
    cols = (np.arange(nbc)[:, None] * bs + i[None, :]).ravel()
    rot = cam_to_level(mount.tilt_rad, mount.roll_rad)
    u = cols.astype(np.float64)[None, :]
    v = rows.astype(np.float64)[:, None]
    lo_mm, hi_mm, range_m = _thresholds(intr, mount, params, rot, rows, u, v)
    block_xy = _block_floor_points(intr, rot, mount.height_m, bs, nbr, nbc)

    # each sample covers the bearings between the left and right edges of its col_step footprint
    e = params.col_step / 2.0
    lx, ly, _ = _floor_hits(intr, rot, u - e, v)
    rx, ry, _ = _floor_hits(intr, rot, u + e, v)
    b_l = np.arctan2(ly, lx)
    b_r = np.arctan2(ry, rx)
    first, last = _sample_bins(np.minimum(b_l, b_r), np.maximum(b_l, b_r), angle_min, inc, n_bins)
    ev_start, ev_code = run_flush_codes(first, last, n_bins, row_block=j.size)
    # index of each row's first flush in each block column (a row's flushes are sorted by column)
    ev_row = np.repeat(np.arange(first.shape[0]), np.diff(ev_start))
    key = ev_row * (nbc + 1) + (ev_code & CODE_MASK) // i.size
    ev_block = np.searchsorted(
        key, np.arange(first.shape[0])[:, None] * (nbc + 1) + np.arange(nbc + 1)[None, :]
    ).astype(np.int64)
    cov_start, cov_row, cov_col = _covering_samples(first, last, n_bins)
    probe_start, probe_bin, probe_col = _probes(cov_start, cov_row, cov_col, first.shape[0])
    cov_code = (cov_col | (cov_row << CODE_BITS)).astype(np.int32)
    probe_code = (probe_col | (probe_bin << CODE_BITS)).astype(np.int32)
    block_ok = np.isfinite(block_xy[..., 0])

    range32 = range_m.astype(np.float32)
    col_sel = _selector(cols)
    col_step = col_sel.step if isinstance(col_sel, slice) else 0
    table = _CliffTable(
        rows=rows,
        cols=cols,
        shape4=(nbr, j.size, nbc, i.size),
        lo_mm=lo_mm,
        hi_mm=hi_mm,
        range_m=range32,
        block_xy_m=block_xy,
        block_ok=block_ok,
        col_step=col_step,
        ev_block=ev_block,
        ev_code=ev_code,
        cov_start=cov_start,
        cov_code=cov_code,
        probe_start=probe_start,
        probe_code=probe_code,
    )
    return frozen_table(table)  # cached and shared between calls


def _thresholds(
    intr: Intrinsics,
    mount: Mount,
    params: CliffParams,
    rot: F64,
    rows: npt.NDArray[np.intp],
    u: F64,
    v: F64,
) -> tuple[npt.NDArray[np.uint16], int, F64]:
    """Per-sample drop-off thresholds: (lo_mm (R, C) uint16, hi_mm, floor range_m (R, C)).

    A reading d (mm) is a drop-off sample iff lo_mm < d < hi_mm: deeper than the floor plus the
    ground margin (``exact``: along the level-frame ray; ``paper``: eq. 6's per-row floor).
    """
    h = mount.height_m
    kx, ky, kz = _floor_hits(intr, rot, u, v)
    down = kz < 0
    with np.errstate(divide="ignore", invalid="ignore"):
        t_floor = np.where(down, h / np.where(down, -kz, 1.0), np.inf)  # floor depth, m
        range_m = np.where(down, t_floor * np.hypot(kx, ky), np.inf)  # (nr, nc)
    if params.method == "exact":
        in_range = down & (range_m >= params.range_min_m) & (range_m <= params.range_max_m)
        with np.errstate(divide="ignore", invalid="ignore"):
            lo = np.where(in_range, (h + params.ground_margin_m) / np.where(down, -kz, 1.0), np.inf)
        hi_mm = NEVER_MM
    else:
        delta = paper_row_angles_rad(intr)[rows][:, None]
        ground = paper_floor_depth_m(h, mount.tilt_rad, delta) + params.ground_margin_m  # eq. 6
        lo = np.broadcast_to(np.maximum(ground, params.range_min_m), range_m.shape)
        hi_mm = min(math.ceil(params.range_max_m * 1000.0), NEVER_MM)
    # integer readings: d > lo_m * 1000 <=> d > floor(lo_m * 1000)
    with np.errstate(invalid="ignore"):
        lo_mm = np.where(np.isfinite(lo), np.clip(np.floor(lo * 1000.0), 0, NEVER_MM), NEVER_MM)
    return lo_mm.astype(np.uint16), hi_mm, range_m


def _block_floor_points(
    intr: Intrinsics, rot: F64, height_m: float, bs: int, nbr: int, nbc: int
) -> F32:
    """(nbr, nbc, 2) level-frame floor point (x, y) of each block's centre ray, NaN none."""
    half = (bs - 1) / 2.0  # the sub-pixel centre
    bu = (np.arange(nbc) * bs + half)[None, :]
    bv = (intr.height - (np.arange(nbr) + 1) * bs + half)[:, None]
    bx, by, bz = _floor_hits(intr, rot, bu, bv)
    with np.errstate(divide="ignore", invalid="ignore"):
        bt = np.where(bz < 0, height_m / -bz, np.nan)
    return np.stack([bt * bx, bt * by], axis=-1).astype(np.float32)


def _selector(idx: npt.NDArray[np.intp]) -> slice | npt.NDArray[np.intp]:
    """A slice equal to the index array when it is evenly spaced (a view beats a gather)."""
    step = int(idx[1] - idx[0]) if idx.size > 1 else 1
    if step == 0 or not np.array_equal(np.diff(idx), np.full(idx.size - 1, step)):
        return idx
    stop = int(idx[-1]) + step
    # a descending run that ends at row 0 needs stop None: -1 would mean the last row
    return slice(int(idx[0]), None if stop < 0 else stop, step)


def detect_cliffs(
    depth: np.ndarray,
    intr: Intrinsics,
    mount: Mount,
    params: CliffParams,
    angle_min: float,
    angle_increment: float,
    n_bins: int,
) -> CliffResult:
    """Find steps down and holes in one depth image.

    Args:
        depth: (H, W) uint16 millimetres (0 = no reading) or float32 metres (NaN = none).
        intr: intrinsics of ``depth``.
        mount: sensor height, tilt (positive down) and roll (positive left side up).
        params: detector parameters.
        angle_min, angle_increment, n_bins: layout of the cliff scan (radians, radians, count);
            pass the obstacle scan's layout (``scan.scan_layout``) so the two line up.

    Returns:
        Floor points and blocks of the detected negative obstacles, and the cliff scan.

    Raises:
        FrameError: wrong dtype or shape. ConfigError: a layout or block size that does not fit.
    """
    check_range("cliff angle_min", angle_min, -math.pi - 1e-9, math.pi, " rad")
    check_range("cliff angle_increment", angle_increment, 1e-6, math.pi, " rad")
    check_int("cliff n_bins", n_bins, 1, MAX_CODE_INDEX)
    mm = depth_to_mm(depth, intr)
    t = _cliff_table(intr, mount, params, float(angle_min), float(angle_increment), int(n_bins))
    if t.col_step:  # a view: sample column k is image column cols[0] + k * col_step
        src, rows = mm[:, int(t.cols[0]) : int(t.cols[-1]) + 1 : t.col_step], t.rows
    else:  # unevenly spaced sample columns: gather the samples once
        src, rows = mm[np.ix_(t.rows, t.cols)], np.arange(t.rows.size, dtype=np.intp)
    _, nj, _, ni = t.shape4
    out = np.empty(n_bins + 1, dtype=np.float32)  # + a scratch slot for runs covering no bin
    blocks, points = cliff_kernel(
        src,
        rows,
        nj,
        ni,
        t.lo_mm,
        np.uint16(t.hi_mm),
        t.range_m,
        t.block_ok,
        params.block_points_thresh,
        t.ev_block,
        t.ev_code,
        t.cov_start,
        t.cov_code,
        t.probe_start,
        t.probe_code,
        t.block_xy_m,
        intr.height,
        params.block_size,
        out,
    )
    ranges = out[:-1]
    scan = LaserScan(
        float(angle_min),
        float(angle_min + (n_bins - 1) * angle_increment),
        float(angle_increment),
        params.range_min_m,
        params.range_max_m,
        ranges,
    )
    return CliffResult(points, blocks, params.block_size, scan)
