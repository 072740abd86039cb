"""Compiled per-frame kernels of the scan stage; the tables they read are built in scan.py.

Both are row-major single passes over the image (the image is stored row by row; walking it column
by column, as the original does, costs ~4x in cache misses: ../shared/reference/performance.md).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from depthnav_daemon.pipeline._jit import kernel

I32 = NDArray[np.int32]


# Packed int32 codes of the scan and cliff kernels: the low CODE_BITS bits hold a column; the bits
# above hold a bin or a sample row (a flush code: column | run-ends flag << 15 | bin << 16).
# Columns and bins stay below 32768.
CODE_BITS = 15
CODE_MASK = (1 << CODE_BITS) - 1
MAX_CODE_INDEX = CODE_MASK
# columns per block of the exact scan kernel (scan_blocks): 4 AVX2 vectors of uint16; smaller
# blocks skip the floor more finely but cost more per block
BLOCK = 64
# a row's "has a reading" flag before it is looked at


def run_flush_codes(
    cb_lo: NDArray[np.integer], cb_hi: NDArray[np.integer], n_bins: int, row_block: int = 0
) -> tuple[I32, I32]:
    """Where the runs of a run-minimum kernel end, as one packed code per (run, bin): what the
    exact scan and cliff kernels read.

    A run of column c is a stretch of rows over which c feeds the same bins; it ends after row i
    when row i + 1 feeds other bins, or i is the last row. One int32 per flush instead of
    separate column, bin and reset lists: the kernel's flush loop is bound by its loads and
    stores (~1 ns a flush against ~2-3 ns with three lists).

    Args:
        cb_lo, cb_hi: (Hs, Ws) first and last bin each pixel (or sample) feeds (cb_lo > cb_hi:
            none), rows in the order the kernel walks them; Ws and the bins below 32768.
        n_bins: bins of the scan; a run feeding none is flushed into bin n_bins (a scratch slot
            the kernel's output has beyond the scan), so that its column starts again too.
        row_block: if > 0, every run also ends after each row_block-th row (a kernel that may
            skip whole blocks of rows needs no run to cross into them).

    Returns:
        fl_start: (Hs + 1,) the flushes after row i are fl_start[i]:fl_start[i + 1];
        fl_code: (F,) ``col | last << 15 | bin << 16``: column col's run minimum goes into bin; a
        run's bins are consecutive, and its last carries ``last`` (the column starts a new run).
    """
    # compiled (releases the GIL): numpy held it for ~5 ms at 1280x720 on the table worker
    return flush_codes_kernel(
        np.ascontiguousarray(cb_lo), np.ascontiguousarray(cb_hi), int(n_bins), int(row_block)
    )


@kernel
def flush_codes_kernel(cb_lo, cb_hi, n_bins, row_block):
    """run_flush_codes: two passes over (Hs, Ws), counting then writing; (fl_start, fl_code)."""
    hs, ws = cb_lo.shape
    fl_start = np.zeros(hs + 1, np.int32)
    total = 0
    for p in range(2):
        if p == 1:
            fl_code = np.empty(total, np.int32)
        else:
            fl_code = np.empty(0, np.int32)
        e = 0
        for i in range(hs):
            block_end = row_block > 0 and (i + 1) % row_block == 0
            for j in range(ws):
                lo = np.int64(cb_lo[i, j])
                hi = np.int64(cb_hi[i, j])
                if i + 1 < hs and not block_end and cb_lo[i + 1, j] == lo and cb_hi[i + 1, j] == hi:
                    continue  # the run goes on
                if hi < lo:
                    lo = n_bins
                    hi = n_bins
                if p == 1:
                    for b in range(lo, hi + 1):
                        last = np.int64(1) if b == hi else np.int64(0)
                        fl_code[e] = np.int32(j | (last << CODE_BITS) | (b << (CODE_BITS + 1)))
                        e += 1
                else:
                    e += hi - lo + 1
            if p == 0:
                fl_start[i + 1] = e
        total = e
    return fl_start, fl_code


# The kernels index the 2-D arrays with an unsigned row and column offset rather than take row
# views or slices: a view costs numba two atomic reference-count updates (~40 ns, as much as a
# block's work), and an unsigned index needs no wrap-around check, so LLVM vectorises the loops.
# For the same reason the exact scan's per-block loops are written out in the kernel rather than
# in inlined helpers: numba's inlining gives each array argument a new variable, with an atomic
# increment and decrement per call, which its pruning pass cannot remove across the loops
# (2026-12-02: 10-18 % of the kernel at every mount).


@kernel
def exact_scan_kernel(
    depth,
    rows,
    near_lo,
    near_hi,
    obst_hi,
    kr,
    blk,
    fl_blk,
    fl_code,
    reach_start,
    reach_code,
    short,
    range_max,
    acc,
    out,
    acc_far,
    far,
):
    """Exact scan of one frame into ``out[:n]`` (float32, REP 117 values), and the farthest
    obstacle of each bin into ``far[:n]``.

    One row-major pass keeps a running minimum per column (``acc``) for as long as the column
    feeds the same bins; where a column's bins change from one row to the next (a "run" ends),
    the run's minimum is flushed into those bins and the column starts again. A column's bins
    change only a few times over the image, and min is exact, so this equals the per-row binning.

    Each row is looked at in blocks of BLOCK columns (scan_blocks): a block none of whose
    depths can be an obstacle or too close is not read further, and its flushes are skipped while
    its columns hold nothing (+inf). A bin left at +inf is NaN unless one of its runs reads at or
    beyond ``range_max`` (horizontal range) at its last row whose floor point lies at or beyond
    range_max: that ray was seen free that far (asked while the row is in cache).

    Args:
        depth: (H, Ws) uint16 mm, already reduced to the used columns (a strided view is fine).
        rows: (Hs,) int32 image row of every used row.
        near_lo, near_hi, obst_hi: (Hs, Ws) uint16: an obstacle closer than range_min iff
            near_lo <= d <= near_hi; an obstacle in range iff near_hi < d <= obst_hi (three
            thresholds, not four: the two intervals always adjoin, see scan._exact_table).
        kr: (Hs, Ws) float32 horizontal range per mm of depth.
        blk: (4, Hs, nb) uint16 block bounds (scan_blocks.block_tables): nb = ceil(Ws / BLOCK).
        fl_blk: (Hs * nb + 1,) int32: the flushes after row i in block k are
            fl_blk[i * nb + k]:fl_blk[i * nb + k + 1].
        fl_code: (F,) int32 ``col | last << 15 | bin << 16``: a flush takes column col's run
            minimum into bin; ``last``: the run ends here, the column starts again.
        reach_start: (Hs + 1,) int32, reach_code: (E,) int32 ``col | bin << 15``: each run's
            range_max row (its last row whose floor point lies at or beyond range_max,
            scan_table.reach_limits), by row: row ii's are reach_code[reach_start[ii]:
            reach_start[ii + 1]], asked while the row is in cache.
        short: (n,) bool: bins whose view does not reach range_max (coverage.floor_extent):
            NaN where no obstacle is found, without looking.
        range_max: float32 m, the scan's range_max.
        acc: (Ws,) float32 work space.
        out: (n + 1,) float32, overwritten: the scan in out[:n]; out[n] is scratch (runs that
            feed no bin are flushed there).
        acc_far: (Ws,) float32 work space.
        far: (n + 1,) float32, overwritten: per bin the horizontal range of its farthest obstacle
            pixel (-inf: none), the same way (the memory: what a bin saw beyond its nearest).
    """
    n_rows, n_cols = near_lo.shape
    nb = blk.shape[2]
    block = BLOCK
    inf = np.float32(np.inf)
    zero = np.float32(0.0)
    for b in range(out.shape[0]):
        out[b] = inf
        far[b] = -inf
    for j in range(n_cols):
        acc[j] = inf
        acc_far[j] = -inf
    dirty = np.zeros(nb, np.bool_)  # some column of the block holds a run minimum below +inf
    kind = np.zeros(nb, np.uint8)
    # per bin: a run's range_max row reads that far; one reads something nearer
    reach = np.zeros(out.shape[0], np.bool_)
    blocked = np.zeros(out.shape[0], np.bool_)
    for ii in range(n_rows):
        i = np.uint64(ii)
        r = np.uint64(rows[ii])
        # the +inf question, asked of each run's range_max row while it is in cache (asked at
        # the end, the rows were cold: twice the kernel's time on the fixture)
        for e in range(reach_start[ii], reach_start[ii + 1]):
            x = np.uint32(reach_code[e])
            b = x >> np.uint32(CODE_BITS)
            c = np.uint64(x & np.uint32(CODE_MASK))
            d = depth[r, c]
            if d != 0:
                far_enough = np.float32(d) * kr[i, c] >= range_max
                reach[b] |= far_enough
                blocked[b] |= not far_enough
        # no software prefetch of the rows ahead: the CPU's own prefetcher keeps up, and 20 hints
        # a row cost more than they saved (2026-12-02, 12 frames in turn: 3.5-9 % faster without
        # at every mount and at both sizes, 2.4 % on 150 frames that are not in the cache; hints
        # into L2 only or 8 rows ahead alike; an earlier day had measured the opposite)
        for k in range(nb):
            # what each block needs (kind[k]): 0 nothing (no depth is an obstacle or too close),
            # 1 ranges only (every depth an obstacle for every pixel), 2 every threshold
            j0 = np.uint64(k * block)
            n = min(block, n_cols - k * block)
            lo = blk[0, i, k]
            hi = blk[1, i, k]
            kind[k] = 0
            if hi < lo:
                continue
            # min of d - lo in uint16 arithmetic: some d lies in [lo, hi] iff it is <= hi - lo
            # (a depth below lo wraps around to a large value); one horizontal reduction a
            # block on the common path (most blocks hold no obstacle)
            m = np.uint16(65535)
            if n == BLOCK:  # a fixed trip count: no remainder loop, fully unrolled
                for jj in range(BLOCK):
                    m = min(m, np.uint16(depth[r, j0 + np.uint64(jj)] - lo))
            else:
                for jj in range(n):
                    m = min(m, np.uint16(depth[r, j0 + np.uint64(jj)] - lo))
            if m > np.uint16(hi - lo):
                continue
            # the lowest reading less one (zeros wrap around to 65535) and the highest depth:
            # every reading an obstacle for every pixel (zeros allowed: a wall with a few holes
            # in it is common)
            mn1 = np.uint16(65535)
            mx = np.uint16(0)
            for jj in range(n):
                d = depth[r, j0 + np.uint64(jj)]
                mn1 = min(mn1, np.uint16(d - np.uint16(1)))
                mx = max(mx, d)
            kind[k] = 1 if mn1 >= blk[2, i, k] and mx <= blk[3, i, k] else 2
        k = 0
        while k < nb:  # one loop per stretch of blocks of one kind: long loops vectorise well
            kk = kind[k]
            k2 = k + 1
            while k2 < nb and kind[k2] == kk:
                k2 += 1
            if kk != 0:
                j0 = np.uint64(k * block)
                n = min(k2 * block, n_cols) - k * block
                # acc = min(acc, what each pixel says): its range if an obstacle, -inf if too
                # close, else +inf. Branch-free, so LLVM vectorises it: kr is read whatever the
                # depth (a read under a condition becomes a masked load, ~2.4x slower on AMD
                # Zen), and "+ 0" (exact: no value is -0) keeps the store unconditional (LLVM
                # otherwise stores only where the minimum changed: a masked store, microcoded)
                if kk == 1:  # every reading (d > 0) an obstacle for every pixel: no thresholds
                    for jj in range(n):
                        j = j0 + np.uint64(jj)
                        d = depth[r, j]
                        v = np.float32(d) * kr[i, j]
                        acc_far[j] = max(acc_far[j], v if d != 0 else -inf) + zero
                        v = v if d != 0 else inf
                        acc[j] = min(acc[j], v) + zero
                else:
                    for jj in range(n):
                        j = j0 + np.uint64(jj)
                        d = depth[r, j]
                        nh = near_hi[i, j]
                        obstacle = (nh < d) & (d <= obst_hi[i, j])
                        close = (near_lo[i, j] <= d) & (d <= nh)
                        v = np.float32(d) * kr[i, j]
                        acc_far[j] = max(acc_far[j], v if obstacle else -inf) + zero
                        v = v if obstacle else inf
                        v = -inf if close else v
                        acc[j] = min(acc[j], v) + zero
                for q in range(k, k2):
                    dirty[q] = True
            k = k2
        k = 0
        while k < nb:  # the flushes of a stretch of pending blocks are one loop
            if not dirty[k]:
                k += 1  # every flush would be min(out, +inf) and every reset a no-op
                continue
            k2 = k + 1
            while k2 < nb and dirty[k2]:
                k2 += 1
            for e in range(fl_blk[ii * nb + k], fl_blk[ii * nb + k2]):
                # unsigned: the indices below need no wrap-around check for negative values
                x = np.uint32(fl_code[e])
                c = x & np.uint32(CODE_MASK)
                b = x >> np.uint32(CODE_BITS + 1)
                a = acc[c]
                o = out[b]
                out[b] = a if a < o else o
                af = acc_far[c]
                of = far[b]
                far[b] = af if af > of else of
                ends = x & np.uint32(1 << CODE_BITS)  # the run ends here
                acc[c] = inf if ends else a
                acc_far[c] = -inf if ends else af
            for q in range(k, k2):
                if kind[q] == 0:  # (a block with obstacles in this row is pending anyway)
                    # still pending: some column's run minimum below +inf
                    q0 = np.uint64(q * block)
                    m2 = inf
                    for jj in range(min(block, n_cols - q * block)):
                        m2 = min(m2, acc[q0 + np.uint64(jj)])
                    dirty[q] = m2 != inf
            k = k2
    n = out.shape[0] - 1
    nan = np.float32(np.nan)
    for b in range(n):
        # +inf only where the view reaches range_max, a run of the bin reads that far at its
        # range_max row (its ray was seen free that far; the safety contract) and none reads
        # nearer: a bin whose readings end nearer (something below the obstacle band in the way:
        # a wall's foot under the view's top edge, seed 1424), or that read nothing that far
        # (no return from far away), is unknown
        if out[b] == inf and (short[b] or not reach[b] or blocked[b]):
            out[b] = nan


@kernel
def paper_scan_kernel(
    depth, row0, row_step, lo_mm, hi_mm, factor, range_per_z, index, scratch, out
):
    """Eq. 1, 2 and 4 over a band of rows, then the original's column-to-bin map.

    Args:
        depth: (H, W) uint16 mm.
        row0, row_step: the band's first row and stride; rows are row0 + i * row_step, i <
            len(lo_mm).
        lo_mm, hi_mm: (B,) uint16: a reading counts iff lo <= d <= hi (range and eq. 5 ground test).
        factor: (B,) float32 metres per mm times eq. 4's tilt factor.
        range_per_z: (W,) float32 sqrt(1 + ((u - cx) / fx)^2), eq. 2 folded into the range.
        index: (W,) int64 bin of every column; where two columns share a bin, the later column's
            range is kept, as in the original (not the nearer one).
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
        # the original's ``ranges[index[u]] = r``: of two columns in one bin the later one wins
        out[index[c]] = r
