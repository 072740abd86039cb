"""Compiled per-frame kernel of the cliff stage; the tables it reads are built in cliff.py.

One row-major sweep per block row: first the drop-off samples are counted per sample column (a
per-column accumulator, vectorised; counting straight into ``counts[bj, c // bs]`` is ~10x slower,
../shared/reference/performance.md §5.1), the block row's blocks are decided (eq. 7-8), then the
same rows (still in cache) feed the cliff scan with the run-minimum scheme of the exact scan, over
the columns of detected blocks only.
"""

from __future__ import annotations

import numpy as np

from depthnav_daemon.pipeline._jit import kernel
from depthnav_daemon.pipeline.scan_kernels import CODE_BITS, CODE_MASK


@kernel
def cliff_kernel(
    depth,
    rows,
    nj,
    ni,
    lo,
    hi,
    range_m,
    block_ok,
    thresh,
    ev_block,
    ev_code,
    cov_start,
    cov_code,
    probe_start,
    probe_code,
    block_xy,
    height,
    bs,
    out,
):
    """Blocks with drop-offs and the cliff scan of one frame.

    A bin of the cliff scan holds the nearest floor range of the drop-off samples of detected
    blocks that cover it; else +inf if some sample covering it has a reading; else NaN.

    Per block row: a sweep counts drop-offs per sample column (uint16 lanes, no branches). If the
    block row holds at least ``thresh`` drop-offs in all, its blocks are decided (eq. 7-8), and
    each stretch of adjacent detected blocks is swept again (its rows still in cache) for the
    ranges, with the run-minimum scheme of the exact scan: a minimum per column while the column
    covers the same bins, written to them when a run ends (runs end at block-row boundaries too).
    Whether a bin has a reading is asked of one covering sample (its "probe", the lowest: the
    floor near the robot nearly always gives one) while its row is in cache, the other covering
    samples only when the probe has none.

    Args:
        depth: (H, C) uint16 mm, the sample columns only (a column-strided view is fine; with
            stride 1 it is contiguous and the sweeps vectorise); sample (i, k) is depth[rows[i], k].
        rows: (R,) intp image row of every sample row, ascending: block row by block row (nj rows
            each) from the top, so sample rows tb * nj ... hold block row nbr - 1 - tb.
        nj, ni: sample rows and columns per block.
        lo: (R, C) uint16, hi: uint16 scalar: a sample is a drop-off iff lo < d < hi.
        range_m: (R, C) float32 horizontal range of the sample's floor point, metres.
        block_ok: (nbr, nbc) bool: the block's centre ray meets the floor (else never reported).
        thresh: drop-off samples a block needs (eq. 8).
        ev_block: (R, nbc + 1) int64: the flushes after sample row i in the columns of block
            column bi are ev_block[i, bi]:ev_block[i, bi + 1] of ev_code.
        ev_code: (E,) int32 ``col | last << 15 | bin << 16``: column col's run minimum goes into
            bin (bin n: scratch, a run that covers no bin); ``last``: the run ends there.
        cov_start: (n + 1,) int64, cov_code: (M,) int32 ``col | row << 15``: the samples covering
            bin b, cov_start[b]:cov_start[b + 1], the probe last.
        probe_start: (R + 1,) int64, probe_code: (P,) int32 ``col | bin << 15``: the probes in
            sample row i are probe_start[i]:probe_start[i + 1].
        block_xy: (nbr, nbc, 2) float32 floor point of each block's centre ray.
        height, bs: image rows and block side, pixels.
        out: (n + 1,) float32, overwritten: the cliff scan (REP 117: range, +inf, NaN) in
            out[:n], scratch in out[n].

    Returns:
        blocks: (K, 2) int64 (row, col) of the top-left pixel of each negative obstacle, and
        points: (K, 2) float32 their floor points, in row-major block order from the bottom block
        row (as the original lists them).
    """
    n_cols = lo.shape[1]
    nbr, nbc = block_ok.shape
    n = out.shape[0] - 1
    inf = np.float32(np.inf)
    colcnt = np.zeros(n_cols, np.uint16)
    racc = np.full(n_cols, inf, np.float32)
    seen = np.zeros(n, np.bool_)
    found = np.empty((nbr, nbc), np.bool_)
    for b in range(n + 1):
        out[b] = inf
    for tb in range(nbr):  # from the top of the image down: memory upwards
        bj = nbr - 1 - tb
        for k in range(n_cols):
            colcnt[k] = 0
        for jj in range(nj):
            i = tb * nj + jj
            drow = depth[rows[i]]
            lo_i = lo[i]
            for k in range(n_cols):
                d = drow[k]
                colcnt[k] += (lo_i[k] < d) & (d < hi)
            for p in range(probe_start[i], probe_start[i + 1]):
                x = probe_code[p]
                seen[x >> CODE_BITS] = drow[x & CODE_MASK] != 0
        total = 0
        for k in range(n_cols):  # a vectorised sum: most block rows see the floor and no drop-off
            total += colcnt[k]
        if total < thresh:
            for bi in range(nbc):
                found[bj, bi] = False
            continue
        for bi in range(nbc):
            s = 0
            for ii in range(ni):
                s += colcnt[bi * ni + ii]
            found[bj, bi] = (s >= thresh) & block_ok[bj, bi]
        b0 = 0
        while b0 < nbc:  # each stretch [b0, b1) of adjacent detected blocks
            if not found[bj, b0]:
                b0 += 1
                continue
            b1 = b0 + 1
            while b1 < nbc and found[bj, b1]:
                b1 += 1
            c0 = b0 * ni
            c1 = b1 * ni
            acc = racc[c0:c1]
            for jj in range(nj):
                i = tb * nj + jj
                # views from column c0 and a loop from 0: LLVM vectorises this loop, not one
                # over range(c0, c1) (~10x, measured)
                drow = depth[rows[i], c0:c1]
                lo_i = lo[i, c0:c1]
                r_i = range_m[i, c0:c1]
                for k in range(c1 - c0):  # branch-free, unconditional store: vectorised
                    d = drow[k]
                    v = r_i[k] if (lo_i[k] < d) & (d < hi) else inf
                    acc[k] = min(acc[k], v)
                for e in range(ev_block[i, b0], ev_block[i, b1]):
                    x = ev_code[e]
                    c = x & CODE_MASK
                    b = x >> (CODE_BITS + 1)
                    a = racc[c]
                    o = out[b]
                    out[b] = a if a < o else o
                    if x & (1 << CODE_BITS):
                        racc[c] = inf
            b0 = b1
    nan = np.float32(np.nan)
    for b in range(n):
        if out[b] != inf or seen[b]:
            continue
        for m in range(cov_start[b], cov_start[b + 1] - 1):  # the probe (the last) had no reading
            x = cov_code[m]
            if depth[rows[x >> CODE_BITS], x & CODE_MASK] != 0:
                break
        else:
            out[b] = nan
    n_found = 0
    for bj in range(nbr):
        for bi in range(nbc):
            n_found += found[bj, bi]
    blocks = np.empty((n_found, 2), np.int64)
    points = np.empty((n_found, 2), np.float32)
    k = 0
    for bj in range(nbr):  # row-major from the bottom block row
        for bi in range(nbc):
            if found[bj, bi]:
                blocks[k, 0] = height - (bj + 1) * bs
                blocks[k, 1] = bi * bs
                points[k, 0] = block_xy[bj, bi, 0]
                points[k, 1] = block_xy[bj, bi, 1]
                k += 1
    return blocks, points
