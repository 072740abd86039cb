"""The exact scan's block skipping (scan_blocks): skipping blocks, the ranges-only path and the
late +inf/NaN look-up change no value. Each case compares the kernel with the per-row binning
definition (test_kernels.reference_exact_scan) on frames made to reach the paths: walls with holes,
a sky of zeros above the floor, readings so sparse that most bins' first pixels are zeros, and
widths that are not a multiple of the block."""

from __future__ import annotations

import numpy as np
import pytest

from depthnav_daemon.pipeline import scan_table
from depthnav_daemon.pipeline.geometry import Mount
from depthnav_daemon.pipeline.scan import ScanParams, depth_to_scan
from depthnav_daemon.pipeline.scan_blocks import block_tables
from depthnav_daemon.pipeline.scan_kernels import BLOCK, CODE_BITS, CODE_MASK
from drivers.base import Intrinsics
from tests.pipeline.test_kernels import noisy_frame, reference_exact_scan

QVGA = Intrinsics(320, 240, 290.0, 291.0, 159.5, 119.5)  # 5 blocks a row
ODD = Intrinsics(130, 90, 120.0, 120.0, 64.2, 44.9)  # 2 blocks and 2 columns
MOUNTS = [Mount(0.55, 15.0, 0.0), Mount(0.8, 40.0, 5.0), Mount(1.2, 50.0, -8.0)]


def _frames(intr: Intrinsics, mount: Mount, seed: int) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(seed)
    base = noisy_frame(intr, mount, seed)
    holes = base.copy()
    holes[rng.random(base.shape) < 0.05] = 0  # a wall with a few holes: still ranges only
    sky = base.copy()
    sky[: intr.height // 2] = 0  # nothing seen above the middle: NaN or +inf from the floor
    sparse = base.copy()
    sparse[rng.random(base.shape) < 0.98] = 0  # most bins' first pixels have no reading
    lone = np.zeros_like(base)
    lone[0, ::7] = 9000  # beyond range_max, top row only
    blind = np.zeros_like(base)  # a covered sensor: every bin NaN, without a walk each
    return {
        "noisy": base,
        "holes": holes,
        "sky": sky,
        "sparse": sparse,
        "lone": lone,
        "blind": blind,
    }


@pytest.mark.parametrize("intr", [QVGA, ODD], ids=["qvga", "odd_width"])
@pytest.mark.parametrize("mount", MOUNTS, ids=lambda m: f"t{m.tilt_deg:g}_r{m.roll_deg:g}")
def test_block_skipping_equals_the_definition(intr: Intrinsics, mount: Mount) -> None:
    params = ScanParams()
    for name, depth in _frames(intr, mount, seed=int(mount.tilt_deg)).items():
        got = depth_to_scan(depth, intr, mount, params).ranges
        want = reference_exact_scan(depth, intr, mount, params)
        assert np.array_equal(got, want, equal_nan=True), name
        if name == "lone":
            # a reading beyond range_max in the top row only: +inf needs one at a run's
            # range_max row (the safety contract), which the top row is for few bins if any
            assert np.isnan(got).any()
        if name == "blind":
            assert np.isnan(got).all()


@pytest.mark.parametrize("mount", MOUNTS, ids=lambda m: f"t{m.tilt_deg:g}_r{m.roll_deg:g}")
def test_block_tables_bound_every_pixel_and_partition_the_flushes(mount: Mount) -> None:
    t = scan_table.exact_table(QVGA, mount, ScanParams())
    blk, fl_blk, probe_start, probe, spans = block_tables(
        t.k_lo, t.k_mid, t.k_hi, t.fl_start, t.fl_code, t.n_bins
    )
    hs, ws = t.k_lo.shape
    nb = blk.shape[2]
    assert nb == -(-ws // BLOCK)
    for k in range(nb):
        cols = slice(k * BLOCK, min(ws, (k + 1) * BLOCK))
        lo, mid, hi = t.k_lo[:, cols], t.k_mid[:, cols], t.k_hi[:, cols]
        top = np.maximum(mid, hi)
        some = lo <= top  # pixels where some depth is close or an obstacle
        assert (blk[0, :, k, None] <= np.where(some, lo, 65535)).all()
        assert (blk[1, :, k, None] >= np.where(some, top, 0)).all()
        assert (blk[2, :, k, None] >= mid).all() and (blk[3, :, k, None] <= hi).all()
    # the block starts split each row's flushes by column, in order, covering all of them
    starts = fl_blk[:-1].reshape(hs, nb)
    assert (starts[:, 0] == t.fl_start[:-1]).all() and fl_blk[-1] == t.fl_start[-1]
    assert (np.diff(fl_blk) >= 0).all()
    col = t.fl_code & CODE_MASK
    for i in range(hs):
        for k in range(nb):
            end = fl_blk[i * nb + k + 1]
            assert (col[starts[i, k] : end] // BLOCK == k).all()
    # every flush into a real bin is one probe of that bin, and a probe's rows end on its flush row
    real = (t.fl_code >> (CODE_BITS + 1)) < t.n_bins
    assert probe_start[0] == 0 and probe_start[-1] == probe.shape[1] == int(real.sum())
    counts = np.bincount(t.fl_code[real] >> (CODE_BITS + 1), minlength=t.n_bins)
    assert np.array_equal(np.diff(probe_start), counts)
    assert (probe[1] <= probe[2]).all() and (probe[2] < hs).all()
    for b in range(t.n_bins):  # a bin's span of rows covers its runs
        runs = probe[:, probe_start[b] : probe_start[b + 1]]
        if runs.shape[1]:
            assert spans[0, b] == runs[1].min() and spans[1, b] == runs[2].max()
        else:
            assert spans[1, b] < spans[0, b]
