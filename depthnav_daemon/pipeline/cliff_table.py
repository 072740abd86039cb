"""The cliff detector's tables: for one camera, mount, parameters and scan layout, the sample grid,
the depth beyond which each sample is a drop-off, and which bearing bins each sample feeds; for the
exact method also, per pixel of the used rows, its drop-off depth, floor point and bins (the edge
refinement), and the bins the used rows do not see out to range_max (built once, cached)."""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from depthnav_daemon.errors import ConfigError
from depthnav_daemon.pipeline.cliff_table_kernels import band_mm_kernel, edge_table_kernel
from depthnav_daemon.pipeline.coverage import floor_extent, seen_to
from depthnav_daemon.pipeline.geometry import (
    F32,
    F64,
    Mount,
    cam_to_level,
    frozen_table,
    normalized_coords,
    paper_floor_depth_m,
    paper_row_angles_rad,
    pixel_rays,
)
from depthnav_daemon.pipeline.params import CliffParams
from depthnav_daemon.pipeline.scan_kernels import (
    CODE_BITS,
    CODE_MASK,
    MAX_CODE_INDEX,
    run_flush_codes,
)
from depthnav_daemon.pipeline.scan_table import edge_coords, table_cache
from drivers.base import Intrinsics

MAX_SPAN_BINS = 64  # a sample looking almost straight down covers many bearings; cap its footprint
NEVER_MM = 65535  # a lower bound no uint16 reading exceeds: the sample never counts


@dataclass(frozen=True, slots=True, kw_only=True)
class CliffTable:
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
    cov_start: npt.NDArray[np.int64]  # (N + 1,) bin b's reach samples: cov_start[b]:cov_start[b+1]
    cov_code: npt.NDArray[np.int32]  # (M,) col | sample row << 15 (_reach_samples: probe last)
    # (M,) exact: each reach sample's bounds, its pixel's (px_band_mm) or, past range_max, the
    # same formula: a reading beyond cov_lo_mm is a drop-off, one short of cov_ob_mm stands on the
    # floor (NEVER_MM: none); paper: NEVER_MM (unused)
    cov_lo_mm: npt.NDArray[np.uint16]
    cov_ob_mm: npt.NDArray[np.uint16]
    probe_start: npt.NDArray[np.int64]  # (R + 1,) probes (a bin's lowest sample) by sample row
    probe_code: npt.NDArray[np.int32]  # (P,) col | bin << 15
    # exact: every pixel of the used rows (image rows row0..H-1); paper: empty (0 rows)
    row0: int  # image row of the pixel tables' first row
    px_band_mm: npt.NDArray[np.uint16]  # (2, Hu, W) drop-off iff d > [0]; obstacle iff d < [1]
    px_xyt_m: F32  # (Hu, W, 3) floor point (x, y) of the pixel's ray and its depth t, NaN none
    px_bins: npt.NDArray[np.int16]  # (2, Hu, W) first and last bin of its footprint (first > last)
    # (n,) bins whose floor the read rows do not see out to range_max (coverage.floor_extent): no
    # drop-off there is unknown (NaN), not +inf. Exact only; all False for paper
    short: npt.NDArray[np.bool_]


def _floor_hits(intr: Intrinsics, rot: F64, u: F64, v: F64) -> tuple[F64, F64, F64]:
    """Level-frame ray per metre of optical depth through pixel coordinates (u, v): (kx, ky, kz)."""
    return _level_hits(rot, *normalized_coords(intr, u, v))


def _level_hits(rot: F64, x: F64, y: F64) -> tuple[F64, F64, F64]:
    """Level-frame ray per metre of optical depth of normalised coordinates (x, y)."""
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


