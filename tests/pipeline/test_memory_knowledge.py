"""What the memory knows (issue 31): it clears only the floor a view saw, tells unknown (NaN) from
known free (+inf), keeps "too close" readings, and forgets free knowledge with max_age_s.

Truth comes from the scene geometry (sim.truth), in the robot's base frame; the synthetic world is
the odometry frame (exact odometry).
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from depthnav_daemon.errors import ConfigError
from depthnav_daemon.pipeline import StageParams, process
from depthnav_daemon.pipeline.cliff_table import cliff_table
from depthnav_daemon.pipeline.coverage import floor_extent
from depthnav_daemon.pipeline.geometry import Mount
from depthnav_daemon.pipeline.memory import (
    MemoryParams,
    SensorView,
    new_state,
    read_scan,
    scan_limits,
    update,
)
from depthnav_daemon.pipeline.memory_kernels import CLIFF, OBSTACLE
from depthnav_daemon.pipeline.scan import ScanParams
from depthnav_daemon.pipeline.scan_table import exact_table
from depthnav_daemon.sim.drive import render_drive, straight, turn_in_place
from depthnav_daemon.sim.synthetic import Box, Scene, step_down
from depthnav_daemon.sim.truth import slab, truth_obstacle_interval
from tests.pipeline.test_memory import DENSE_CLIFF, MOUNT, QVGA, view_of

SCAN = StageParams(scan=ScanParams())
AHEAD_BOX = Box(2.15, 0.0, 0.3, 0.3, 0.5)  # its face 2.0 m ahead


def _frame(scene: Scene, pose=(0.0, 0.0, 0.0), params: StageParams = SCAN, mount: Mount = MOUNT):
    (d,) = render_drive(scene, QVGA, mount, [(0.0, *pose)])
    return d.frame, process(d.frame, mount, params)


def _bin(scan, bearing: float) -> int:
    return int(np.argmin(np.abs((scan.angles - bearing + np.pi) % (2 * np.pi) - np.pi)))


def _in_base_frame(box: Box, pose) -> Box:
    x, y, yaw = pose
    c, s = math.cos(yaw), math.sin(yaw)
    dx, dy = box.x_m - x, box.y_m - y
    return dataclasses.replace(
        box, x_m=c * dx + s * dy, y_m=-s * dx + c * dy, yaw_deg=box.yaw_deg - math.degrees(yaw)
    )


def test_start_up_is_unknown_and_a_view_makes_only_what_it_saw_known() -> None:
    state = new_state(MemoryParams())
    assert np.isnan(read_scan(state, (0.0, 0.0, 0.0)).scan.ranges).all()
    _, r = _frame(Scene())
    update(state, (0.0, 0.0, 0.0), 0.0, [view_of(r)])
    scan = read_scan(state, (0.0, 0.0, 0.0)).scan
    wide = np.abs(scan.angles) > math.radians(40.0)  # the camera sees +-29 deg
    assert np.isnan(scan.ranges[wide]).all()
    assert np.isposinf(scan.ranges[_bin(scan, 0.0)])  # floor seen from the blind radius on
    assert not np.isfinite(scan.ranges).any()


def test_bearings_never_observed_stay_unknown_after_a_drive() -> None:
    state = new_state(MemoryParams())
    for d in render_drive(Scene(), QVGA, MOUNT, straight(0.3, 5.0, 8)):  # 1.4 m
        update(state, d.frame.odom, d.frame.timestamp_s, [view_of(process(d.frame, MOUNT, SCAN))])
    scan = read_scan(state, d.frame.odom).scan
    behind = np.abs(scan.angles) > math.radians(150.0)  # behind the start: never in view
    assert np.isnan(scan.ranges[behind]).all()
    ahead = np.abs(scan.angles) < math.radians(10.0)
    assert np.isposinf(scan.ranges[ahead]).all()


def test_a_too_close_reading_is_kept_at_range_min_and_clears_nothing() -> None:
    state = new_state(MemoryParams())
    _, boxed = _frame(Scene(boxes=(AHEAD_BOX,)))
    update(state, (0.0, 0.0, 0.0), 0.0, [view_of(boxed)])
    # the box went, and something now stands too close on the bearings around straight ahead
    _, empty = _frame(Scene())
    sc = empty.level_scan
    ranges = sc.ranges.copy()
    close = np.abs(sc.angles) < math.radians(2.0)
    ranges[close] = -np.inf
    view = dataclasses.replace(view_of(empty), scan=dataclasses.replace(sc, ranges=ranges))
    update(state, (0.0, 0.0, 0.0), 0.1, [view])
    scan = read_scan(state, (0.0, 0.0, 0.0)).scan
    assert scan.ranges[_bin(scan, 0.0)] == pytest.approx(sc.range_min, abs=0.01)
    # on the -inf bins nothing was cleared: the box's points there are still remembered
    n = state.grid.shape[0]
    ix, iy = np.nonzero(state.grid == OBSTACLE)
    gx, gy = state.wx0 + (ix - state.wx0) % n, state.wy0 + (iy - state.wy0) % n
    px, py = gx * 0.05 + state.offx[ix, iy], gy * 0.05 + state.offy[ix, iy]
    on_box = px > 1.9
    assert on_box.any()
    assert (np.abs(np.arctan2(py[on_box], px[on_box])) < math.radians(2.5)).all()  # the rest went


def test_cells_outside_the_view_keep_their_state() -> None:
    state = new_state(MemoryParams())
    _, r = _frame(Scene(boxes=(AHEAD_BOX,)))
    update(state, (0.0, 0.0, 0.0), 0.0, [view_of(r)])
    grid, known = state.grid.copy(), state.known.copy()
    boxed = state.grid == OBSTACLE
    assert boxed.sum() > 3
    # turned 90 deg left: the box is now on the robot's right, out of view; the view sees floor
    left = (0.0, 0.0, math.pi / 2)
    _, r = _frame(Scene(boxes=(AHEAD_BOX,)), left)
    update(state, left, 0.1, [view_of(r)])
    assert (state.grid[boxed] == OBSTACLE).all()
    changed = (state.grid != grid) | (state.known != known)
    n = state.grid.shape[0]
    _, iy = np.nonzero(changed)
    gy = state.wy0 + (iy - state.wy0) % n
    assert changed.sum() > 100
    assert ((gy + 0.5) * 0.05 > 0.5).all()  # all in front of the new view (its floor from 0.65 m)
    assert np.isnan(read_scan(state, left).scan.ranges[_bin(read_scan(state, left).scan, -1.0)])


def _mark_at(state, mount: Mount, empty, pairs: list[tuple[int, float]]) -> None:
    """Remember obstacle points at (bin, range) of ``empty``'s scan layout (a view that saw only
    them)."""
    sc = empty.level_scan
    ranges = np.full(sc.ranges.size, np.nan, np.float32)
    for i, d in pairs:
        ranges[i] = d
    scan = dataclasses.replace(sc, ranges=ranges)
    update(state, (0.0, 0.0, 0.0), 0.0, [SensorView(mount, QVGA, scan)])


@pytest.mark.parametrize("told", [False, True])
def test_a_view_clears_no_farther_than_its_image_reaches(told: bool) -> None:
    """The issue's cause: a bin at the edge of a tilted image sees floor only near the robot (its
    ``far``), and its scan says NaN there (the view does not reach range_max); told which NaN bins
    saw only floor (``short_free``), the memory clears up to ``far`` on them, never beyond."""
    _, empty = _frame(Scene())
    sc = empty.level_scan
    n = sc.ranges.size
    near, far = floor_extent(QVGA, MOUNT, sc.angle_min, sc.angle_increment, n, (0, -1, 1))
    short = exact_table(QVGA, MOUNT, SCAN.scan).short_view
    reach = np.where(far[short] < 3.0, far[short], 0.0)
    i = int(short[np.argmax(reach)])  # a short bin whose floor ends between 1 and 3 m
    assert np.isnan(sc.ranges[i]) and 1.0 < far[i] < 3.0
    state = new_state(MemoryParams())
    _mark_at(state, MOUNT, empty, [(i, float(far[i]) + 0.3)])
    state2 = new_state(MemoryParams())
    _mark_at(state2, MOUNT, empty, [(i, float(near[i] + far[i]) / 2)])
    free = short[np.isnan(sc.ranges[short])] if told else None
    view = dataclasses.replace(view_of(empty), short_free=free)
    update(state, (0.0, 0.0, 0.0), 0.1, [view])
    update(state2, (0.0, 0.0, 0.0), 0.1, [view])
    assert (state.grid == OBSTACLE).sum() == 1  # beyond far: kept
    assert (state2.grid == OBSTACLE).sum() == (0 if told else 1)  # within: cleared if told


def test_free_knowledge_expires_with_max_age() -> None:
    state = new_state(MemoryParams(max_age_s=1.0))
    _, r = _frame(Scene())
    update(state, (0.0, 0.0, 0.0), 0.0, [view_of(r)])
    ahead = lambda: read_scan(state, (0.0, 0.0, 0.0)).scan.ranges[180]  # noqa: E731
    assert np.isposinf(ahead())
    assert update(state, (0.0, 0.0, 0.0), 0.9, []).forgotten_free == 0
    assert np.isposinf(ahead())
    assert update(state, (0.0, 0.0, 0.0), 1.1, []).forgotten_free > 100
    assert np.isnan(ahead())


def test_driving_past_a_box_keeps_it_and_never_reads_clear_on_it() -> None:
    """Issue 31: a box 0.7-1.0 m to the left, 2.0-2.3 m ahead at the start, passed at 0.3 m/s.
    Every frame, on every bin whose bearing touches the box: never +inf while the box is within
    range_max, never a phantom nearer than it, never beyond the box's far side; and its nearest
    point read within 5 cm until it is farther than range_max."""
    box = Box(2.15, 0.85, 0.3, 0.3, 0.5)
    state = new_state(MemoryParams())
    kept = 0
    for d in render_drive(Scene(boxes=(box,)), QVGA, MOUNT, straight(0.3, 5.0, 105)):
        update(state, d.frame.odom, d.frame.timestamp_s, [view_of(process(d.frame, MOUNT, SCAN))])
        scan = read_scan(state, d.frame.odom).scan
        rel = _in_base_frame(box, d.pose)
        half = scan.angle_increment / 2
        lo, _ = truth_obstacle_interval(Scene(boxes=(rel,)), scan.angles, half, 0.05, 2.0)
        on = np.isfinite(lo)
        # a remembered point covers the bearings of a disc of half a cell about it (the box is
        # >= 0.7 m away): on a face seen at a grazing angle that reads nearer than the bin's own
        # truth (the safe side)
        widened = half + math.atan(0.025 / 0.7)
        lo_w, _ = truth_obstacle_interval(Scene(boxes=(rel,)), scan.angles, widened, 0.05, 2.0)
        r = scan.ranges[on]
        assert not np.isposinf(r[lo[on] <= scan.range_max]).any(), d.pose
        # the far side of the box over each bin (the remembered points lie on or in the box)
        sub = scan.angles[on, None] + np.linspace(-half, half, 9)[None, :]
        dirs = np.stack([np.cos(sub), np.sin(sub)], axis=-1)
        centre = np.array([rel.x_m, rel.y_m])
        extent = np.array([box.length_m, box.width_m]) / 2
        _, t_out = slab(-centre, dirs, -extent, extent)
        t_out = np.where(np.isfinite(t_out) & (t_out > 0), t_out, np.nan)
        fin = np.isfinite(r)
        assert (r[fin] >= lo_w[on][fin] - 0.01).all(), d.pose
        assert (r[fin] <= np.nanmax(t_out, axis=1)[fin] + 0.05).all(), d.pose
        nearest = float(lo[on].min())
        if nearest <= scan.range_max - 0.05:
            assert np.nanmin(np.where(fin, r, np.nan)) == pytest.approx(nearest, abs=0.05), d.pose
            kept += d.pose[0] > 2.3  # passed it: only the memory has it
    assert kept >= 40


def test_a_step_edge_stays_where_it_was_through_a_quarter_turn() -> None:
    params = StageParams(scan=ScanParams(), cliff=DENSE_CLIFF)
    edge_x = 1.5
    state = new_state(MemoryParams())
    still = [(0.1 * i, 0.0, 0.0, 0.0) for i in range(3)]
    turn = [(0.3 + t, x, y, a) for t, x, y, a in turn_in_place(30.0, 10.0, 31)]  # to 90 deg
    for d in render_drive(Scene(holes=(step_down(edge_x, 0.15),)), QVGA, MOUNT, still + turn):
        r = process(d.frame, MOUNT, params)
        update(state, d.frame.odom, d.frame.timestamp_s, [view_of(r)])
    assert d.pose[2] == pytest.approx(math.pi / 2)
    scan = read_scan(state, d.pose).scan
    world = scan.angles + d.pose[2]
    with np.errstate(divide="ignore"):
        truth = np.where(np.cos(world) > 0.05, edge_x / np.cos(world), np.inf)
    right = np.abs(scan.angles + math.pi / 2) < math.radians(25.0)  # the edge, now on the right
    r = scan.ranges[right]
    assert np.isfinite(r).sum() >= 40
    assert np.isfinite(scan.ranges[_bin(scan, -math.pi / 2)])
    fin = np.isfinite(r)
    np.testing.assert_allclose(r[fin], truth[right][fin], atol=0.05)
    assert not np.isposinf(scan.ranges[truth <= scan.range_max]).any()


def test_blind_radius_and_range_max_follow_the_sensors() -> None:
    state = new_state(MemoryParams())
    assert scan_limits(state) == pytest.approx((0.0, 3.9))  # before any view: the grid's reach
    placed = Mount(0.5, 15.0, 0.0, x_m=0.2)
    _, r = _frame(Scene(), mount=placed, params=StageParams(scan=ScanParams(range_max_m=3.0)))
    update(state, (0.0, 0.0, 0.0), 0.0, [view_of(r, placed)])
    sc = r.level_scan
    near, _ = floor_extent(
        QVGA, MOUNT, sc.angle_min, sc.angle_increment, sc.ranges.size, (0, -1, 1)
    )
    blind, rmax = scan_limits(state)
    # the sensor's dead zone ahead, and a cell's diagonal (the fill marks cells only whole)
    assert blind == pytest.approx(0.2 + float(near[_bin(sc, 0.0)]) + 1.5 * math.sqrt(2) * 0.05)
    assert 0.9 < blind < 1.0 and rmax == 3.0  # its range_max
    assert read_scan(state, (0.0, 0.0, 0.0)).scan.range_max == 3.0
    state.params = MemoryParams(range_max_m=2.0, blind_m=0.3)  # configured: they win
    assert scan_limits(state) == (0.3, 2.0)


def test_memory_params_check_what_the_scan_can_claim() -> None:
    assert MemoryParams().cells == 160 and MemoryParams(size_m=1.1).cells % 8 == 0
    assert MemoryParams().grid_reach_m == pytest.approx(3.9)
    with pytest.raises(ConfigError, match=r"memory\.range_max_m"):
        MemoryParams(range_max_m=4.0)  # past the 8 m grid's reach (3.9 m)
    with pytest.raises(ConfigError, match=r"memory\.blind_m"):
        MemoryParams(blind_m=-0.1)


@pytest.mark.parametrize("told", [False, True])
def test_a_cliff_scan_that_does_not_reach_clears_only_when_told(told: bool) -> None:
    """The cliff scan's NaN on a short bin (its rows do not see the floor out to its range_max)
    hides whether a drop-off lies there; told which of them read floor and no drop-off
    (``cliff_short_free``, with the scan's ``short_free``), the memory clears up to ``far``."""
    params = StageParams(scan=ScanParams(), cliff=DENSE_CLIFF)
    _, empty = _frame(Scene(), params=params)
    sc, cs = empty.level_scan, empty.level_cliff.scan
    n = sc.ranges.size
    near, far = floor_extent(QVGA, MOUNT, sc.angle_min, sc.angle_increment, n, (0, -1, 1))
    cshort = cliff_table(QVGA, MOUNT, DENSE_CLIFF, sc.angle_min, sc.angle_increment, n).short
    short = exact_table(QVGA, MOUNT, SCAN.scan).short_view
    both = np.intersect1d(short, np.flatnonzero(cshort & np.isnan(cs.ranges)))
    i = int(both[np.argmax(np.where(far[both] < 3.0, far[both], 0.0))])
    assert np.isnan(sc.ranges[i]) and np.isnan(cs.ranges[i]) and far[i] > 1.0
    state = new_state(MemoryParams())
    ranges = np.full(n, np.nan, np.float32)
    ranges[i] = (near[i] + far[i]) / 2
    drop = dataclasses.replace(cs, ranges=ranges)
    blank = dataclasses.replace(sc, ranges=np.full(n, np.nan, np.float32))
    update(state, (0.0, 0.0, 0.0), 0.0, [SensorView(MOUNT, QVGA, blank, drop)])
    assert (state.grid == CLIFF).sum() == 1
    view = dataclasses.replace(
        view_of(empty),
        short_free=short[np.isnan(sc.ranges[short])],
        cliff_short_free=np.flatnonzero(cshort & np.isnan(cs.ranges)) if told else None,
    )
    update(state, (0.0, 0.0, 0.0), 0.1, [view])
    assert (state.grid == CLIFF).sum() == (0 if told else 1)
