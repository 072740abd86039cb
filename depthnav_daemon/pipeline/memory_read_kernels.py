"""Compiled read-back of the obstacle memory (``memory.read_scan``): the 360 deg memory scan.

Per bin: the nearest remembered point covering it (within range_max), NaN if a SHADOW cell lies in
front of it (``hole``: what a view saw there, the memory did not keep); else +inf if every cell
the bin's wedge touches between the blind radius and range_max is known free; else NaN. The
grid layout and the two arrays (``grid``, ``known``) are ``memory_kernels``'.

Which bins a cell touches is judged with the cell's circumscribed disc (conservative: a bin next
to an unknown cell may read NaN although the cell only grazes it). The known-free array is read
in blocks of 8 x 8 cells, 8 bytes a row: a block all known free costs 8 loads, a block all
unknown one bearing span; only blocks with both (the edges of what was seen) are judged cell by
cell. So the read-back costs in proportion to the blocks within range_max, not to 360 rays.
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
    SHADOW,
    fast_atan2,
    row_empty,
)

BLOCK = 8  # cells per block side (the grid side is a multiple of it)
_ONES = 0x0101010101010101  # eight known-free cells
_HALF_DIAGONAL = 0.7072  # a cell's circumscribed radius, in cells (sqrt(2) / 2, rounded up)
_UNJUDGED = -1e9  # lim of a bin no cell can decide
_UNKNOWN = -2e9  # lim of a bin decided unknown (NaN)
_SERIES_UP_TO = 0.5  # _asin_up's x + x^3 / 5 bounds asin(x) from above up to here


@helper
def _asin_up(x):
    """An upper bound of asin(x) for 0 <= x < 1, within 0.2 % (x + x^3 / 5 below 0.5)."""
    if x < _SERIES_UP_TO:
        return x + 0.2 * x * x * x
    return math.asin(min(x, 1.0)) * 1.000001


@helper
def _wrap(j, nb):
    """j mod nb for -nb <= j < 2 nb, without an integer division (it costs more than a bin)."""
    if j < 0:
        return j + nb
    return j - nb if j >= nb else j


@helper
def _judge(lim, out, fx, fy, h, lo, hi, inc, inf_only):
    """Judge the bins a disc of radius ``h`` at (fx, fy) (base frame, metres) touches, for cells
    whose centres lie between ``lo`` and ``hi`` metres from the robot; bin j is centred on
    -pi + j inc. A bin with ``hi`` < lim[j] is decided unknown (lim[j] = _UNKNOWN); ``inf_only``:
    only bins without a remembered point (``out`` = +inf) are judged. Returns (how many were
    decided, how many others have ``lo`` < lim[j]: a cell of the disc may still decide them)."""
    nb = lim.shape[0]
    r2 = fx * fx + fy * fy
    j0 = np.int64(0)
    j1 = np.int64(nb - 1)
    if r2 > h * h:  # else the disc holds the origin: every bearing
        r = math.sqrt(r2)
        b = fast_atan2(fy, fx)
        hw = _asin_up(h / r) + 2e-5  # + fast_atan2's error
        j0 = np.int64(math.floor((b - hw + np.pi) / inc + 0.5))
        j1 = min(np.int64(math.floor((b + hw + np.pi) / inc + 0.5)), j0 + nb - 1)
    newly = 0
    pending = 0
    jj = _wrap(j0, nb)
    for _ in range(j1 - j0 + 1):
        if not inf_only or out[jj] == np.inf:
            if hi < lim[jj]:
                lim[jj] = _UNKNOWN
                newly += 1
            elif lo < lim[jj]:
                pending += 1
        jj = jj + 1 if jj + 1 < nb else 0
    return newly, pending


@kernel
def memory_read(
    grid, offx, offy, known, wx0, wy0, cell, rx, ry, ryaw, blind, rmax, hole, out, hidden, counts
):
    """The memory scan around the robot at (rx, ry, ryaw) (odometry frame).

    Each remembered point covers the bearings of a disc of half a cell about it (so a row of
    cells reads as a wall, without gaps between its points) at the point's own range.

    Args:
        grid, offx, offy, known, wx0, wy0, cell: the memory (memory_kernels).
        rx, ry, ryaw: the robot's pose in the odometry frame.
        blind, rmax: the cells judged are those whose circumscribed disc reaches beyond
            ``blind`` from the robot (no sensor sees under it) and within ``rmax``
            (the scan's range_max: +inf claims known free all the way to it); points farther
            than rmax are not reported.
        hole: a bin's remembered point is read NaN if a SHADOW cell it touches lies more than
            this much nearer (centre to point), metres (0: never); cells never seen are not
            judged before a point.
        out: (N,) float32, overwritten: bin j centred on -pi + j * 2 pi / N (base frame).
        hidden: (N,) uint8, overwritten: 1 where a remembered point was read NaN (``hole``).
        counts: (3,) int64, overwritten: cells per state (FREE unused, OBSTACLE, CLIFF).
    """
    n = grid.shape[0]
    nb = out.shape[0]
    inc = 2.0 * np.pi / nb
    for j in range(nb):
        out[j] = np.inf
    counts[:] = 0
    c0 = np.cos(ryaw)
    s0 = np.sin(ryaw)
    half = 0.5 * cell
    inv_inc = 1.0 / inc
    r2max = rmax * rmax
    n_obstacle = 0
    n_cliff = 0
    nw = n // 8
    bxn = wx0 % n  # once: an integer division costs more than a cell
    byn = wy0 % n
    words = grid.reshape(-1).view(np.uint64)
    for ix in range(n):
        if row_empty(words, ix, nw):
            continue
        # the row's global coordinate from its index and the window
        gx = wx0 + (ix - bxn if ix >= bxn else ix - bxn + n)
        px0 = gx * cell - rx
        for wi in range(nw):
            if words[ix * nw + wi] == 0:
                continue
            for iy in range(wi * 8, wi * 8 + 8):
                g = grid[ix, iy]
                if g == FREE:
                    continue
                if g == OBSTACLE:
                    n_obstacle += 1
                else:
                    n_cliff += 1
                gy = wy0 + (iy - byn if iy >= byn else iy - byn + n)
                px = px0 + offx[ix, iy]
                py = gy * cell + offy[ix, iy] - ry
                r2 = px * px + py * py
                if r2 > r2max:
                    continue
                r = math.sqrt(r2)
                fx = c0 * px + s0 * py
                fy = -s0 * px + c0 * py
                b = fast_atan2(fy, fx) + np.pi
                hw = min(half / r, np.pi)  # >= atan(half / r): never narrower
                j0 = np.int64(math.floor((b - hw) * inv_inc + 0.5))
                j1 = min(np.int64(math.floor((b + hw) * inv_inc + 0.5)), j0 + nb - 1)
                v = np.float32(r)
                jj = _wrap(j0, nb)
                for _ in range(j1 - j0 + 1):
                    out[jj] = min(out[jj], v)
                    jj = jj + 1 if jj + 1 < nb else 0
    counts[OBSTACLE] = n_obstacle
    counts[CLIFF] = n_cliff
    # then the unknown cells: a bin is +inf only if every judged cell it touches is known free,
    # and a remembered point only if no unknown cell it touches lies ``hole`` or more nearer;
    # lim[j]: the cells whose centre lies nearer than it decide bin j
    hd = _HALF_DIAGONAL * cell
    outer = rmax + hd  # a cell is judged while its centre lies within this
    inner = blind - hd  # and beyond this
    lim = np.empty(nb, np.float64)
    undecided = 0
    for j in range(nb):
        if out[j] < np.inf:
            lim[j] = out[j] - hole if hole > 0.0 else _UNJUDGED
        elif blind < rmax:
            lim[j] = outer
        else:
            lim[j] = _UNKNOWN  # nothing to judge: no bin is known free
        if lim[j] > inner:
            undecided += 1
    hdb = BLOCK * hd  # a block's circumscribed radius
    spread = (BLOCK - 1) * hd  # farthest cell centre from the block's centre
    kw = known.reshape(-1).view(np.uint64)
    ones = np.uint64(_ONES)
    reach = rmax + hdb
    bx0 = np.int64(math.floor((rx - reach) / cell)) // BLOCK
    bx1 = np.int64(math.floor((rx + reach) / cell)) // BLOCK
    by0 = np.int64(math.floor((ry - reach) / cell)) // BLOCK
    by1 = np.int64(math.floor((ry + reach) / cell)) // BLOCK
    # first the blocks all known or all unknown (cheap); the others after, cell by cell, each
    # skipped if the bins its disc touches are decided by then (a wall's blocks: behind it)
    mixed = np.empty((bx1 - bx0 + 1) * (by1 - by0 + 1), np.int64)
    n_mixed = 0
    for bx in range(bx0, bx1 + 1):
        if undecided == 0:
            break
        gx0 = bx * BLOCK
        x_in = wx0 <= gx0 and gx0 + BLOCK <= wx0 + n
        x_out = gx0 + BLOCK <= wx0 or gx0 >= wx0 + n
        ix0 = gx0 - wx0 + bxn  # the block's first row index, when inside the window
        ix0 = ix0 - n if ix0 >= n else ix0
        for by in range(by0, by1 + 1):
            if undecided == 0:
                break
            gy0 = by * BLOCK
            px = (gx0 + 0.5 * BLOCK) * cell - rx
            py = (gy0 + 0.5 * BLOCK) * cell - ry
            rb = math.sqrt(px * px + py * py)
            if rb - spread > outer or rb + spread < inner:
                continue  # no cell of it judged
            inside = x_in and wy0 <= gy0 and gy0 + BLOCK <= wy0 + n
            unknown = x_out or gy0 + BLOCK <= wy0 or gy0 >= wy0 + n  # wholly outside the window
            if inside:
                iy0 = gy0 - wy0 + byn
                iy0 = iy0 - n if iy0 >= n else iy0
                wi = iy0 // BLOCK
                all_known = True
                unknown = True
                for a in range(BLOCK):
                    wd = kw[(ix0 + a) * nw + wi]
                    all_known = all_known and wd == ones
                    unknown = unknown and wd == 0 and words[(ix0 + a) * nw + wi] == 0
                if all_known:
                    continue
            # every cell unknown and never in a view's shadow: the block's disc holds theirs and
            # only bins without a remembered point are judged; those it decides whole are decided
            # here, the others (a cell nearer than lim, another not) cell by cell
            fx = c0 * px + s0 * py
            fy = -s0 * px + c0 * py
            hi = rb + spread if unknown and rb - spread >= inner else np.inf  # inf: none
            k, pending = _judge(lim, out, fx, fy, hdb, rb - spread, hi, inc, unknown)
            undecided -= k
            if pending > 0:
                mixed[n_mixed] = (bx - bx0) * (by1 - by0 + 1) + (by - by0)
                n_mixed += 1
    for k in range(n_mixed):
        if undecided == 0:
            break
        bx = bx0 + mixed[k] // (by1 - by0 + 1)
        by = by0 + mixed[k] % (by1 - by0 + 1)
        gx0 = bx * BLOCK
        gy0 = by * BLOCK
        px = (gx0 + 0.5 * BLOCK) * cell - rx
        py = (gy0 + 0.5 * BLOCK) * cell - ry
        rb = math.sqrt(px * px + py * py)
        fx = c0 * px + s0 * py
        fy = -s0 * px + c0 * py
        if _judge(lim, out, fx, fy, hdb, rb - spread, np.inf, inc, False)[1] == 0:
            continue  # every bin it could touch is decided by now
        for a in range(BLOCK):
            gx = gx0 + a
            qx = (gx + 0.5) * cell - rx
            x_in = wx0 <= gx < wx0 + n
            ix = gx - wx0 + bxn
            ix = ix - n if ix >= n else ix
            for b in range(BLOCK):
                gy = gy0 + b
                qy = (gy + 0.5) * cell - ry
                rc = math.sqrt(qx * qx + qy * qy)
                if rc < inner or rc > outer:
                    continue
                inf_only = True  # outside the window: unknown, never in a shadow
                if x_in and wy0 <= gy < wy0 + n:
                    iy = gy - wy0 + byn
                    iy = iy - n if iy >= n else iy
                    kc = known[ix, iy]
                    if kc == KNOWN_FREE:
                        continue
                    # a remembered point (its own range is read above) and a cell never in a
                    # view's shadow judge only the bins without a remembered point
                    inf_only = kc != SHADOW or grid[ix, iy] != FREE
                fx = c0 * qx + s0 * qy
                fy = -s0 * qx + c0 * qy
                undecided -= _judge(lim, out, fx, fy, hd, rc, rc, inc, inf_only)[0]
    for j in range(nb):
        hidden[j] = 0
        if lim[j] == _UNKNOWN:
            hidden[j] = out[j] < np.inf
            out[j] = np.nan
