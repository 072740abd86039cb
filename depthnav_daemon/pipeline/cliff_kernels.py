"""Compiled per-frame kernel of the cliff stage; the tables it reads are built in cliff_table.py.

One row-major sweep per block row: first the drop-off samples are counted per sample column (a
per-column accumulator, vectorised; counting straight into ``counts[bj, c // bs]`` is ~10x slower,
../shared/reference/performance.md §5.1) and the block row's blocks are decided (eq. 7-8).
``paper``: the same rows (still in cache) then feed the cliff scan with the run-minimum scheme of
the exact scan, over the columns of detected blocks only. ``exact``: after the sweep, the edge of
each drop-off is found per image column (``edges``), only where blocks
were detected.
"""

from __future__ import annotations

import numpy as np

from depthnav_daemon.pipeline._jit import helper, kernel
from depthnav_daemon.pipeline.scan_kernels import CODE_BITS, CODE_MASK

# in this module, not another: numba's cache of cliff_kernel holds the helpers it calls, and is
# only renewed when this file changes
NEVER = 65535  # cliff_table.NEVER_MM: a pixel out of the range limits or at/above the horizon
RUN = 2  # readings in a row that start (drop-offs) or end (others) a run: one alone is noise
UNSEEN = -2  # a row not looked for yet


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
    cov_lo,
    cov_ob,
    probe_start,
    probe_code,
    block_xy,
    height,
    bs,
    out,
    image,
    row0,
    px_band,
    px_xyt,
    px_bins,
    short,
    range_min,
    refine,
):
    """Blocks with drop-offs and the cliff scan of one frame.

    A bin of the cliff scan holds the nearest drop-off range (``refine`` False, paper: the floor
    range of the drop-off samples of detected blocks that cover it; True, exact: the edges
    ``edges`` finds); else NaN if ``short[b]``; else (exact) +inf if one of its reach samples
    (its highest sample row read and the next one above, past range_max,
    cliff_table._reach_samples) within range reads the floor, and one past it where the bin has
    any there (the stretch up to range_max seen), none reads a drop-off (one that
    did not make a block, or an edge crossing the bin; a reading beyond ``hi`` says nothing of
    the floor on the way) or something standing on the floor, and no sample of their sample
    columns or the columns beside them read a drop-off in any row (a hole too small for a block,
    or an edge at a slant between two sample columns: seed 1336 read +inf over an edge 0.8 m
    away); (paper) +inf if any covering sample has a reading; else NaN.

    Per block row: a sweep counts drop-offs per sample column (uint16 lanes, no branches). If the
    block row holds at least ``thresh`` drop-offs in all, its blocks are decided (eq. 7-8), and
    each stretch of adjacent detected blocks is swept again (its rows still in cache) for the
    ranges, with the run-minimum scheme of the exact scan: a minimum per column while the column
    covers the same bins, written to them when a run ends (runs end at block-row boundaries too).
    Whether a bin is seen that far: paper, asked of one reach sample (its "probe", in its highest
    row read) while its row is in cache, the other reach samples only when the probe has none;
    exact, every reach sample of a bin that found no drop-off, at the end (one reading a drop-off
    decides it).

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
        cov_start: (n + 1,) int64, cov_code: (M,) int32 ``col | row << 15``: the reach samples
            of bin b, cov_start[b]:cov_start[b + 1], the probe last; cov_lo, cov_ob: (M,)
            uint16 (exact) their bounds: a reading beyond cov_lo is a drop-off, one short of
            cov_ob (65535: none) stands on the floor (CliffTable.cov_lo_mm: past range_max too).
        probe_start: (R + 1,) int64, probe_code: (P,) int32 ``col | bin << 15``: the probes in
            sample row i are probe_start[i]:probe_start[i + 1].
        block_xy: (nbr, nbc, 2) float32 floor point of each block's centre ray.
        height, bs: image rows and block side, pixels.
        out: (n + 1,) float32, overwritten: the cliff scan (REP 117: range, +inf, NaN) in
            out[:n], scratch in out[n].
        image: (H, W) uint16 mm, the whole frame (the edges are found on every column).
        row0, px_band, px_xyt, px_bins: the pixel tables of image rows row0..H-1
            (cliff_table.CliffTable; empty unless ``refine``).
        short: (n,) bool: bins the read rows do not see out to range_max (NaN without a drop-off).
        range_min: metres; an edge nearer than this is reported at range_min.
        refine: the exact method's per-column edges instead of the samples' floor ranges.

    Returns:
        blocks: (K, 2) int64 (row, col) of the top-left pixel of each negative obstacle, in
        row-major block order from the bottom block row (as the original lists them), and
        points: (P, 2) float32 floor points: ``refine``: one per column with an edge (``edges``);
        else each block's centre ray's (P = K, in block order).
    """
    n_cols = lo.shape[1]
    nbr, nbc = block_ok.shape
    paper = not refine  # the original: any reading of a covering sample makes its bin +inf
    n = out.shape[0] - 1
    inf = np.float32(np.inf)
    colcnt = np.zeros(n_cols, np.uint16)
    dropped = np.zeros(n_cols, np.bool_)  # exact: a sample column read a drop-off somewhere
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
            if paper:  # the exact method reads every reach sample at the end
                for p in range(probe_start[i], probe_start[i + 1]):
                    x = probe_code[p]
                    seen[x >> CODE_BITS] = drow[x & CODE_MASK] != 0
        total = 0
        for k in range(n_cols):  # a vectorised sum: most block rows see the floor and no drop-off
            total += colcnt[k]
        if refine and total > 0:
            for k in range(n_cols):
                dropped[k] |= colcnt[k] > 0
        if total < thresh:
            for bi in range(nbc):
                found[bj, bi] = False
            continue
        for bi in range(nbc):
            s = 0
            for ii in range(ni):
                s += colcnt[bi * ni + ii]
            found[bj, bi] = (s >= thresh) & block_ok[bj, bi]
        if refine:
            continue
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
    n_found = 0
    for bj in range(nbr):
        for bi in range(nbc):
            n_found += found[bj, bi]
    edge_xy = np.empty((0, 2), np.float32)
    if refine and n_found > 0:
        edge_xy = edges(image, row0, px_band, px_xyt, px_bins, found, height, bs, range_min, out)
    nan = np.float32(np.nan)
    for b in range(n):
        if out[b] != inf:
            continue
        if short[b]:
            out[b] = nan
            continue
        if paper:
            if seen[b]:
                continue
            for m in range(cov_start[b], cov_start[b + 1] - 1):  # the probe (last) read nothing
                x = cov_code[m]
                if depth[rows[x >> CODE_BITS], x & CODE_MASK] != 0:
                    break
            else:
                out[b] = nan
            continue
        # exact: +inf if a reach sample reads the floor, none a drop-off (a drop-off too few
        # samples saw to make a block, or whose edge crosses the bin, is not clear) and none
        # something standing on the floor (it hides the floor behind it: a costmap fed the cliff
        # scan would clear a drop-off marked there before; seed 1422)
        floor = False
        past = False  # the bin has reach samples past range_max
        past_floor = False  # and one of them read the floor
        for m in range(cov_start[b], cov_start[b + 1]):
            x = cov_code[m]
            i = x >> CODE_BITS
            c = x & CODE_MASK
            d = depth[rows[i], c]
            near = dropped[max(c - 1, 0)] | dropped[c] | dropped[min(c + 1, n_cols - 1)]
            lo_m = cov_lo[m]
            o = cov_ob[m]
            above = (d != 0) & (d < o) & (o != np.uint16(65535))
            if ((lo_m < d) & (d < hi)) | near | above:
                floor = False
                break
            # the floor read within range (lo[i, c] is 65535 past range_max) and past it: the
            # stretch between the highest row read and range_max was seen
            read = (d != 0) & (d <= lo_m)
            beyond = lo[i, c] == np.uint16(65535)
            floor = floor | (read & ~beyond)
            past = past | beyond
            past_floor = past_floor | (read & beyond)
        if not floor or (past and not past_floor):
            out[b] = nan
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
    if refine:
        return blocks, edge_xy
    return blocks, points


