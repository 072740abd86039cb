"""Compiled per-frame kernel of the cliff stage; the tables it reads are built in cliff.py.

One row-major sweep per block row: first the drop-off samples are counted per sample column (a
per-column accumulator, vectorised; counting straight into ``counts[bj, c // bs]`` is ~10x slower,
../shared/reference/performance.md §5.1), the block row's blocks are decided (eq. 7-8), then the
same rows (still in cache) feed the cliff scan with the run-minimum scheme of the exact scan.
"""

from __future__ import annotations

import numpy as np

from depthnav_daemon.pipeline._jit import kernel


@kernel
def cliff_kernel(
    depth,
    rows,
    nj,
    ni,
    lo,
    hi,
    range_m,
    block_xy,
    thresh,
    ev_block,
    ev_col,
    ev_lo,
    ev_hi,
    cov_start,
    cov_row,
    cov_col,
    probe_start,
    probe_bin,
    probe_col,
    colcnt,
    fcol,
    racc,
    seen,
    found,
    blocks,
    points,
    out,
):
    """Blocks with drop-offs and the cliff scan of one frame.

    A bin of the cliff scan holds the nearest floor range of the drop-off samples of detected
    blocks that cover it; else +inf if some sample covering it has a reading; else NaN.

    Per block row: a sweep counts drop-offs per sample column (uint16 lanes, no branches) and the
    blocks are decided (eq. 7-8). Only a block row with a detected block is swept again (its rows
    still in cache) for the ranges, with the run-minimum scheme of the exact scan: a minimum per
    column while the column covers the same bins, written to them when a run ends (runs end at
    block-row boundaries too). Whether a bin has a reading is asked of one covering sample (its
    "probe", the lowest: the floor near the robot nearly always gives one) while its row is in
    cache, the other covering samples only when the probe has none.

    Args:
        depth: (H, C) uint16 mm, the sample columns only (a column-strided view is fine; with
            stride 1 it is contiguous and the sweeps vectorise); sample (i, k) is depth[rows[i], k].
        rows: (R,) intp image row of every sample row, ascending: block row by block row (nj rows
            each) from the top, so sample rows tb * nj ... hold block row nbr - 1 - tb.
        nj, ni: sample rows and columns per block.
        lo, hi: (R, C) uint16: a sample is a drop-off iff lo < d < hi.
        range_m: (R, C) float32 horizontal range of the sample's floor point, metres.
        block_xy: (nbr, nbc, 2) float32 floor point of each block's centre ray (not finite: the
            ray misses the floor, the block is never reported).
        thresh: drop-off samples a block needs (eq. 8).
        ev_block: (R, nbc + 1) int64: the run ends after sample row i in the columns of block
            column bi are ev_block[i, bi]:ev_block[i, bi + 1] of ev_col, ev_lo, ev_hi (run ends
            over the sample grid, runs ending at every block row too; ``scan_kernels.run_ends``).
        cov_start: (n + 1,) int64, cov_row, cov_col: (M,) int32: the samples covering bin b are
            (cov_row[m], cov_col[m]) for m in cov_start[b]:cov_start[b + 1].
        probe_start: (R + 1,) int64, probe_bin, probe_col: (P,) int32: the probes in sample row i
            are (probe_bin[p], probe_col[p]) for p in probe_start[i]:probe_start[i + 1]; a bin's
            probe is its last covering sample.
        colcnt: (C,) uint16, fcol: (C,) bool, racc: (C,) float32, seen: (n,) bool,
            found: (nbr, nbc) bool: work space.
        blocks: (nbr * nbc, 2) int64: (block row, block column) of the negative obstacles, from
            the top, in row-major block order (block row 0 = the bottom of the image).
        points: (nbr * nbc, 2) float32: their floor points, same order.
        out: (n,) float32 cliff scan, overwritten (REP 117: range, +inf, NaN).

    Returns:
        The number of negative obstacles (rows of ``blocks`` and ``points`` written).
    """
    n_cols = lo.shape[1]
    nbr, nbc = block_xy.shape[0], block_xy.shape[1]
    inf = np.float32(np.inf)
    n_found = 0
    for b in range(out.shape[0]):
        out[b] = inf
        seen[b] = False
    for k in range(n_cols):
        racc[k] = inf
    for tb in range(nbr):  # from the top of the image down: memory upwards
        bj = nbr - 1 - tb
        for k in range(n_cols):
            colcnt[k] = 0
        for jj in range(nj):
            i = tb * nj + jj
            drow = depth[rows[i]]
            lo_i = lo[i]
            hi_i = hi[i]
            for k in range(n_cols):
                d = drow[k]
                colcnt[k] += (lo_i[k] < d) & (d < hi_i[k])
            for p in range(probe_start[i], probe_start[i + 1]):
                seen[probe_bin[p]] = drow[probe_col[p]] != 0
        any_found = False
        for bi in range(nbc):
            s = 0
            for ii in range(ni):
                s += colcnt[bi * ni + ii]
            f = (s >= thresh) & np.isfinite(block_xy[bj, bi, 0])
            found[bj, bi] = f
            any_found |= f
            for ii in range(ni):
                fcol[bi * ni + ii] = f
        if not any_found:
            continue
        for jj in range(nj):
            i = tb * nj + jj
            drow = depth[rows[i]]
            lo_i = lo[i]
            hi_i = hi[i]
            r_i = range_m[i]
            for k in range(n_cols):  # branch-free, unconditional store: vectorised
                d = drow[k]
                v = r_i[k] if (lo_i[k] < d) & (d < hi_i[k]) & fcol[k] else inf
                racc[k] = min(racc[k], v)
            for bi in range(nbc):
                if not found[bj, bi]:
                    continue  # only the columns of detected blocks hold ranges
                for e in range(ev_block[i, bi], ev_block[i, bi + 1]):
                    c = ev_col[e]
                    m = racc[c]
                    if m < inf:
                        for b in range(ev_lo[e], ev_hi[e] + 1):
                            out[b] = min(out[b], m)
                        racc[c] = inf
    nan = np.float32(np.nan)
    for b in range(out.shape[0]):
        if out[b] != inf or seen[b]:
            continue
        for m in range(cov_start[b], cov_start[b + 1] - 1):  # the probe (the last) had no reading
            if depth[rows[cov_row[m]], cov_col[m]] != 0:
                break
        else:
            out[b] = nan
    for bj in range(nbr):  # row-major from the bottom block row, as the original lists them
        for bi in range(nbc):
            if found[bj, bi]:
                blocks[n_found, 0] = bj
                blocks[n_found, 1] = bi
                points[n_found, 0] = block_xy[bj, bi, 0]
                points[n_found, 1] = block_xy[bj, bi, 1]
                n_found += 1
    return n_found