def _reach_samples(
    cov_start: npt.NDArray[np.int64],
    cov_row: npt.NDArray[np.int32],
    cov_col: npt.NDArray[np.int32],
    range_m: F64,
    params: CliffParams,
) -> tuple[npt.NDArray[np.int64], npt.NDArray[np.int32], npt.NDArray[np.int32]]:
    """Of every bin's covering samples, those that say whether it is seen out to range_max: the
    samples read (floor point within [range_min, range_max]) in the bin's highest sample row read,
    and those of the next sample row above it, whose floor lies past range_max (at 160x120 the
    highest row read can end 0.3 m short of it: a pit whose edge lies between read +inf, seed
    1006; the kernel judges these with bounds of their own, CliffTable.cov_lo_mm). A bin is +inf
    (no drop-off) only if one of each row reads the floor: a drop-off nearer than them shows as
    lower-floor readings in the rows above its edge, and where the highest row reads nothing (a
    lower floor beyond the sensor's reach) the far end of the bin is unknown (the safety
    contract). The next row down is no stand-in: at 4 m its floor lies ~0.4 m nearer.

    The paper method keeps them all (the original: +inf where any covering sample reads).

    Returns:
        (start (n + 1,), row, col) as ``_covering_samples``'.
    """
    if params.method == "paper":
        return cov_start, cov_row, cov_col
    r = range_m[cov_row, cov_col]
    read = (r >= params.range_min_m) & (r <= params.range_max_m)
    past = np.isfinite(r) & (r > params.range_max_m)
    n = cov_start.size - 1
    bin_of = np.repeat(np.arange(n), np.diff(cov_start))
    big = np.iinfo(np.int32).max
    top = np.full(n, big, np.int64)
    np.minimum.at(top, bin_of[read], cov_row[read])
    beyond = np.full(n, -1, np.int64)  # the bin's nearest sample row past range_max, above top
    above = past & (cov_row < top[bin_of])
    np.maximum.at(beyond, bin_of[above], cov_row[above])
    keep = (read & (cov_row == top[bin_of])) | (above & (cov_row == beyond[bin_of]))
    rows, cols = cov_row[keep], cov_col[keep]  # bin by bin, as _covering_samples gave them
    start = np.zeros(n + 1, dtype=np.int64)
    np.cumsum(np.bincount(bin_of[keep], minlength=n), out=start[1:])
    return start, rows.astype(np.int32), cols.astype(np.int32)


def _probes(
    cov_start: npt.NDArray[np.int64],
    cov_row: npt.NDArray[np.int32],
    cov_col: npt.NDArray[np.int32],
    n_rows: int,
) -> tuple[npt.NDArray[np.int64], npt.NDArray[np.int32], npt.NDArray[np.int32]]:
    """Every covered bin's last reach sample (one of its highest read), grouped by sample row.

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


@functools.lru_cache(maxsize=24)  # six grids per configuration (two of every pixel)
def _coords(intr: Intrinsics, us: tuple[float, ...], vs: tuple[float, ...]) -> tuple[F64, F64]:
    """normalized_coords on the grid us x vs (pixels), (len(vs), len(us)) each, per camera: a
    lens model's undistortion runs once per camera and sample grid, not once per mount."""
    x, y = normalized_coords(intr, np.array(us)[None, :], np.array(vs)[:, None])
    x.setflags(write=False)
    y.setflags(write=False)
    return x, y


def _grid_coords(intr: Intrinsics, u: F64, v: F64) -> tuple[F64, F64]:
    """``_coords`` of the grid u (1, C) x v (R, 1)."""
    return _coords(intr, tuple(u.ravel().tolist()), tuple(v.ravel().tolist()))