@helper
def edges(image, row0, band, xyt, bins, found, height, bs, range_min, out):
    """The edge of every drop-off per image column, into the cliff scan; their floor points.

    A run of detected blocks up a block column says a drop-off is there; its edge is searched for
    on every image column of the run, of the block below it (the block straddling the edge may not
    have reached the threshold) and of the same blocks in the block columns either side. The edge
    is then followed sideways: where a window's outermost column found one, the next block column
    is searched there (the edge's block row and the one above, those not searched yet), and so
    on while edges are found (a drop-off goes on where block alignment or dropout kept its blocks
    from the threshold): depth first, a stack of windows. How a window is searched: ``_window``.

    Args:
        image, row0, band, xyt, bins, height, bs, range_min, out: as ``cliff_kernel``'s image,
            row0, px_band, px_xyt, px_bins, ...
        found: (nbr, nbc) bool detected blocks, block row 0 the lowest.

    Returns:
        (P, 2) float32 the edge points in the order they were found (the windows' order: the
        detected ones by block column then upwards, each followed sideways before the next).
    """
    nbr, nbc = found.shape
    seed = np.zeros((nbr, nbc), np.bool_)
    for bi in range(nbc):
        for bj in range(nbr):
            if found[bj, bi] and (bj == 0 or not found[bj - 1, bi]):
                top = bj
                while top + 1 < nbr and found[top + 1, bi]:
                    top += 1
                for b2 in range(max(bi - 1, 0), min(bi + 2, nbc)):
                    for b1 in range(max(bj - 1, 0), top + 1):
                        seed[b1, b2] = True
    # a stack of windows (block column, lowest and top block rows); a block is pushed once
    win = np.zeros((nbr, nbc), np.bool_)  # the blocks pushed
    stack = np.empty((nbr * nbc, 3), np.int64)
    n = 0
    for bi in range(nbc - 1, -1, -1):  # pushed backwards: popped by column, then upwards
        for bj in range(nbr - 1, -1, -1):
            if seed[bj, bi] and (bj == 0 or not seed[bj - 1, bi]):
                top = bj
                while top + 1 < nbr and seed[top + 1, bi]:
                    top += 1
                win[bj : top + 1, bi] = True
                stack[n, 0], stack[n, 1], stack[n, 2] = bi, bj, top
                n += 1
    w = image.shape[1]
    pts = np.empty((2 * w, 2), np.float32)  # grown when full (a column: an edge per window)
    edge = np.full(w, -1, np.int64)  # per column: the row of the edge its last window found
    done = np.full(w, -1, np.int64)  # per column: the floor row its last edge was reported at
    scratch = np.empty((2, bs), np.int64)  # _window's per-column results, allocated once
    k = 0
    while n > 0:
        n -= 1
        bi, bj, top = stack[n, 0], stack[n, 1], stack[n, 2]
        edge[bi * bs : (bi + 1) * bs] = -1
        if k + bs > pts.shape[0]:
            more = np.empty((2 * pts.shape[0], 2), np.float32)
            more[:k] = pts[:k]
            pts = more
        k = _window(
            image, row0, band, xyt, bins, bi, bj, top, height, bs, range_min, out, pts, k, edge,
            done, scratch,
        )  # fmt: skip
        for side in range(2):  # follow the edges found on the window's outermost columns
            c = bi * bs + (bs - 1) * side
            b2 = bi + 2 * side - 1
            if edge[c] < 0 or b2 < 0 or b2 >= nbc:
                continue
            # the edge's block row and the one above (a lower edge there is found all the same:
            # the search goes down from a window's bottom to the floor), those not pushed yet
            be = (height - 1 - edge[c]) // bs
            b1 = be
            while b1 <= min(be + 1, nbr - 1):
                if win[b1, b2]:
                    b1 += 1
                    continue
                stack[n, 0], stack[n, 1] = b2, b1
                while b1 <= min(be + 1, nbr - 1) and not win[b1, b2]:
                    win[b1, b2] = True
                    b1 += 1
                stack[n, 2] = b1 - 1
                n += 1
    return pts[:k]


