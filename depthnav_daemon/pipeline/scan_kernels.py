"""Compiled per-frame kernels of the scan stage; the tables they read are built in scan.py.

Both are row-major single passes over the image (the image is stored row by row; walking it column
by column, as the original does, costs ~4x in cache misses: ../shared/reference/performance.md).
"""

from __future__ import annotations

import numpy as np

from depthnav_daemon.pipeline._jit import kernel

SEEN = np.float32(1e30)  # "valid readings, no obstacle": sorts between ranges and no-data (+inf)


@kernel
def exact_scan_kernel(depth, rows, zlo, zhi, nlo, nhi, kr, fl_start, fl_col, fl_bin, rs_start, rs_col, acc, out):  # noqa: ANN001, ANN201, PLR0913
    """Exact scan of one frame into ``out`` (n,) float32, REP 117 values.

    One row-major pass keeps a running minimum per column (``acc``) for as long as the column
    feeds the same bins; where a column's bins change from one row to the next (a "run" ends),
    the run's minimum is flushed into those bins and the column starts again. A column's bins
    change only a few times over the image (tens of thousands of flushes per 640x480 frame,
    against one gather per row and bin), and min is exact, so this equals the per-row binning.

    Args:
        depth: (H, Ws) uint16 mm, already reduced to the used columns (a strided view is fine).
        rows: (Hs,) int32 image row of every used row.
        zlo, zhi: (Hs, Ws) uint16: obstacle iff zlo <= d <= zhi.
        nlo, nhi: (Hs, Ws) uint16: an obstacle closer than range_min iff nlo <= d <= nhi.
        kr: (Hs, Ws) float32 horizontal range per mm of depth.
        fl_start: (Hs + 1,) int32: flushes after row i are fl_start[i]:fl_start[i + 1].
        fl_col, fl_bin: (F,) int16: a flush takes column fl_col's run minimum into bin fl_bin.
        rs_start: (Hs + 1,) int32, rs_col: (R,) int16: columns whose run ends after row i.
        acc: (Ws,) float32 work space.
        out: (n,) float32, overwritten.
    """
    n_rows, n_cols = zlo.shape
    inf = np.float32(np.inf)
    seen = SEEN
    for b in range(out.shape[0]):
        out[b] = inf
    for j in range(n_cols):
        acc[j] = inf
    for i in range(n_rows):
        drow = depth[rows[i]]
        zl = zlo[i]
        zh = zhi[i]
        nl = nlo[i]
        nh = nhi[i]
        k = kr[i]
        for j in range(n_cols):  # branch-free and an unconditional store, so LLVM vectorises it
            d = drow[j]
            obstacle = (zl[j] <= d) & (d <= zh[j])
            close = (nl[j] <= d) & (d <= nh[j])
            # obstacle range < SEEN (a reading, no obstacle) < inf (no reading); -inf too close
            v = np.float32(d) * k[j] if obstacle else (seen if d != 0 else inf)
            v = -inf if close else v
            acc[j] = min(acc[j], v)
        for e in range(fl_start[i], fl_start[i + 1]):
            b = fl_bin[e]
            out[b] = min(out[b], acc[fl_col[e]])
        for e in range(rs_start[i], rs_start[i + 1]):
            acc[rs_col[e]] = inf
    nan = np.float32(np.nan)
    for b in range(out.shape[0]):
        v = out[b]
        out[b] = inf if v == seen else (nan if v == inf else v)


@kernel
def paper_scan_kernel(depth, row0, row_step, lo_mm, hi_mm, factor, range_per_z, index, scratch, out):  # noqa: ANN001, ANN201, PLR0913
    """Eq. 1, 2 and 4 over a band of rows, then the original's column-to-bin map.

    Args:
        depth: (H, W) uint16 mm.
        row0, row_step: the band's first row and stride; rows are row0 + i * row_step, i < len(lo_mm).
        lo_mm, hi_mm: (B,) uint16: a reading counts iff lo <= d <= hi (range and eq. 5 ground test).
        factor: (B,) float32 metres per mm times eq. 4's tilt factor.
        range_per_z: (W,) float32 sqrt(1 + ((u - cx) / fx)^2), eq. 2 folded into the range.
        index: (W,) int64 bin of every column.
        scratch: (2, W) float32 work space.
        out: (n,) float32 ranges, overwritten: NaN no reading, +inf nothing counted.
    """
    n_bands = lo_mm.shape[0]
    width = depth.shape[1]
    inf = np.float32(np.inf)
    a = scratch[0]
    b = scratch[1]
    col_max = np.zeros(width, np.uint16)
    for c in range(width):
        a[c] = inf
    for i in range(n_bands):
        drow = depth[row0 + i * row_step]
        lo = lo_mm[i]
        hi = hi_mm[i]
        f = factor[i]
        # "ping-pong": read a, write b, so LLVM emits a blend and a plain store rather than a
        # masked store (vmaskmovps), which is microcoded and ~4x slower on AMD Zen
        for c in range(width):
            d = drow[c]
            z = np.float32(d) * f
            ok = (lo <= d) & (d <= hi) & (z < a[c])
            b[c] = z if ok else a[c]
            col_max[c] = max(col_max[c], d)
        a, b = b, a
    for k in range(out.shape[0]):
        out[k] = np.float32(np.nan)
    for c in range(width):
        z = a[c]
        r = z * range_per_z[c] if z < inf else (inf if col_max[c] > 0 else np.float32(np.nan))
        k = index[c]
        cur = out[k]
        if np.isnan(cur) or r < cur:  # fmin: a number beats NaN; colliding columns keep the nearest
            out[k] = r
