"""The exact scan's block tables (built once per mount, beside scan_table's per-pixel tables).

The per-frame kernel (scan_kernels.exact_scan_kernel) looks at every row in blocks of BLOCK
columns. Three tables let it skip most of the work on the pixels that cannot matter:

- per block, the depths that are an obstacle or too close for *some* pixel of the block: a block
  whose depths all lie outside is not read further (most of the floor, and everything beyond
  range_max), and a block whose depths are all obstacles for *every* pixel needs no thresholds;
- where in the flush codes each block's flushes of a row start (a block whose columns hold no
  obstacle since their runs last ended has nothing to flush);
- per bin, the runs of pixels that feed it, so that a bin left without an obstacle is told apart
  (+inf: some reading; NaN: none) by looking up its pixels only then, usually the first one.
"""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

from depthnav_daemon.pipeline._jit import inlined, kernel
from depthnav_daemon.pipeline.scan_kernels import BLOCK, CODE_BITS, CODE_MASK

U16 = npt.NDArray[np.uint16]
I32 = npt.NDArray[np.int32]
I16 = npt.NDArray[np.int16]


def block_tables(
    k_lo: U16, k_mid: U16, k_hi: U16, fl_start: I32, fl_code: I32, n_bins: int
) -> tuple[U16, I32, I32, I16, I16]:
    """The block tables of one mount (see the module docstring).

    Args:
        k_lo, k_mid, k_hi: (Hs, Ws) the kernel's per-pixel thresholds (scan_table.ExactTable):
            close iff k_lo <= d <= k_mid, obstacle iff k_mid < d <= k_hi.
        fl_start, fl_code: the run flush codes (scan_kernels.run_flush_codes).
        n_bins: bins of the scan (bin n_bins is the codes' scratch slot).

    Returns:
        blk: (4, Hs, nb) uint16 per block: [0] lo and [1] hi: a depth d is close or an obstacle
            for some pixel only if lo <= d <= hi (none: lo > hi); [2] the largest k_mid and [3]
            the smallest k_hi: readings all in (blk[2], blk[3]] are obstacles for every pixel;
        fl_blk: (Hs * nb + 1,) the flushes after row i in block k are
            fl_code[fl_blk[i * nb + k]:fl_blk[i * nb + k + 1]];
        probe_start: (n + 1,) the runs feeding bin b are
            probe[:, probe_start[b]:probe_start[b + 1]];
        probe: (3, P) int16 column, first and last row (kernel rows) of each run;
        spans: (2, n) int16 first and last row of each bin's runs (last < first: no run).
    """
    return block_tables_kernel(k_lo, k_mid, k_hi, fl_start, fl_code, BLOCK, int(n_bins))


@kernel
def block_tables_kernel(k_lo, k_mid, k_hi, fl_start, fl_code, block, n_bins):
    """block_tables (one kernel: each compiled kernel costs about a second on a first run)."""
    blk, fl_blk = _block_bounds(k_lo, k_mid, k_hi, fl_start, fl_code, block)
    probe_start, probe, spans = _probes(fl_start, fl_code, n_bins, k_lo.shape[1])
    return blk, fl_blk, probe_start, probe, spans


@inlined
def _block_bounds(k_lo, k_mid, k_hi, fl_start, fl_code, block):
    """block_tables' blk and fl_blk."""
    hs, ws = k_lo.shape
    nb = (ws + block - 1) // block
    blk = np.empty((4, hs, nb), np.uint16)
    for i in range(hs):
        for k in range(nb):
            blk[0, i, k] = 65535
            blk[1, i, k] = 0
            blk[2, i, k] = 0
            blk[3, i, k] = 65535
        for j in range(ws):
            k = j // block
            lo = k_lo[i, j]
            hi = max(k_mid[i, j], k_hi[i, j])
            if lo <= hi:  # some depth is close or an obstacle here
                blk[0, i, k] = min(blk[0, i, k], lo)
                blk[1, i, k] = max(blk[1, i, k], hi)
            blk[2, i, k] = max(blk[2, i, k], k_mid[i, j])
            blk[3, i, k] = min(blk[3, i, k], k_hi[i, j])
    fl_blk = np.empty(hs * nb + 1, np.int32)
    for i in range(hs):
        e = fl_start[i]
        for k in range(nb):
            fl_blk[i * nb + k] = e
            # codes of a row are in column order (run_flush_codes walks the columns in order)
            while e < fl_start[i + 1] and (fl_code[e] & CODE_MASK) < (k + 1) * block:
                e += 1
    fl_blk[hs * nb] = fl_start[hs]
    return blk, fl_blk


@inlined
def _probes(fl_start, fl_code, n_bins, ws):
    """block_tables' probe_start, probe and spans: every (run, bin) flush as (column, first row,
    last row), grouped by bin (a counting sort); flushes into the scratch bin n_bins are left
    out."""
    hs = fl_start.shape[0] - 1
    start = np.zeros(n_bins + 2, np.int32)
    for e in range(fl_code.shape[0]):
        b = fl_code[e] >> (CODE_BITS + 1)
        if b < n_bins:
            start[b + 2] += 1
    for b in range(n_bins + 1):
        start[b + 1] += start[b]
    probe = np.empty((3, start[n_bins + 1]), np.int16)  # columns and rows < 32768
    first = np.zeros(ws, np.int32)  # the row each column's current run began at
    for i in range(hs):
        for e in range(fl_start[i], fl_start[i + 1]):
            x = fl_code[e]
            c = x & CODE_MASK
            b = x >> (CODE_BITS + 1)
            if b < n_bins:
                p = start[b + 1]
                probe[0, p] = np.int16(c)
                probe[1, p] = np.int16(first[c])
                probe[2, p] = np.int16(i)
                start[b + 1] = p + 1
            if x & (1 << CODE_BITS):
                first[c] = i + 1
    # each bin's span of rows (first, last; none: last < first), so that a bin over rows
    # without a reading is answered at once
    spans = np.empty((2, n_bins), np.int16)
    for b in range(n_bins):
        lo = np.int16(32767)
        hi = np.int16(-1)
        for p in range(start[b], start[b + 1]):
            lo = min(lo, probe[1, p])
            hi = max(hi, probe[2, p])
        spans[0, b] = lo
        spans[1, b] = hi
    return start[: n_bins + 1].copy(), probe, spans