@table_cache(16)
def cliff_table(
    intr: Intrinsics, mount: Mount, params: CliffParams, angle_min: float, inc: float, n_bins: int
) -> CliffTable:
    """The cliff stage's tables for this camera, mount, parameters and scan layout (cached).

    Raises:
        ConfigError: a block size or sample grid that does not fit this image.
    """
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
    lo_mm, hi_mm, range_m, t_floor = _thresholds(intr, mount, params, rot, rows, u, v)
    block_xy = _block_floor_points(intr, rot, mount.height_m, bs, nbr, nbc)

    # each sample covers the bearings between the left and right edges of its col_step footprint
    e = params.col_step / 2.0
    lx, ly, _ = _level_hits(rot, *_grid_coords(intr, u - e, v))
    rx, ry, _ = _level_hits(rot, *_grid_coords(intr, u + e, v))
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
    cov_start, cov_row, cov_col = _reach_samples(cov_start, cov_row, cov_col, range_m, params)
    probe_start, probe_bin, probe_col = _probes(cov_start, cov_row, cov_col, first.shape[0])
    cov_code = (cov_col | (cov_row << CODE_BITS)).astype(np.int32)
    probe_code = (probe_col | (probe_bin << CODE_BITS)).astype(np.int32)
    block_ok = np.isfinite(block_xy[..., 0])
    row0 = intr.height - nbr * bs
    if params.method == "exact":
        px_band, px_xyt, px_bins = _pixel_tables(
            intr, mount, params, rot, row0, angle_min, inc, n_bins
        )
        lo_mm = np.ascontiguousarray(px_band[0][rows - row0][:, cols])  # the samples' pixels'
        cov_lo, cov_ob = _reach_bounds(mount, params, px_band, row0, rows, cols, t_floor, cov_code)
        # the rows the decision reads: from the top sample row down, one in row_step (the top
        # row and the image's sides bound the view; fewer rows only see less: the safe side)
        read = (int(rows[0]), intr.height, params.row_step)
        _, far = floor_extent(intr, mount, angle_min, inc, n_bins, read)
        short = ~seen_to(far, params.range_max_m)
    else:  # the original's scan: no pixel tables, no coverage mask (same array types)
        px_band, px_xyt, px_bins = (
            np.empty((2, 0, intr.width), np.uint16),
            np.empty((0, intr.width, 3), np.float32),
            np.empty((2, 0, intr.width), np.int16),
        )
        short, cov_lo = np.zeros(n_bins, np.bool_), np.full(cov_code.shape, NEVER_MM, np.uint16)
        cov_ob = cov_lo

    # a ray that grazes the floor meets it beyond float32's range (~1e41 m at 1e-40 deg tilt):
    # +inf there, which is what +inf means here (no floor point in reach), not an error
    with np.errstate(over="ignore"):
        range32 = range_m.astype(np.float32)
    col_sel = _selector(cols)
    col_step = col_sel.step if isinstance(col_sel, slice) else 0
    table = CliffTable(
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
        cov_lo_mm=cov_lo,
        cov_ob_mm=cov_ob,
        probe_start=probe_start,
        probe_code=probe_code,
        row0=row0,
        px_band_mm=px_band,
        px_xyt_m=px_xyt,
        px_bins=px_bins,
        short=np.ascontiguousarray(short),
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
) -> tuple[npt.NDArray[np.uint16], int, F64, F64]:
    """Per-sample drop-off thresholds: (lo_mm (R, C) uint16, hi_mm, floor range_m (R, C), floor
    depth along the optical axis t_m (R, C), +inf none).

    A reading d (mm) is a drop-off sample iff lo_mm < d < hi_mm: deeper than the floor plus the
    ground margin (``paper``: eq. 6's per-row floor). ``exact``: lo_mm is left for the caller to
    fill from the pixel tables (the same bound as the edge search's).
    """
    h = mount.height_m
    kx, ky, kz = _level_hits(rot, *_grid_coords(intr, u, v))
    down = kz < 0
    with np.errstate(divide="ignore", invalid="ignore"):
        t_floor = np.where(down, h / np.where(down, -kz, 1.0), np.inf)  # floor depth, m
        range_m = np.where(down, t_floor * np.hypot(kx, ky), np.inf)  # (nr, nc)
    if params.method == "exact":  # the samples' bounds are their pixels' (cliff_table)
        return np.empty(range_m.shape, np.uint16), NEVER_MM, range_m, t_floor
    delta = paper_row_angles_rad(intr)[rows][:, None]
    ground = paper_floor_depth_m(h, mount.tilt_rad, delta) + params.ground_margin_m  # eq. 6
    lo = np.broadcast_to(np.maximum(ground, params.range_min_m), range_m.shape)
    hi_mm = min(math.ceil(params.range_max_m * 1000.0), NEVER_MM)
    return _to_mm(lo), hi_mm, range_m, t_floor


