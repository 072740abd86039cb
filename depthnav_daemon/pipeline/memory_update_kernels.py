"""Compiled update of the obstacle memory (``memory.update``): one call per sensor view.

``view_extent`` says per scan bin which ranges the view saw free (between the near and far floor
ranges of its image, up to what it hit), ``clear_view`` frees the remembered points inside that,
``fill_view`` marks the cells inside it known free, ``shadow_view`` (memory_shadow_kernels) the
cells where it saw more than it keeps, ``mark_view`` marks what the view hit; ``update_view`` runs
them. The grid's layout is ``memory_kernels``'.
"""

from __future__ import annotations

import math

import numpy as np

from depthnav_daemon.pipeline._jit import helper, kernel
from depthnav_daemon.pipeline.memory_kernels import (
    CLIFF,
    FREE,
    KNOWN_FREE,
    OBSTACLE,
    fast_atan2,
    mark_segment,
)
from depthnav_daemon.pipeline.memory_shadow_kernels import SHADOW_FROM_CELLS, shadow_view

# spacing of the fill's samples, in cells: samples at most s apart radially and across put one into
# every disc of diameter s * sqrt(2), so no cell wholly inside the seen region is missed at
# s <= 1 / sqrt(2)
FILL_STEP_CELLS = 0.7


@helper
def view_extent(
    ranges,
    free_nan,
    cliff,
    cfree_nan,
    near,
    far,
    cnear,
    cfar,
    rmax,
    crmin,
    crmax,
    margin,
    k_spacing,
    h2,
    rows_scan,
    rows_cliff,
    lo,
    hi,
):
    """Per scan bin, the ranges the view saw free floor: [lo, hi] (empty where hi < lo).

    Args:
        ranges: (M,) float32 the level-frame scan (REP 117, with the coverage rule: NaN where the
            view does not reach range_max and found nothing); bin i at a0 + i * inc.
        free_nan: (M,) uint8, 1 where a NaN bin is only the coverage rule's (its pixels saw floor
            and no obstacle out to ``far``), or an empty array (none known).
        cliff: (M,) float32 the cliff scan in the same bins, or an empty array (no cliff stage).
        cfree_nan: (M,) uint8 as ``free_nan`` for the cliff scan (its pixels read floor and no
            drop-off out to ``cfar``), or an empty array.
        near, far: (M,) float32 the floor ranges the scan's rows see per bin (coverage.py).
        cnear, cfar: (M,) float32 the same for the cliff stage's rows (unused without a cliff).
        rmax: the scan's range_max; crmin, crmax: the cliff stage's range_min and range_max.
        margin, k_spacing, h2, rows_scan, rows_cliff: the floor is known free only up to the last
            floor row the stage read, which lies up to ``rows`` image rows short of what it
            found (``rows_scan``: the scan's row stride; ``rows_cliff``: a block and a sample
            stride, as a block straddling the edge may not reach the threshold); one row spans
            (h^2 + d^2) / (h f_y) metres of floor at range d (k_spacing = 1 / (h f_y)), and the
            margin is never below ``margin`` metres.
        lo, hi: (M,) float64, overwritten, metres; hi = -1 where the bin saw nothing free.
    """
    m = ranges.shape[0]
    has_cliff = cliff.shape[0] == m
    has_free = free_nan.shape[0] == m
    has_cfree = cfree_nan.shape[0] == m
    inf = np.inf
    for i in range(m):
        v = ranges[i]
        a = np.float64(near[i])
        if np.isnan(v):  # no reading, or the coverage rule's (free out to far)
            lim = min(np.float64(far[i]), rmax) if has_free and free_nan[i] != 0 else -1.0
        elif v == -inf:  # too close: nothing seen free
            lim = -1.0
        elif v == inf:  # clear: out to far
            lim = min(np.float64(far[i]), rmax)
        else:
            lim = min(np.float64(far[i]), np.float64(v))
        # -1: nothing seen free on this bin
        d = lim - max(margin, rows_scan * k_spacing * (h2 + lim * lim)) if lim > 0.0 else -1.0
        if has_cliff:
            c = cliff[i]
            a = max(a, np.float64(cnear[i]), crmin)
            free = c == inf or (np.isnan(c) and has_cfree and cfree_nan[i] != 0)
            if not free and not np.isfinite(c):  # NaN: the floor was not read; -inf: too close
                d = -1.0
            else:
                cl = min(np.float64(cfar[i]), crmax) if free else np.float64(c)
                d = min(d, cl - max(margin, rows_cliff * k_spacing * (h2 + cl * cl)))
        lo[i] = a
        hi[i] = d


