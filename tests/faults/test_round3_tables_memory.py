"""Round 3, part 2 (issue 35 item 11): the exact scan's and the cliff's tables within a memory
budget (scan_table.TABLE_BUDGET_B_PER_PX, 64 B a pixel at the peak of their building, kept tables
and scratch; the camera rays they share counted apart). Before: ~107 B a pixel for the tables
(the (Hs, Ws) grid of rays, float64 bearings and int64 bin maps of every pixel, a float64 floor
range array), two 4096x8192 frames peaked at 4.5 GB. Values unchanged: tests/pipeline's
test_tables, test_scan and test_cliff pin them; here the compiled +inf rows against numpy's."""

from __future__ import annotations

import dataclasses
import sys
from pathlib import Path

import numpy as np
import pytest

from depthnav_daemon.commands.bench.table_memory import table_memory
from depthnav_daemon.pipeline import scan_table
from depthnav_daemon.pipeline.geometry import Mount, cam_to_level
from depthnav_daemon.pipeline.params import ScanParams
from depthnav_daemon.pipeline.scan_table import TABLE_BUDGET_B_PER_PX, exact_table, table_cache
from drivers.base import Frame, Intrinsics
from drivers.formats.recording_writer import write_recording
from tests.faults.kit import FAST, depthnav_measured

BIG = 2048  # a 4 M pixel camera: ~200 MB of tables at the budget


def test_the_tables_stay_within_their_budget_per_pixel() -> None:
    """In a fresh child per size (bench's own measure): peak while building, over the rays."""
    for got in table_memory(((640, 480), (BIG, BIG))):
        assert got.exact, "VmHWM cannot be reset here"
        assert got.tables <= TABLE_BUDGET_B_PER_PX, got
        assert got.kept <= got.tables + 1.0, got  # what stays is within the peak
        assert 20 < got.rays < 30, got  # (H, W, 3) float64: the rays are counted apart


def test_a_large_frame_run_peaks_far_below_what_it_did(tmp_path: Path) -> None:
    """Two 2048x2048 frames through ``depthnav run``: the peak over a run of the 640x480 fixture
    grows by less than 80 B a pixel (the tables 24, the rays 24, the pose table, frames; it was
    133: 709 MB against 374 MB now)."""
    from depthnav_daemon.sim.synthetic import Scene, render

    f = 525.0 * BIG / 640
    intr = Intrinsics(BIG, BIG, f, f, BIG / 2 - 0.5, BIG / 2 - 0.5)
    depth = render(Scene(), intr, Mount(0.5, 15.0, 0.0)).depth_mm
    write_recording(tmp_path / "big", [Frame(i, i / 30, depth, intr) for i in range(2)])
    small = depthnav_measured("run", "--device", FAST, "--sink", "null", "--max-frames", "2")
    big = depthnav_measured("run", "--device", f"replay:{tmp_path / 'big'}", "--sink", "null")
    assert small.returncode == 0 and big.returncode == 0, big.stderr
    per_px = (big.peak_mb - small.peak_mb) * (1 << 20) / BIG**2
    assert per_px < 80, (big.peak_mb, small.peak_mb, per_px)


def _reach_numpy(probe: np.ndarray, g: object, rot: np.ndarray, h: float, reach: float):
    """The numpy definition the kernel replaced: every pixel's floor range, then per run its
    last row from the first on whose floor point lies at or beyond ``reach``."""
    v = [rot[k, 0] * g.x + rot[k, 1] * g.y + rot[k, 2] for k in range(3)]  # type: ignore[attr-defined]
    with np.errstate(divide="ignore", invalid="ignore"):
        t = np.where(v[2] < 0, h / -v[2], np.inf)
        floor = np.where(np.isfinite(t), t * np.hypot(v[0], v[1]), np.inf)
    c, r0, r1 = (probe[k].astype(np.int64) for k in range(3))
    lim = r0 - 1
    for k in range(int((r1 - r0).max(initial=-1)) + 1):
        row = np.minimum(r0 + k, floor.shape[0] - 1)
        ok = (r0 + k <= r1) & (lim == r0 + k - 1) & (floor[row, c] >= reach)
        lim = np.where(ok, r0 + k, lim)
    return lim.astype(np.int16)


@pytest.mark.parametrize(
    "mount", [Mount(0.5, 15.0, 0.0), Mount(1.2, 40.0, 8.0), Mount(0.3, -5.0, -20.0)]
)
@pytest.mark.parametrize("lens", [False, True])
def test_the_compiled_reach_rows_are_numpys(mount: Mount, lens: bool) -> None:
    k = {"k1": 0.08, "k2": -0.03, "p1": 0.001, "p2": -0.001} if lens else {}
    intr = Intrinsics(320, 240, 290.0, 280.0, 161.0, 118.0, **k)
    params = ScanParams(range_max_m=3.0, col_step=2)
    t = exact_table(intr, mount, params)
    g = scan_table._grid(intr, (0, intr.height, 1), params.col_step)
    rot = cam_to_level(mount.tilt_rad, mount.roll_rad)
    reach = params.range_max_m * (1 + scan_table.REACH_MARGIN)
    want = _reach_numpy(t.probe, g, rot, mount.height_m, reach)
    np.testing.assert_array_equal(t.probe_lim, want)
    assert (want >= t.probe[1]).any() and (want < t.probe[1]).any()  # both kinds of run


@dataclasses.dataclass(frozen=True)
class _Table:
    a: np.ndarray


def test_the_table_cache_is_bounded_by_bytes_and_keeps_the_newest_two() -> None:
    built: list[int] = []

    @table_cache(16, max_bytes=3 << 20)
    def build(key: int) -> _Table:
        built.append(key)
        return _Table(np.zeros(1 << 20, np.uint8))  # 1 MiB each

    for key in range(6):
        build(key)
    assert build.cache_info().currsize == 3  # 3 MiB of them
    build(5)
    build(4)
    assert built == list(range(6))  # the newest were kept
    build(0)
    assert built[-1] == 0 and build.cache_info().misses == 7
    huge = table_cache(16, max_bytes=1)(build.__wrapped__)  # every table over the bound
    for key in range(4):
        huge(key)
    assert huge.cache_info().currsize == 2  # the one serving and the one being built
    build.cache_clear()
    assert build.cache_info().currsize == 0 and build.cache_info().hits == 0


if __name__ == "__main__":
    sys.exit(pytest.main([__file__]))
