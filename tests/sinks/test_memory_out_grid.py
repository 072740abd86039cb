"""The memory-out read helpers (sinks/ros/memory_out.py) on hand-made grids: the occupancy
layout (rows along y, the corner at the window's origin), the known-free layer when a snapshot
carries one, drop-off cells into the base frame, the grid rate, and the ROS messages' sizes."""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from types import SimpleNamespace

import numpy as np
import numpy.typing as npt
import pytest

from depthnav_daemon.pipeline.memory_io import GridSnapshot
from depthnav_daemon.sinks.ros.memory_out import (
    GridClock,
    MemoryMessages,
    cliff_cells_xy,
    occupancy,
    occupancy_rgba,
)
from depthnav_daemon.sinks.ros.messages import NAME_OPTIONS, MessageBuilder, RosNames, typestore
from tests.sinks.conftest import with_memory


def snapshot(n: int = 8, cell: float = 0.5) -> GridSnapshot:
    """An n x n grid at (-2, -1): an obstacle in cell (x 1, y 5), a drop-off in cell (6, 2)."""
    grid = np.zeros((n, n), np.uint8)
    grid[1, 5] = 1  # [i, j] = (x index, y index)
    grid[6, 2] = 2
    return GridSnapshot(grid, (-2.0, -1.0), cell)


@dataclass(frozen=True)
class KnownSnapshot:
    """A snapshot with the memory's known-free layer, as the pipeline may give it."""

    grid: npt.NDArray[np.uint8]
    origin_m: tuple[float, float]
    cell_m: float
    known: npt.NDArray[np.uint8]


def test_rows_run_along_y_and_drop_offs_are_occupied() -> None:
    occ = occupancy(snapshot())
    assert occ.cells.shape == (8, 8) and occ.cells.dtype == np.int8
    assert occ.cells[5, 1] == occ.cells[2, 6] == 100  # [row = y, col = x]
    assert np.count_nonzero(occ.cells == 100) == 2
    # without the known-free layer nothing is claimed free: the rest is unknown
    assert np.count_nonzero(occ.cells == -1) == 62 and not occ.known_free
    assert occ.origin_m == (-2.0, -1.0) and occ.cell_m == 0.5


def test_the_known_free_layer_gives_free_cells_and_occupied_wins() -> None:
    snap = snapshot()
    known = np.zeros((8, 8), np.uint8)
    known[:4, :] = 1  # x index 0..3 known free
    known[1, 5] = 1  # an obstacle cell also flagged: occupied wins
    occ = occupancy(KnownSnapshot(snap.grid, snap.origin_m, snap.cell_m, known))  # type: ignore[arg-type]
    assert occ.known_free
    assert np.all(occ.cells[:, :4][occ.cells[:, :4] != 100] == 0)
    assert occ.cells[5, 1] == 100 and np.all(occ.cells[:, 4:][occ.cells[:, 4:] != 100] == -1)
    rgba = occupancy_rgba(occ)
    assert rgba.shape == (8, 8, 5)
    assert rgba[0, 0, 4] > 0 and rgba[0, 7, 4] == 0  # free faint, unknown clear
    assert tuple(rgba[5, 1, 1:4]) != tuple(rgba[2, 6, 1:4])  # obstacle and drop-off differ
    assert rgba[5, 1, 0] == 100 and rgba[0, 7, 0] == 255  # the int8 value's byte


def test_drop_off_cells_come_into_the_base_frame() -> None:
    # the drop-off cell (6, 2) has its centre at odometry (-2 + 3.25, -1 + 1.25) = (1.25, 0.25)
    for pose in ((0.0, 0.0, 0.0), (1.0, -0.5, math.radians(90))):
        (xy,) = cliff_cells_xy(SimpleNamespace(grid=snapshot(), pose=pose))  # type: ignore[arg-type]
        x, y, yaw = pose
        dx, dy = 1.25 - x, 0.25 - y
        want = (math.cos(yaw) * dx + math.sin(yaw) * dy, -math.sin(yaw) * dx + math.cos(yaw) * dy)
        assert tuple(xy) == pytest.approx(want, abs=1e-6)


def test_the_grid_clock_keeps_its_rate_in_frame_time() -> None:
    clock = GridClock(2.0)
    due = [clock.due(i / 30.0) for i in range(90)]  # 3 s at 30 frames/s
    assert [i for i, d in enumerate(due) if d] == [0, 15, 30, 45, 60, 75]
    assert clock.due(0.1)  # time went back (a new pass): at once
    assert not any(GridClock(0.0).due(t) for t in (0.0, 1.0, 100.0))
    slow = GridClock(2.0)
    assert all(slow.due(i * 0.83) for i in range(5))  # frames slower than the rate: every one


@pytest.mark.parametrize("ros1", [True, False])
def test_a_grid_is_the_memorys_size_and_nothing_goes_out_while_frozen(pairs, ros1) -> None:
    _, result = pairs[0]
    result = with_memory(result)
    names = RosNames(dict(NAME_OPTIONS))
    store = typestore(ros1=ros1)
    mem = MemoryMessages(MessageBuilder(store, names))
    out = dict(mem.messages(result, 10**9))
    assert set(out) == {"/tf", "/memory/grid", "/memory/scan", "/memory/cliff/points"}
    assert set(mem.msgtypes()) == set(out)
    grid = out["/memory/grid"]
    assert (grid.info.width, grid.info.height) == (160, 160)
    size = len(store.serialize_ros1(grid, grid.__msgtype__) if ros1 else store.serialize_cdr(
        grid, grid.__msgtype__))  # fmt: skip
    assert 160 * 160 < size < 160 * 160 + 200  # the cells and a small header
    frozen = replace(result, memory=replace(result.memory, status="frozen", scan=None, pose=None))
    assert mem.messages(frozen, 2 * 10**9) == []
    off = RosNames(dict(NAME_OPTIONS), grid_rate=0.0, odom_tf=False)
    quiet = MemoryMessages(MessageBuilder(store, off))
    assert [t for t, _ in quiet.messages(result, 10**9)] == ["/memory/scan", "/memory/cliff/points"]