def _reach_bounds(
    mount: Mount,
    params: CliffParams,
    px_band: npt.NDArray[np.uint16],
    row0: int,
    rows: npt.NDArray[np.intp],
    cols: npt.NDArray[np.intp],
    t_floor: F64,
    cov_code: npt.NDArray[np.int32],
) -> tuple[npt.NDArray[np.uint16], npt.NDArray[np.uint16]]:
    """(M,) uint16 each: the drop-off and standing bounds of every reach sample: its pixel's
    (px_band_mm: within the range limits) or, for a sample whose floor lies past range_max (the
    pixel tables say NEVER there), the pixel tables' own formula (cliff_table_kernels.band_mm)."""
    i, c = cov_code >> CODE_BITS, cov_code & CODE_MASK
    lo = px_band[0][rows[i] - row0, cols[c]].copy()
    ob = px_band[1][rows[i] - row0, cols[c]].copy()
    h = mount.height_m
    t = t_floor[i, c]
    past = (lo == NEVER_MM) & np.isfinite(t)
    lo_p, ob_p = np.empty((2, int(past.sum())), np.uint16)
    nk = params.noise_sigmas * params.depth_noise_k
    band_mm_kernel(t[past] / h, h, params.ground_margin_m, nk, float(NEVER_MM), lo_p, ob_p)
    lo[past], ob[past] = lo_p, ob_p
    return lo, ob


def _to_mm(lo: F64) -> npt.NDArray[np.uint16]:
    """Drop-off depths (m, +inf never) as the uint16 bound the kernel compares readings with."""
    # integer readings: d > lo_m * 1000 <=> d > floor(lo_m * 1000)
    with np.errstate(invalid="ignore"):
        lo_mm = np.where(np.isfinite(lo), np.clip(np.floor(lo * 1000.0), 0, NEVER_MM), NEVER_MM)
    return lo_mm.astype(np.uint16)


def _pixel_tables(
    intr: Intrinsics,
    mount: Mount,
    params: CliffParams,
    rot: F64,
    row0: int,
    angle_min: float,
    inc: float,
    n_bins: int,
) -> tuple[npt.NDArray[np.uint16], F32, npt.NDArray[np.int16]]:
    """The edge search's tables, per pixel of image rows row0..H-1 (every column): CliffTable's
    px_band_mm (2, Hu, W), px_xyt_m (Hu, W, 3) and px_bins (2, Hu, W) (edge_table_kernel)."""
    v = np.arange(row0, intr.height, dtype=np.float64)[:, None]
    # memory (scan_table.TABLE_BUDGET_B_PER_PX): the centres are views of the pixel rays the
    # coverage and the pose stage hold anyway, a pinhole's edges broadcast views (edge_coords);
    # the same values as full grids, bit for bit. Through a lens the edges are remembered per
    # camera (the undistortion once, not once per mount)
    rays = pixel_rays(intr)[row0:]
    x, y = rays[..., 0], rays[..., 1]
    # the footprint's edges: u - 1/2 and u + 1/2, shared by neighbours (one grid of W + 1)
    ue = (np.arange(intr.width + 1) - 0.5)[None, :]
    xe, ye = _grid_coords(intr, ue, v) if intr.has_distortion else edge_coords(intr, ue, v)
    limits = np.array(
        [
            mount.height_m,
            params.ground_margin_m,
            params.noise_sigmas * params.depth_noise_k,
            params.range_min_m,
            params.range_max_m,
            angle_min,
            inc,
            n_bins,
            NEVER_MM,
        ]
    )
    hu, w = x.shape
    band = np.empty((2, hu, w), np.uint16)
    xyt = np.empty((hu, w, 3), np.float32)
    bins = np.empty((2, hu, w), np.int16)
    # compiled, one pass: numpy took ~40 ms at 640x480 (90 at 1280x720) on a mount change
    edge_table_kernel(x, y, xe, ye, rot, limits, float(MAX_SPAN_BINS), band, xyt, bins)
    return band, xyt, bins


def _block_floor_points(
    intr: Intrinsics, rot: F64, height_m: float, bs: int, nbr: int, nbc: int
) -> F32:
    """(nbr, nbc, 2) level-frame floor point (x, y) of each block's centre ray, NaN none."""
    half = (bs - 1) / 2.0  # the sub-pixel centre
    bu = (np.arange(nbc) * bs + half)[None, :]
    bv = (intr.height - (np.arange(nbr) + 1) * bs + half)[:, None]
    bx, by, bz = _level_hits(rot, *_grid_coords(intr, bu, bv))
    # a centre ray grazing the floor meets it beyond float32's range: +inf, not ok (block_ok)
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
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
