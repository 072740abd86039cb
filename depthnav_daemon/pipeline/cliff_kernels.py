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
def cliff_kernel(depth, rows, nj, ni, lo, hi, range_m, first, last, block_ok, thresh,  # noqa: ANN001, ANN201, PLR0913
                 cov_start, cov_row, cov_col, colcnt, found, out):
    """Blocks with drop-offs and the cliff scan of one frame.

    A bin of the cliff scan holds the nearest floor range of the drop-off samples of detected
    blocks that cover it; else +inf if some sample covering it has a reading; else NaN. The sweep
    only counts drop-offs per block (uint16 lanes, no branches); the ranges come from the detected
    blocks alone; and a bin without a drop-off looks through its covering samples (bottom rows
    first, where the floor nearly always gives a reading) only until it meets a reading.

    Args:
        depth: (H, C) uint16 mm, the sample columns only (a column-strided view is fine; with
            stride 1 it is contiguous and the sweep vectorises); sample (i, k) is depth[rows[i], k].
        rows: (R,) intp image row of every sample row, block row by block row (nj rows each).
        nj, ni: sample rows and columns per block.
        lo, hi: (R, C) uint16: a sample is a drop-off iff lo < d < hi.
        range_m: (R, C) float32 horizontal range of the sample's floor point, metres.
        first, last: (R, C) int32 first and last bin a sample covers (first > last: none).
        block_ok: (nbr, nbc) bool: the block's centre ray meets the floor (it can be reported).
        thresh: drop-off samples a block needs (eq. 8).
        cov_start: (n + 1,) int64, cov_row, cov_col: (M,) int32: the samples covering bin b are
            (cov_row[m], cov_col[m]) for m in cov_start[b]:cov_start[b + 1].
        colcnt: (C,) uint16 work space.
        found: (nbr, nbc) bool, overwritten: blocks that are negative obstacles.
        out: (n,) float32 cliff scan, overwritten (REP 117: range, +inf, NaN).
    """
    n_cols = lo.shape[1]
    nbr, nbc = found.shape
    inf = np.float32(np.inf)
    for b in range(out.shape[0]):
        out[b] = inf
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
        for bi in range(nbc):
            s = 0
            for ii in range(ni):
                s += colcnt[bi * ni + ii]
            f = (s >= thresh) & block_ok[bj, bi]
            found[bj, bi] = f
            if not f:
                continue
            # a detected block: its drop-off samples give the cliff ranges of the bins they cover.
            # Column by column, so that the rows of a column that cover the same bins are reduced
            # in a register and written once (one sample after another into the same bins would
            # wait on each other's stores).
            i0 = bj * nj
            for k in range(bi * ni, (bi + 1) * ni):
                f0 = first[i0, k]
                l0 = last[i0, k]
                m = inf
                for i in range(i0, i0 + nj):
                    d = depth[rows[i], k]
                    r = range_m[i, k] if (lo[i, k] < d) & (d < hi[i, k]) else inf  # a select
                    f = first[i, k]
                    l_ = last[i, k]
                    if f != f0 or l_ != l0:
                        if m < inf:
                            for b in range(f0, l0 + 1):
                                out[b] = min(out[b], m)
                        f0 = f
                        l0 = l_
                        m = inf
                    m = min(m, r)
                if m < inf:
                    for b in range(f0, l0 + 1):
                        out[b] = min(out[b], m)
    nan = np.float32(np.nan)
    for b in range(out.shape[0]):
        if out[b] != inf:
            continue
        seen = False
        for m in range(cov_start[b], cov_start[b + 1]):
            if depth[rows[cov_row[m]], cov_col[m]] != 0:
                seen = True
                break
        if not seen:
            out[b] = nan
