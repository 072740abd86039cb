"""Compiled per-frame kernel of the cliff stage; the tables it reads are built in cliff.py.

One row-major sweep per block row: first the drop-off samples are counted per sample column (a
per-column accumulator, vectorised; counting straight into ``counts[bj, c // bs]`` is ~10x slower,
../shared/reference/performance.md §5.1), the block row's blocks are decided (eq. 7-8), then the
same rows (still in cache) feed the cliff scan with the run-minimum scheme of the exact scan.
"""

from __future__ import annotations

import numpy as np

from depthnav_daemon.pipeline._jit import kernel
from depthnav_daemon.pipeline.scan_kernels import SEEN


@kernel
def cliff_kernel(depth, rows, nj, ni, lo, hi, range_m, block_ok, thresh,  # noqa: ANN001, ANN201, PLR0913
                 ev_start, ev_col, ev_lo, ev_hi, colcnt, fcol, acc, found, out):
    """Blocks with drop-offs and the cliff scan of one frame.

    Args:
        depth: (H, C) uint16 mm, the sample columns only (a column-strided view is fine; with
            stride 1 it is contiguous and the sweeps vectorise); sample (i, k) is depth[rows[i], k].
        rows: (R,) intp image row of every sample row, block row by block row (nj rows each).
        nj, ni: sample rows and columns per block.
        lo, hi: (R, C) uint16: a sample is a drop-off iff lo < d < hi.
        range_m: (R, C) float32 horizontal range of the sample's floor point, metres.
        block_ok: (nbr, nbc) bool: the block's centre ray meets the floor (it can be reported).
        thresh: drop-off samples a block needs (eq. 8).
        ev_start, ev_col, ev_lo, ev_hi: run ends over the sample grid (``scan_kernels.run_ends``;
            a sample spans col_step pixels, often several bins, so a run flushes a bin range).
        colcnt: (C,) uint16, fcol: (C,) bool, acc: (C,) float32: work space.
        found: (nbr, nbc) bool, overwritten: blocks that are negative obstacles.
        out: (n,) float32 cliff scan, overwritten (REP 117: range, +inf, NaN).
    """
    n_cols = lo.shape[1]
    nbr, nbc = found.shape
    inf = np.float32(np.inf)
    seen = SEEN
    for b in range(out.shape[0]):
        out[b] = inf
    for k in range(n_cols):
        acc[k] = inf
    for bj in range(nbr):
        for k in range(n_cols):
            colcnt[k] = 0
        for jj in range(nj):
            i = bj * nj + jj
            drow = depth[rows[i]]
            lo_i = lo[i]
            hi_i = hi[i]
            for k in range(n_cols):
                d = drow[k]
                colcnt[k] += (lo_i[k] < d) & (d < hi_i[k])
        any_found = False
        for bi in range(nbc):
            s = 0
            for ii in range(ni):
                s += colcnt[bi * ni + ii]
            f = (s >= thresh) & block_ok[bj, bi]
            found[bj, bi] = f
            any_found |= f
            for ii in range(ni):
                fcol[bi * ni + ii] = f
        for jj in range(nj):
            i = bj * nj + jj
            drow = depth[rows[i]]
            if any_found:
                lo_i = lo[i]
                hi_i = hi[i]
                r_i = range_m[i]
                for k in range(n_cols):
                    d = drow[k]
                    marked = (lo_i[k] < d) & (d < hi_i[k]) & fcol[k]
                    # a marked sample has a reading: never report it as "no reading"
                    v = min(r_i[k], seen) if marked else (seen if d != 0 else inf)
                    acc[k] = min(acc[k], v)
            else:
                for k in range(n_cols):
                    d = drow[k]
                    acc[k] = min(acc[k], seen if d != 0 else inf)
            for e in range(ev_start[i], ev_start[i + 1]):
                c = ev_col[e]
                a = acc[c]
                for b in range(ev_lo[e], ev_hi[e] + 1):
                    out[b] = min(out[b], a)
                acc[c] = inf
    nan = np.float32(np.nan)
    for b in range(out.shape[0]):
        v = out[b]
        out[b] = inf if v == seen else (nan if v == inf else v)
