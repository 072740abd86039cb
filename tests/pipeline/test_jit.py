"""The compile helpers of pipeline/_jit.py: the prefetch hint compiles for every array the exact
scan is handed (C-ordered, strided, read-only), changes nothing, and takes only 2-D arrays."""

from __future__ import annotations

import numpy as np
import pytest
from numba import njit
from numba.core.errors import TypingError

from depthnav_daemon.pipeline._jit import prefetch


@njit(cache=False)
def _sum_rows_ahead(a, ahead):
    """Sum of a's elements, prefetching ``ahead`` rows ahead (past the end: not asked)."""
    total = 0
    rows, cols = a.shape
    for i in range(rows):
        if i + ahead < rows:
            for j in range(0, cols, 32):
                prefetch(a, i + ahead, j)
        for j in range(cols):
            total += a[i, j]
    return total


@pytest.mark.parametrize("ahead", [0, 1, 4, 1000])
def test_prefetch_compiles_for_every_layout_and_changes_nothing(ahead: int) -> None:
    rng = np.random.default_rng(3)
    frame = rng.integers(0, 8000, (48, 130), dtype=np.uint16)
    strided = frame[:, 1::2]
    read_only = frame.copy()
    read_only.setflags(write=False)
    for a in (frame, strided, read_only, np.asfortranarray(frame)):
        assert _sum_rows_ahead(a, ahead) == int(a.sum(dtype=np.int64))


def test_prefetch_takes_only_a_2d_array() -> None:
    @njit(cache=False)
    def flat(a):
        prefetch(a, 0, 0)

    with pytest.raises(TypingError):
        flat(np.zeros(4, np.uint16))
