"""The obstacle memory's grid (``memory.py``): its layout, cell codes and compiled housekeeping
(moving the window, forgetting old cells). The per-view update is ``memory_update_kernels.py``,
the read-back ``memory_read_kernels.py``.

The grid is toroidal: global cell (gx, gy) = floor(odometry x / cell, y / cell) lives at index
(gx mod n, gy mod n), so moving the window is forgetting the rows and columns that leave it (no
copy). Each marked cell also keeps where in the cell its last point was (sub-cell offsets), so
ranges read back from the memory are not rounded to the cell.

Two arrays say what is known of a cell: ``grid`` (FREE / OBSTACLE / CLIFF; mostly FREE, so the
passes over what is remembered read it eight bytes at a time, row by row (the side is a multiple
of 8: no word straddles two rows, and no integer division per cell), and cost in proportion to
what is remembered) and
``known`` (KNOWN_FREE = seen free; SHADOW = not seen free, but inside a view behind what it hit, so
something it did not report may stand there; 0 = unknown, or occupied). A cell is known free iff
known = KNOWN_FREE, which implies grid = FREE; a cell with known = 0 and grid = FREE has never been
seen, left the window or was forgotten.
"""

from __future__ import annotations

import math

import numpy as np

from depthnav_daemon.pipeline._jit import helper, inlined, kernel

FREE = 0
OBSTACLE = 1
CLIFF = 2
KNOWN_FREE = 1  # known: seen free
SHADOW = 2  # known: not seen free, but inside a view behind what it hit (a surface may hide there)

_PI = np.pi
_HALF_PI = np.pi / 2.0


@kernel
def fast_atan2(y, x):
    """atan2(y, x) within 1e-5 rad (a minimax polynomial on [0, 1] after octant reduction),
    written in selects rather than branches, so that a loop calling it vectorises
    (placement_pixel_kernels); atan2(0, 0) = 0."""
    ax = abs(x)
    ay = abs(y)
    hi = max(ax, ay)
    t = min(ax, ay) / (hi if hi > 0.0 else 1.0)
    t2 = t * t
    a = t * (
        0.99997726
        + t2
        * (
            -0.33262347
            + t2 * (0.19354346 + t2 * (-0.11643287 + t2 * (0.05265332 - 0.0117212 * t2)))
        )
    )
    a = _HALF_PI - a if ay > ax else a
    a = _PI - a if x < 0.0 else a
    return -a if y < 0.0 else a


@helper
def row_empty(words, ix, nw):
    """Whether row ``ix`` of a grid read as (n * n / 8,) uint64 words holds only FREE cells (one
    pass without a branch, which the compiler vectorises; most rows are empty)."""
    acc = np.uint64(0)
    for wi in range(ix * nw, ix * nw + nw):
        acc |= words[wi]
    return acc == 0


@inlined
def mark_segment(
    grid, known, free_t, wx0, wy0, bx, by, sx, sy, c, s, a, b, step, inv, t_rel, value
):
    """Mark the cells along the segment from range ``a`` to ``b`` (metres) on heading (c, s) from
    (sx, sy), samples at most ``step`` apart: ``value`` KNOWN_FREE on every FREE cell, SHADOW on
    the FREE cells never seen (known 0), stamped ``t_rel``. (bx, by): (wx0, wy0) mod n, which the
    caller works out once (an integer division costs more than a cell). Returns the cells
    written."""
    n = grid.shape[0]
    count = np.int64(math.ceil((b - a) / step)) + 1
    dr = (b - a) / (count - 1) if count > 1 else 0.0
    # in cells, relative to the window's corner
    u = (sx + a * c) * inv - wx0
    v = (sy + a * s) * inv - wy0
    du = dr * c * inv
    dv = dr * s * inv
    written = 0
    last_x = last_y = -1
    for j in range(count):
        dx = np.int64(math.floor(u + j * du))
        dy = np.int64(math.floor(v + j * dv))
        if dx == last_x and dy == last_y:
            continue  # the previous sample's cell (samples are under a cell apart)
        last_x = dx
        last_y = dy
        if 0 <= dx < n and 0 <= dy < n:
            ix = bx + dx
            ix = ix - n if ix >= n else ix
            iy = by + dy
            iy = iy - n if iy >= n else iy
            if grid[ix, iy] == FREE and (value == KNOWN_FREE or known[ix, iy] == 0):
                known[ix, iy] = value
                free_t[ix, iy] = t_rel
                written += 1
    return written


@kernel
def clear_lines(grid, known, wx0, wy0, nx0, ny0):
    """Move the window from origin (wx0, wy0) to (nx0, ny0) (global cells): the columns and rows
    that leave it become unknown (they are the indices the entering ones reuse)."""
    n = grid.shape[0]
    dx = nx0 - wx0
    dy = ny0 - wy0
    if abs(dx) >= n or abs(dy) >= n:
        grid[:, :] = FREE
        known[:, :] = 0
        return
    lo, hi = (wx0, nx0) if dx > 0 else (nx0 + n, wx0 + n)
    for gx in range(lo, hi):
        grid[gx % n, :] = FREE
        known[gx % n, :] = 0
    lo, hi = (wy0, ny0) if dy > 0 else (ny0 + n, wy0 + n)
    for gy in range(lo, hi):
        grid[:, gy % n] = FREE
        known[:, gy % n] = 0


@kernel
def expire(grid, stamp, oldest):
    """Forget occupied cells last marked before ``oldest`` (seconds since the epoch): they become
    unknown. Returns how many."""
    n = grid.shape[0]
    nw = n // 8
    gone = 0
    words = grid.reshape(-1).view(np.uint64)
    for ix in range(n):
        if row_empty(words, ix, nw):
            continue
        for wi in range(nw):
            if words[ix * nw + wi] == 0:
                continue
            for iy in range(wi * 8, wi * 8 + 8):
                if grid[ix, iy] != FREE and stamp[ix, iy] < oldest:
                    grid[ix, iy] = FREE
                    gone += 1
    return gone


@kernel
def expire_free(known, free_t, oldest):
    """Forget free and SHADOW cells last seen before ``oldest``: they become unknown. Returns how
    many."""
    k = known.reshape(-1)
    t = free_t.reshape(-1)
    gone = 0
    for i in range(k.shape[0]):
        if k[i] != 0 and t[i] < oldest:
            k[i] = 0
            gone += 1
    return gone
