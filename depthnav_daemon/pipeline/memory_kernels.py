"""Compiled kernels of the obstacle memory (``memory.py``): the per-view update and the memory scan.

The grid is toroidal: global cell (gx, gy) = floor(odometry x / cell, y / cell) lives at index
(gx mod n, gy mod n), so moving the window is clearing the rows and columns that leave it (no copy).
Each marked cell also keeps where in the cell its last point was (sub-cell offsets), so ranges
read back from the memory are not rounded to the cell.

Occupied cells are found by reading the grid eight bytes at a time (a 160 x 160 grid is 3200 words,
most of them zero), so both kernels cost in proportion to what is remembered, not to the grid.
"""

from __future__ import annotations

import numpy as np

from depthnav_daemon.pipeline._jit import kernel

FREE = 0
OBSTACLE = 1
CLIFF = 2

_PI = np.pi
_HALF_PI = np.pi / 2.0


@kernel
def fast_atan2(y, x):
    """atan2(y, x) within 1e-5 rad (a minimax polynomial on [0, 1] after octant reduction)."""
    ax = abs(x)
    ay = abs(y)
    if ax == 0.0 and ay == 0.0:
        return 0.0
    swap = ay > ax
    t = ax / ay if swap else ay / ax
    t2 = t * t
    a = t * (
        0.99997726
        + t2
        * (
            -0.33262347
            + t2 * (0.19354346 + t2 * (-0.11643287 + t2 * (0.05265332 - 0.0117212 * t2)))
        )
    )
    if swap:
        a = _HALF_PI - a
    if x < 0.0:
        a = _PI - a
    return -a if y < 0.0 else a


@kernel
def clear_lines(grid, wx0, wy0, nx0, ny0):
    """Move the window from origin (wx0, wy0) to (nx0, ny0) (global cells): clear the columns and
    rows that leave it (they are the indices the entering ones reuse)."""
    n = grid.shape[0]
    dx = nx0 - wx0
    dy = ny0 - wy0
    if abs(dx) >= n or abs(dy) >= n:
        grid[:, :] = FREE
        return
    lo, hi = (wx0, nx0) if dx > 0 else (nx0 + n, wx0 + n)
    for gx in range(lo, hi):
        grid[gx % n, :] = FREE
    lo, hi = (wy0, ny0) if dy > 0 else (ny0 + n, wy0 + n)
    for gy in range(lo, hi):
        grid[:, gy % n] = FREE


