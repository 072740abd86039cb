"""Compiled per-frame kernels of the scan stage; the tables they read are built in scan.py.

Both are row-major single passes over the image (the image is stored row by row; walking it column
by column, as the original does, costs ~4x in cache misses: ../shared/reference/performance.md).
"""

from __future__ import annotations

import numpy as np

from depthnav_daemon.pipeline._jit import kernel

SEEN = np.float32(1e30)  # "valid readings, no obstacle": sorts between ranges and no-data (+inf)


@kernel
def exact_scan_kernel(depth, rows, zlo, zhi, nlo, nhi, kr, g_lo, g_hi, cb_lo, cb_hi, out):  # noqa: ANN001, ANN201, PLR0913
    """Exact scan of one frame into ``out`` (n,) float32, REP 117 values.

    Args:
        depth: (H, Ws) uint16 mm, already reduced to the used columns (a strided view is fine).
        rows: (Hs,) int32 image row of every used row.
        zlo, zhi: (Hs, Ws) uint16: obstacle iff zlo <= d <= zhi.
        nlo, nhi: (Hs, Ws) uint16: an obstacle closer than range_min iff nlo <= d <= nhi.
        kr: (Hs, Ws) float32 horizontal range per mm of depth.
        g_lo, g_hi: (Hs, n) int16 interval of columns feeding bin b in row i; Ws = none.
        cb_lo, cb_hi: (Hs, Ws) int16 first and last bin fed by a column (cb_lo > cb_hi = none).
        out: (n,) float32, overwritten.
    """
    n_rows, n_cols = zlo.shape
    n = out.shape[0]
    inf = np.float32(np.inf)
    for b in range(n):
        out[b] = inf
    val = np.empty(n_cols + 1, np.float32)
    val[n_cols] = inf
    for i in range(n_rows):
        drow = depth[rows[i]]
        zl = zlo[i]
        zh = zhi[i]
        nl = nlo[i]
        nh = nhi[i]
        k = kr[i]
        hits = 0
        for j in range(n_cols):  # branch-free so that LLVM vectorises it
            d = drow[j]
            obstacle = (zl[j] <= d) & (d <= zh[j])
            close = (nl[j] <= d) & (d <= nh[j])
            v = np.float32(d) * k[j] if obstacle else inf
            v = -inf if close else v
            val[j] = v
            hits += obstacle | close
        if hits == 0:
            continue  # nothing in this row's height band
        first = 0
        while val[first] == inf:
            first += 1
        last = n_cols - 1
        while val[last] == inf:
            last -= 1
        # bearings fall as columns grow: the last obstacle column feeds the lowest bins
        lo = g_lo[i]
        hi = g_hi[i]
        for b in range(cb_lo[i, last], cb_hi[i, first] + 1):
            c0 = lo[b]
            c1 = hi[b]
            m = min(val[c0], val[c1])
            for c in range(c0 + 1, c1):  # a bin holding three or more pixel centres: rare
                m = min(m, val[c])
            out[b] = min(out[b], m)
    # bins without an obstacle: +inf if some used pixel feeding them has a reading, else NaN
    for b in range(n):
        if out[b] != inf:
            continue
        seen = False
        for i in range(n_rows):
            for j in range(g_lo[i, b], min(g_hi[i, b], n_cols - 1) + 1):
                if depth[rows[i], j] != 0:
                    seen = True
                    break
            if seen:
                break
        if not seen:
            out[b] = np.float32(np.nan)


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
