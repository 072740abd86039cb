"""The obstacle memory's shadow (``memory.update``): where a view saw something beyond the point it
keeps on a scan bin (a face seen edge-on, a wall above a low box), the cells that were never seen
free become SHADOW, so that the memory scan does not read a point behind them from a later pose
(memory_read_kernels). The grid's layout is ``memory_kernels``'.
"""

from __future__ import annotations

import math

import numpy as np

from depthnav_daemon.pipeline._jit import helper
from depthnav_daemon.pipeline.memory_kernels import SHADOW, mark_segment

# shadow_view: the samples' spacing along a group of bins and the group's width at its farthest
# sample, in cells
SHADOW_STEP_CELLS = 1.0
SHADOW_GROUP_CELLS = 0.7
# where a bin's shadow starts behind the point it reports, in cells: what it saw nearer behind the
# point is the point's own surface, within the memory's stated error of it (a cell's diagonal)
SHADOW_FROM_CELLS = 1.5


@helper
def shadow_view(grid, known, free_t, wx0, wy0, cell, sx, sy, syaw, a0, inc, lo, hi, t_rel):
    """Mark as SHADOW at ``t_rel`` the cells never seen (neither known free nor occupied) between
    lo[i] and hi[i] of each bin (hi < lo: none): where the view saw something beyond the point it
    reports (the memory keeps only that point). A face seen edge-on is a sliver of one bin, so
    every bin is walked: bins in groups as wide as SHADOW_GROUP_CELLS at the farthest hi (one
    bin where bins are wider), each group's centre from its least lo to its largest hi,
    SHADOW_STEP_CELLS apart. A shadow needs no cell-tight marking (a cell left out is judged as
    never seen, one marked too many makes the memory scan more cautious). Returns the samples
    written."""
    n = grid.shape[0]
    bx = wx0 % n  # once: an integer division costs more than a cell
    by = wy0 % n
    m = lo.shape[0]
    step = SHADOW_STEP_CELLS * cell
    reach = 0.0
    for i in range(m):
        if hi[i] >= lo[i]:
            reach = max(reach, hi[i])
    if reach <= 0.0:
        return 0
    g = max(np.int64(1), np.int64(SHADOW_GROUP_CELLS * cell / (inc * reach)))  # bins per group
    inv = 1.0 / cell
    written = 0
    for i0 in range(0, m, g):
        i1 = min(i0 + g, m)
        a = np.inf
        b = -1.0
        for i in range(i0, i1):
            if hi[i] >= lo[i]:
                a = min(a, lo[i])
                b = max(b, hi[i])
        if not b >= a:
            continue
        th = syaw + a0 + 0.5 * (i0 + i1 - 1) * inc
        c = math.cos(th)
        s = math.sin(th)
        written += mark_segment(
            grid, known, free_t, wx0, wy0, bx, by, sx, sy, c, s, a, b, step, inv, t_rel, SHADOW
        )
    return written