@helper
def sector_box(t0, t1, r):
    """(x0, x1, y0, y1): the bounding box of the circular sector of radius ``r`` between headings
    t0 <= t1 (radians) about the origin: its apex, arc ends and the arc's axis crossings."""
    x0 = min(0.0, r * math.cos(t0), r * math.cos(t1))
    x1 = max(0.0, r * math.cos(t0), r * math.cos(t1))
    y0 = min(0.0, r * math.sin(t0), r * math.sin(t1))
    y1 = max(0.0, r * math.sin(t0), r * math.sin(t1))
    for q in range(4):  # headings 0, 90, 180, 270 deg
        phi = q * 0.5 * np.pi
        if (phi - t0) % (2.0 * np.pi) <= t1 - t0:
            if q == 0:
                x1 = r
            elif q == 1:
                y1 = r
            elif q == 2:  # noqa: PLR2004
                x0 = -r
            else:
                y0 = -r
    return x0, x1, y0, y1


@helper
def clear_view(grid, offx, offy, wx0, wy0, cell, sx, sy, syaw, a0, inc, lo, hi):
    """Free the remembered points the view saw free: a point at range r in bin i with
    lo[i] <= r < hi[i] (the sensor's foot at (sx, sy), heading syaw, odometry frame). The cells
    stay unknown until ``fill_view`` marks them. Returns how many."""
    n = grid.shape[0]
    m = lo.shape[0]
    c0 = np.cos(syaw)
    s0 = np.sin(syaw)
    lo_b = a0 - 0.5 * inc
    hi_b = a0 + (m - 0.5) * inc
    # the view's wedge as two half-planes (no arctangent for the points outside it), when it is
    # narrower than a half turn
    narrow = hi_b - lo_b < np.pi
    cl, sl = np.cos(lo_b), np.sin(lo_b)
    ch, sh = np.cos(hi_b), np.sin(hi_b)
    rmax = 0.0
    for i in range(m):
        rmax = max(rmax, hi[i])
    r2max = rmax * rmax
    cleared = 0
    if rmax <= 0.0:
        return 0
    # only the rows and words of the wedge's bounding box (a view covers a fraction of the grid)
    x0, x1, y0, y1 = sector_box(syaw + lo_b, syaw + hi_b, rmax)
    gx_lo = max(np.int64(math.floor((sx + x0) / cell)), wx0)
    gx_hi = min(np.int64(math.floor((sx + x1) / cell)), wx0 + n - 1)
    gy_lo = max(np.int64(math.floor((sy + y0) / cell)), wy0)
    gy_hi = min(np.int64(math.floor((sy + y1) / cell)), wy0 + n - 1)
    if gx_lo > gx_hi or gy_lo > gy_hi:
        return 0
    nw = n // 8
    bx = wx0 % n
    by = wy0 % n
    # the box's columns as one or two runs of words of each row (the grid wraps around)
    iy_lo = by + (gy_lo - wy0)
    iy_lo = iy_lo - n if iy_lo >= n else iy_lo
    iy_hi = by + (gy_hi - wy0)
    iy_hi = iy_hi - n if iy_hi >= n else iy_hi
    runs = 1 if iy_lo <= iy_hi else 2
    words = grid.reshape(-1).view(np.uint64)
    for gx in range(gx_lo, gx_hi + 1):
        ix = bx + (gx - wx0)
        ix = ix - n if ix >= n else ix
        px0 = gx * cell - sx
        for run in range(runs):
            w0 = (iy_lo if run == 0 else 0) // 8
            w1 = (iy_hi if runs == 1 or run == 1 else n - 1) // 8
            for wi in range(w0, w1 + 1):
                if words[ix * nw + wi] == 0:
                    continue
                for iy in range(wi * 8, wi * 8 + 8):
                    if grid[ix, iy] == FREE:
                        continue
                    gy = wy0 + (iy - by if iy >= by else iy - by + n)
                    px = px0 + offx[ix, iy]
                    py = gy * cell + offy[ix, iy] - sy
                    along = c0 * px + s0 * py
                    across = -s0 * px + c0 * py
                    r2 = along * along + across * across
                    if r2 >= r2max:
                        continue
                    if narrow and (
                        cl * across - sl * along < 0.0 or ch * across - sh * along > 0.0
                    ):
                        continue
                    b = fast_atan2(across, along)
                    if b < lo_b or b > hi_b:
                        continue
                    i = min(max(np.int64(np.floor((b - a0) / inc + 0.5)), 0), m - 1)
                    r = np.sqrt(r2)
                    if lo[i] <= r < hi[i]:
                        grid[ix, iy] = FREE
                        cleared += 1
    return cleared