@helper
def _window(
    image, row0, band, xyt, bins, bi, bj, top, height, bs, range_min, out, pts, k, edge, done, scr
):
    """Search the columns of block column ``bi``, block rows ``bj``..``top``, for an edge each;
    record them (``edge``: the row of the first lower-floor pixel), report them into ``out`` and
    ``pts`` from index ``k``; returns the next index.

    Each column is searched upwards from the bottom of the window for its first lower-floor
    pixel: the lowest drop-off reading with another one above it before any other reading (one
    alone is noise); 0 readings and pixels out of the range limits say nothing; a run of drop-off
    readings ends at two other readings in a row (one alone is noise too). The edge hiding the
    lower floor lies between that pixel's ray and the ray of the reading under it: on a floor
    reading, the edge is where that ray meets the floor, at most a pixel's floor footprint before
    the true edge and never beyond it; on an obstacle (a reading above the floor), the edge is
    hidden behind it and the obstacle's point is reported. Without a reading under it in the
    window, the search goes on down the used rows (their lowest row's floor point if none). The
    point's range, at least ``range_min``, goes into the bins of that pixel's footprint; an edge
    a column already reported (``done``: its floor row) is not reported again. ``scr``: (2, bs)
    int64 scratch.
    """
    c0 = bi * bs
    r_low = height - 1 - bj * bs
    r_top = height - (top + 1) * bs
    cand = scr[0]  # lowest drop-off row of the current run, -1 none
    base = scr[1]  # the last other reading's row under it, -1 none
    r = r_low
    # the rows under the first drop-off reading of any column, branch-free (vectorised: one
    # compare a pixel; d > NEVER never holds): most of the rows searched
    while r >= r_top:
        j = r - row0
        hit = False
        for c in range(c0, c0 + bs):
            hit |= image[r, c] > band[0, j, c]
        if hit:
            break
        r -= 1
    r_hit = r
    for i in range(bs):  # then each column on its own: most find their edge within a few rows
        c = c0 + i
        cand[i] = -1
        last = UNSEEN  # the last other reading's row (not looked for under r_hit yet)
        n_d = 0  # drop-off readings since cand
        n_o = 0  # other readings in a row since the last drop-off
        for r in range(r_hit, r_top - 1, -1):  # upwards: the nearest edge first
            d = image[r, c]
            t = band[0, r - row0, c]
            if d == 0 or t == NEVER:
                continue
            if d > t:  # a drop-off reading
                if cand[i] < 0:
                    cand[i] = r
                    if last == UNSEEN:  # rows under r_hit hold no drop-off: the first reading
                        last = -1
                        for q in range(r + 1, r_low + 1):
                            if image[q, c] != 0 and band[0, q - row0, c] != NEVER:
                                last = q
                                break
                    base[i] = last
                    n_d = 0
                n_d += 1
                n_o = 0
                if n_d == RUN:
                    break
            else:  # floor or obstacle; one alone inside a run of drop-offs is noise
                last = r
                if cand[i] >= 0:
                    n_o += 1
                    if n_o == RUN:
                        cand[i] = -1
    for i in range(bs):
        if cand[i] < 0:
            continue
        c = c0 + i
        edge[c] = cand[i]
        r = base[i]
        if r < 0:  # no other reading under it in the window: look further down
            r = r_low + 1
            while r < height:
                d = image[r, c]
                if d != 0 and band[0, r - row0, c] != NEVER and d <= band[0, r - row0, c]:
                    break
                r += 1
            r = min(r, height - 1)
        if r == done[c]:
            continue
        done[c] = r
        j = r - row0
        s = np.float32(1.0)
        d = image[r, c]
        if d != 0 and d < band[1, j, c]:  # an obstacle hides the edge
            s = np.float32(d) * np.float32(0.001) / xyt[j, c, 2]
        x = s * xyt[j, c, 0]
        y = s * xyt[j, c, 1]
        if not (np.isfinite(x) and np.isfinite(y)):
            continue
        v = max(np.float32(np.sqrt(x * x + y * y)), range_min)
        for b in range(bins[0, j, c], bins[1, j, c] + 1):
            out[b] = min(out[b], v)
        pts[k, 0] = x
        pts[k, 1] = y
        k += 1
    return k