@kernel
def update_view(
    grid,
    stamp,
    offx,
    offy,
    wx0,
    wy0,
    cell,
    sx,
    sy,
    syaw,
    ranges,
    cliff,
    near,
    a0,
    inc,
    rmax,
    margin,
    k_spacing,
    h2,
    rows_scan,
    rows_cliff,
    t_rel,
):
    """Fold one sensor view into the grid: clear what it sees free, then mark what it sees.

    Args:
        grid: (n, n) uint8 FREE / OBSTACLE / CLIFF, toroidal (module docstring).
        stamp: (n, n) float32 time each cell was last marked (seconds since the memory's epoch).
        offx, offy: (n, n) float32 where in its cell the last marked point lies, metres.
        wx0, wy0: the window's first global cell; cell: cell side, metres.
        sx, sy, syaw: the sensor's foot and heading in the odometry frame (metres, radians).
        ranges: (M,) float32 the sensor's level-frame scan (REP 117); bin i at a0 + i * inc.
        cliff: (M,) float32 its cliff scan in the same bins, or an empty array (no cliff stage).
        near: (M,) float32 nearest floor range the sensor sees per bin (its lower dead zone).
        rmax: the scan's range_max (a +inf bin saw floor or beyond up to here).
        margin, k_spacing, h2, rows_scan, rows_cliff: a remembered point within
            max(margin, rows * k_spacing (h2 + d^2)) of what the sensor sees at range d is not
            cleared. The floor is known free only up to the last floor row the stage read, which
            lies up to ``rows`` image rows short of the obstacle (``rows_scan``: the scan's row
            stride) or of the first drop-off it counts (``rows_cliff``: a block and a sample
            stride, as a block straddling the edge may not reach the threshold), one row spanning
            (h^2 + d^2) / (h f_y) metres of floor at range d (k_spacing = 1 / (h f_y)).
        t_rel: this view's time, seconds since the memory's epoch.

    Returns:
        (cleared, marked) cell counts.
    """
    n = grid.shape[0]
    m = ranges.shape[0]
    has_cliff = cliff.shape[0] == m
    inf = np.inf
    # per bin: how far the sensor sees free floor (0: nothing cleared on this bearing)
    clear = np.empty(m, np.float64)
    for i in range(m):
        v = ranges[i]
        d = 0.0
        if not np.isnan(v) and v != -inf:
            d = rmax if v == inf else np.float64(v)
        d -= max(margin, rows_scan * k_spacing * (h2 + d * d))
        if has_cliff:
            c = cliff[i]
            if np.isnan(c) or c == -inf:
                d = 0.0  # the floor there was not read: keep what is remembered
            elif c != inf:
                c = np.float64(c)
                d = min(d, c - max(margin, rows_cliff * k_spacing * (h2 + c * c)))
        clear[i] = d
    c0 = np.cos(syaw)
    s0 = np.sin(syaw)
    lo_b = a0 - 0.5 * inc
    hi_b = a0 + (m - 0.5) * inc
    r2max = rmax * rmax
    cleared = 0
    words = grid.reshape(-1).view(np.uint64)
    for w in range(words.shape[0]):
        if words[w] == 0:
            continue
        for k in range(w * 8, w * 8 + 8):
            ix = k // n
            iy = k - ix * n
            if grid[ix, iy] == FREE:
                continue
            # the cell's global coordinates from its index and the window
            gx = wx0 + (ix - wx0) % n
            gy = wy0 + (iy - wy0) % n
            px = gx * cell + offx[ix, iy] - sx
            py = gy * cell + offy[ix, iy] - sy
            along = c0 * px + s0 * py
            across = -s0 * px + c0 * py
            r2 = along * along + across * across
            if r2 > r2max:
                continue
            b = fast_atan2(across, along)
            if b < lo_b or b > hi_b:
                continue
            i = min(max(np.int64(np.floor((b - a0) / inc + 0.5)), 0), m - 1)
            r = np.sqrt(r2)
            if near[i] <= r < clear[i]:
                grid[ix, iy] = FREE
                cleared += 1
    marked = 0
    # bin bearings by rotation (one cos/sin for the scan, not per bin)
    cb = np.cos(syaw + a0)
    sb = np.sin(syaw + a0)
    ci = np.cos(inc)
    si = np.sin(inc)
    for i in range(m):
        if i > 0:
            cb, sb = cb * ci - sb * si, sb * ci + cb * si
        for kind in range(2):
            if kind == 0:
                v = ranges[i]
                code = OBSTACLE
            elif has_cliff:
                v = cliff[i]
                code = CLIFF
            else:
                break
            if not np.isfinite(v):
                continue
            x = sx + np.float64(v) * cb
            y = sy + np.float64(v) * sb
            gx = np.int64(np.floor(x / cell))
            gy = np.int64(np.floor(y / cell))
            if gx < wx0 or gx >= wx0 + n or gy < wy0 or gy >= wy0 + n:
                continue
            ix = gx % n
            iy = gy % n
            ox = x - gx * cell
            oy = y - gy * cell
            g = grid[ix, iy]
            if g == code:
                # the same kind again: a point this view did not clear is still true, so the
                # cell keeps the nearer point (the one a robot driving up to it meets first)
                stamp[ix, iy] = t_rel
                dold = (gx * cell + offx[ix, iy] - sx) ** 2 + (gy * cell + offy[ix, iy] - sy) ** 2
                if (x - sx) ** 2 + (y - sy) ** 2 >= dold:
                    continue
            elif g == OBSTACLE and code == CLIFF and stamp[ix, iy] == t_rel:
                continue  # an obstacle seen in this frame is not also a drop-off
            grid[ix, iy] = code
            stamp[ix, iy] = t_rel
            offx[ix, iy] = ox
            offy[ix, iy] = oy
            marked += 1
    return cleared, marked


@kernel
def expire(grid, stamp, oldest):
    """Forget cells last marked before ``oldest`` (seconds since the epoch); returns how many."""
    n = grid.shape[0]
    gone = 0
    words = grid.reshape(-1).view(np.uint64)
    for w in range(words.shape[0]):
        if words[w] == 0:
            continue
        for k in range(w * 8, w * 8 + 8):
            ix = k // n
            iy = k - ix * n
            if grid[ix, iy] != FREE and stamp[ix, iy] < oldest:
                grid[ix, iy] = FREE
                gone += 1
    return gone


@kernel
def memory_scan(grid, offx, offy, wx0, wy0, cell, rx, ry, ryaw, out, counts):
    """Nearest remembered point per bearing around the robot (360 deg, bins of 2 pi / N).

    Each remembered point covers the bearings of a disc of half a cell about it (so a row of
    cells reads as a wall, without gaps between its points) at the point's own range.

    Args:
        grid, offx, offy, wx0, wy0, cell: the memory (update_view).
        rx, ry, ryaw: the robot's pose in the odometry frame.
        out: (N,) float32, overwritten: bin j centred on -pi + j * 2 pi / N (base frame), +inf
            where nothing is remembered.
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
    words = grid.reshape(-1).view(np.uint64)
    for w in range(words.shape[0]):
        if words[w] == 0:
            continue
        for k in range(w * 8, w * 8 + 8):
            ix = k // n
            iy = k - ix * n
            g = grid[ix, iy]
            if g == FREE:
                continue
            counts[g] += 1
            gx = wx0 + (ix - wx0) % n
            gy = wy0 + (iy - wy0) % n
            px = gx * cell + offx[ix, iy] - rx
            py = gy * cell + offy[ix, iy] - ry
            fx = c0 * px + s0 * py
            fy = -s0 * px + c0 * py
            r = np.sqrt(fx * fx + fy * fy)
            b = fast_atan2(fy, fx)
            hw = fast_atan2(half, r)
            j0 = np.int64(np.floor((b - hw + np.pi) / inc + 0.5))
            j1 = np.int64(np.floor((b + hw + np.pi) / inc + 0.5))
            v = np.float32(r)
            for j in range(j0, j1 + 1):
                jj = j % nb
                out[jj] = min(out[jj], v)