@helper
def fill_view(grid, known, free_t, wx0, wy0, cell, sx, sy, syaw, a0, inc, lo, hi, t_rel):
    """Mark the cells the view saw free as known free at ``t_rel`` (occupied cells keep their
    state). Returns the samples written.

    Samples lie on spokes from the sensor's foot (sx, sy, heading syaw), FILL_STEP_CELLS apart
    along each spoke and between neighbouring spokes: the ranges are cut into bands 1.5 times
    wider each (narrower bands cost more spokes than they save samples), each band with its own
    spokes spread over the scan's bearings at most a step apart at the band's outer edge.

    A sample marks the whole cell it falls in, and that cell lies within a cell's diagonal of it:
    so a spoke walks only where the disc of that radius about each sample lies inside the seen
    region (every bin the disc touches saw free floor from the disc's near to its far side, and
    the disc stays within the view's bearings). A cell straddling the seen region's edge stays
    unknown: marked free, it let the memory scan read +inf through the unseen part (a hole's
    interior in the dead zone, behind a cell whose far part was seen).
    """
    n = grid.shape[0]
    bx = wx0 % n  # once: an integer division costs more than a cell
    by = wy0 % n
    m = lo.shape[0]
    r0 = np.inf
    r1 = 0.0
    for i in range(m):
        if hi[i] >= lo[i]:
            r0 = min(r0, lo[i])
            r1 = max(r1, hi[i])
    if not r1 >= r0:
        return 0
    step = FILL_STEP_CELLS * cell
    diag = math.sqrt(2.0) * cell  # a sample's cell lies within this of it
    span = m * inc
    th0 = syaw + a0 - 0.5 * inc  # the first bin's lower edge, odometry frame
    c_start = math.cos(th0)
    s_start = math.sin(th0)
    inv = 1.0 / cell
    written = 0
    band_lo = r0
    while True:
        band_hi = min(r1, max(band_lo * 1.5, band_lo + step))
        k_n = np.int64(math.ceil(span * band_hi / step)) + 1
        dth = span / (k_n - 1)
        q = dth / inc  # bins per spoke: spoke k lies in bin floor(k q)
        cd = math.cos(dth)
        sd = math.sin(dth)
        c = c_start
        s = s_start
        # the bearings a sample's disc spans either side of its spoke, in bins
        half_w = math.asin(diag / band_lo) / inc if band_lo > diag else np.inf
        for k in range(k_n):
            a = band_lo
            b = band_hi
            t = k * q  # the spoke's bearing from the first bin's lower edge, in bins
            j0 = np.int64(math.floor(t - half_w)) if half_w < m else np.int64(-1)
            j1 = np.int64(math.floor(t + half_w)) if half_w < m else m
            if j0 < 0 or j1 >= m:
                b = -1.0  # the disc reaches past the view's side: nothing seen there
            else:
                for j in range(j0, j1 + 1):
                    a = max(a, lo[j] + diag)
                    b = min(b, hi[j] - diag)
            if a <= b:
                written += mark_segment(
                    grid, known, free_t, wx0, wy0, bx, by, sx, sy, c, s, a, b, step, inv, t_rel,
                    KNOWN_FREE,
                )  # fmt: skip
            c, s = c * cd - s * sd, s * cd + c * sd
        if band_hi >= r1:
            return written
        band_lo = band_hi


@helper
def mark_view(
    grid, stamp, offx, offy, known, wx0, wy0, cell, sx, sy, syaw, ranges, cliff, a0, inc, rmin,
    crmin, t_rel,
):  # fmt: skip
    """Mark what the view hit: an OBSTACLE cell at each finite scan range, then a CLIFF cell at
    each finite cliff range (the edge), and at ``rmin`` / ``crmin`` on a bin that reads -inf (too
    close: it is there or nearer). Marked cells are not known free. Returns how many.

    One flat loop over both scans, the point's marking written out in it: a helper call per
    point (five arrays passed field by field) cost more than the marking."""
    n = grid.shape[0]
    m = ranges.shape[0]
    total = 2 * m if cliff.shape[0] == m else m
    bx = wx0 % n  # once: an integer division costs more than a point
    by = wy0 % n
    marked = 0
    ci = math.cos(inc)
    si = math.sin(inc)
    cb = sb = 0.0
    last_ix = last_iy = last_code = -1
    last_d2 = 0.0
    for k in range(total):
        if k % m == 0:  # each scan's first bin; then bearings by rotation (no cos/sin per bin)
            cb = math.cos(syaw + a0)
            sb = math.sin(syaw + a0)
        else:
            cb, sb = cb * ci - sb * si, sb * ci + cb * si
        obstacle = k < m
        v = np.float64(ranges[k] if obstacle else cliff[k - m])
        if v == -np.inf:
            v = rmin if obstacle else crmin
        elif not (v < np.inf):  # NaN or +inf: nothing hit
            continue
        code = OBSTACLE if obstacle else CLIFF
        x = sx + v * cb
        y = sy + v * sb
        # window-relative: no integer division per point
        dx = np.int64(math.floor(x / cell)) - wx0
        dy = np.int64(math.floor(y / cell)) - wy0
        if not (0 <= dx < n and 0 <= dy < n):
            continue
        gx = wx0 + dx
        gy = wy0 + dy
        ix = bx + dx
        ix = ix - n if ix >= n else ix
        iy = by + dy
        iy = iy - n if iy >= n else iy
        d2 = (x - sx) * (x - sx) + (y - sy) * (y - sy)
        if ix == last_ix and iy == last_iy and code == last_code and d2 >= last_d2:
            continue  # the cell the previous bin marked, with a nearer point (a cell spans bins)
        g = grid[ix, iy]
        known[ix, iy] = 0
        if g == code:
            # the same kind again: a point this view did not clear is still true, so the cell
            # keeps the nearer point (the one a robot driving up to it meets first)
            stamp[ix, iy] = t_rel
            qx = gx * cell + offx[ix, iy] - sx
            qy = gy * cell + offy[ix, iy] - sy
            last_ix, last_iy, last_code, last_d2 = ix, iy, code, min(d2, qx * qx + qy * qy)
            if d2 >= qx * qx + qy * qy:
                continue
        elif g == OBSTACLE and not obstacle and stamp[ix, iy] == t_rel:
            continue  # an obstacle seen in this frame is not also a drop-off
        last_ix, last_iy, last_code, last_d2 = ix, iy, code, d2
        grid[ix, iy] = code
        stamp[ix, iy] = t_rel
        offx[ix, iy] = x - gx * cell
        offy[ix, iy] = y - gy * cell
        marked += 1
    return marked


@kernel
def update_view(
    grid,
    stamp,
    offx,
    offy,
    known,
    free_t,
    wx0,
    wy0,
    cell,
    sx,
    sy,
    syaw,
    ranges,
    free_nan,
    cliff,
    cfree_nan,
    near,
    far,
    cnear,
    cfar,
    a0,
    inc,
    rmin,
    rmax,
    crmin,
    crmax,
    margin,
    k_spacing,
    h2,
    rows_scan,
    rows_cliff,
    t_rel,
    seen_far,
):
    """Fold one sensor view into the memory (one call: a kernel call costs ~2 us of argument
    checks): ``view_extent``, then ``clear_view``, ``fill_view`` (free, then the shadow) and
    ``mark_view`` (their docstrings say what each argument is). ``seen_far``: (M,) float32 per
    bin the farthest obstacle the view saw (LaserScan.far; -inf: none), or an empty array: the
    shadow is [what the bin hit, seen_far] (what it saw there beyond the point it reports, which
    the memory does not keep). Returns (cleared, marked, samples written)."""
    m = ranges.shape[0]
    lo = np.empty(m, np.float64)
    hi = np.empty(m, np.float64)
    view_extent(
        ranges, free_nan, cliff, cfree_nan, near, far, cnear, cfar, rmax, crmin, crmax, margin,
        k_spacing, h2, rows_scan, rows_cliff, lo, hi,
    )  # fmt: skip
    cleared = clear_view(grid, offx, offy, wx0, wy0, cell, sx, sy, syaw, a0, inc, lo, hi)
    written = fill_view(grid, known, free_t, wx0, wy0, cell, sx, sy, syaw, a0, inc, lo, hi, t_rel)
    if seen_far.shape[0] == m:
        for i in range(m):
            v = np.float64(ranges[i])
            lo[i] = (rmin if v == -np.inf else v) + SHADOW_FROM_CELLS * cell
            hi[i] = min(np.float64(seen_far[i]), rmax) if v < np.inf else -1.0  # NaN: -1
        written += shadow_view(
            grid, known, free_t, wx0, wy0, cell, sx, sy, syaw, a0, inc, lo, hi, t_rel
        )
    marked = mark_view(
        grid, stamp, offx, offy, known, wx0, wy0, cell, sx, sy, syaw, ranges, cliff, a0, inc,
        rmin, crmin, t_rel,
    )  # fmt: skip
    return cleared, marked, written
