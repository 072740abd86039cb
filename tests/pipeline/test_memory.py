"""The obstacle memory through the real stages on synthetic drives (sim.drive): a step down kept in
the dead zone, a box kept behind the robot until it leaves the grid, a removed box cleared, a turn
in place that keeps every cell where it belongs.

The synthetic world is the odometry frame: the robot starts at the world origin, so exact odometry
is the true pose.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from depthnav_daemon.pipeline import Result, StageParams, process
from depthnav_daemon.pipeline.cliff import CliffParams
from depthnav_daemon.pipeline.geometry import Mount
from depthnav_daemon.pipeline.memory import (
    MemoryParams,
    MemoryState,
    SensorView,
    new_state,
    read_scan,
    snapshot,
    update,
)
from depthnav_daemon.pipeline.memory_kernels import CLIFF, OBSTACLE
from depthnav_daemon.pipeline.scan import ScanParams
from depthnav_daemon.sim.drive import (
    OdometryNoise,
    odometry,
    render_drive,
    straight,
    turn_in_place,
)
from depthnav_daemon.sim.synthetic import Box, Scene, step_down, truth_obstacle_interval
from drivers.base import KINECT_V1

MOUNT = Mount(0.5, 15.0, 0.0)  # the sensor: 0.5 m high, 15 deg down
# one sample per pixel, a block counts from one row of drop-off samples: the edge to a pixel row
DENSE_CLIFF = CliffParams(block_size=8, row_step=1, col_step=1, block_points_thresh=8)
PARAMS = StageParams(scan=ScanParams(), cliff=DENSE_CLIFF)
QVGA = KINECT_V1.scaled(320, 240)
STEP_M = 3.0
SPEED_MPS, FPS = 0.3, 10.0


def view_of(result: Result, mount: Mount = MOUNT) -> SensorView:
    cliff = result.level_cliff
    return SensorView(
        mount,
        result.intrinsics,
        result.level_scan,
        None if cliff is None else cliff.scan,
        cliff_margin_rows=DENSE_CLIFF.block_size + DENSE_CLIFF.row_step,
    )


def ahead(state: MemoryState, pose) -> float:
    """memory.scan straight ahead (the bin centred on bearing 0)."""
    scan = read_scan(state, pose).scan
    return float(scan.ranges[int(np.argmin(np.abs(scan.angles)))])


@pytest.fixture(scope="module")
def step_drive():
    """0.3 m/s toward a 15 cm step 3 m ahead, 10 frames/s, until 0.24 m from it (VGA, exact
    depth): (true poses, results)."""
    n = int((STEP_M - 0.24) / (SPEED_MPS / FPS)) + 1
    scene = Scene(holes=(step_down(STEP_M, 0.15),))
    poses, results = [], []
    for d in render_drive(scene, KINECT_V1, MOUNT, straight(SPEED_MPS, FPS, n)):
        poses.append(d.pose)
        results.append(process(d.frame, MOUNT, PARAMS))
    return poses, results


def _drive_errors(step_drive, odom_noise: OdometryNoise | None) -> tuple[np.ndarray, np.ndarray]:
    """(memory error, live cliff scan error) straight ahead per frame, metres."""
    poses, results = step_drive
    odom = odometry(poses, odom_noise)
    state = new_state(MemoryParams())
    mem, live = [], []
    for pose, o, r in zip(poses, odom, results, strict=True):
        truth = STEP_M - pose[0]
        if truth < 0.25:
            break
        update(state, o, r.timestamp_s, [view_of(r)])
        mem.append(ahead(state, o) - truth)
        cs = r.cliff.scan
        live.append(float(cs.ranges[int(np.argmin(np.abs(cs.angles)))]) - truth)
    return np.array(mem), np.array(live)


def test_step_edge_is_kept_through_the_dead_zone_with_exact_odometry(step_drive) -> None:
    mem, live = _drive_errors(step_drive, None)
    assert len(mem) >= 90
    assert np.abs(mem).max() <= 0.05, np.abs(mem).argmax()
    # the live cliff scan loses the edge once it is in the lower dead zone (eq. 15: the floor is
    # seen from 0.5 / tan(15 + 21.9 deg) = 0.67 m on), for the last ~14 frames at 3 cm a frame
    lost = ~(np.abs(live) <= 0.05)
    assert lost.sum() >= 10 and lost[-10:].all()
    assert np.abs(mem[lost]).max() <= 0.05


@pytest.mark.parametrize("scale_error", [0.02, -0.02])
def test_step_edge_with_2_percent_odometry_scale_error(step_drive, scale_error: float) -> None:
    mem, _ = _drive_errors(step_drive, OdometryNoise(scale_error=scale_error))
    assert np.abs(mem).max() <= 0.10


def _box_points(state: MemoryState, kind: int) -> np.ndarray:
    """(K, 2) remembered points of one kind in the odometry frame."""
    snap = snapshot(state)
    n = snap.grid.shape[0]
    ix, iy = np.nonzero(snap.grid == kind)
    # the snapshot is in window order; offsets are stored at the toroidal index
    gx, gy = ix + state.wx0, iy + state.wy0
    ox = state.offx[gx % n, gy % n]
    oy = state.offy[gx % n, gy % n]
    return np.stack([gx * snap.cell_m + ox, gy * snap.cell_m + oy], axis=-1)


def _dist_to_box(pts: np.ndarray, box: Box) -> np.ndarray:
    """Distance of points to an axis-aligned box footprint (0 inside)."""
    dx = np.maximum(np.abs(pts[:, 0] - box.x_m) - box.length_m / 2, 0)
    dy = np.maximum(np.abs(pts[:, 1] - box.y_m) - box.width_m / 2, 0)
    return np.hypot(dx, dy)


def test_box_passed_on_the_left_stays_behind_until_it_leaves_the_scan() -> None:
    box = Box(1.5, 0.75, 0.3, 0.3, 0.5)
    params = MemoryParams()  # 8 x 8 m: a point leaves 4 m behind the robot (to a cell)
    state = new_state(params)
    behind = []
    for d in render_drive(Scene(boxes=(box,)), QVGA, MOUNT, straight(0.15, 1.0, 48)):
        r = process(d.frame, MOUNT, StageParams(scan=ScanParams()))
        update(state, d.frame.odom, d.frame.timestamp_s, [view_of(r)])
        pts = _box_points(state, OBSTACLE)
        x = d.pose[0]
        if x < 1.0:
            continue
        # every remembered point is on the box
        assert len(pts) == 0 or _dist_to_box(pts, box).max() <= params.cell_m
        read = read_scan(state, d.frame.odom)
        scan, hidden = read.scan, read.hidden
        assert hidden is not None
        rel = pts - np.array(d.pose[:2])
        dist = np.hypot(rel[:, 0], rel[:, 1])
        if len(pts) and dist.min() <= scan.range_max - params.cell_m:
            # within the memory scan's range_max: it shows the nearest point on its bearing,
            # unless a face it saw beside that point but did not keep lies in front of it from
            # here (the box's side, seen at a grazing angle): then that bearing is unknown
            k = int(np.argmin(dist))
            b = math.atan2(rel[k, 1], rel[k, 0])
            j = int(np.floor((b - scan.angle_min) / scan.angle_increment + 0.5)) % scan.ranges.size
            assert hidden[j] or scan.ranges[j] == pytest.approx(dist[k], abs=1e-3)
            assert np.isnan(scan.ranges[hidden]).all()
            fin = np.isfinite(scan.ranges)
            near = float(scan.ranges[fin].min()) if fin.any() else np.inf
            assert near >= dist.min() - 1e-3  # never nearer than what it keeps
            behind.append(x > 1.7 and near <= dist.min() + params.cell_m)
        else:
            # beyond range_max (3.9 m here) nothing is reported: the scan does not reach it
            assert not np.isfinite(scan.ranges).any()
        if x > 1.5 + params.size_m / 2 + params.cell_m:
            assert len(pts) == 0  # it left the grid
    assert sum(behind) >= 20  # remembered behind the robot for many frames
    assert len(_box_points(state, OBSTACLE)) == 0  # and gone at the end (x = 7.05)


def test_removed_box_is_cleared_within_a_frame_of_seeing_floor() -> None:
    box = Box(1.8, -0.25, 0.3, 0.3, 0.4)
    scenes = [Scene(boxes=(box,))] * 3 + [Scene()] * 2
    state = new_state(MemoryParams())
    counts = []
    for d in render_drive(scenes, QVGA, MOUNT, straight(0.0, 10.0, 5)):
        r = process(d.frame, MOUNT, StageParams(scan=ScanParams()))
        update(state, d.frame.odom, d.frame.timestamp_s, [view_of(r)])
        counts.append(read_scan(state, d.frame.odom).obstacle_cells)
    assert min(counts[:3]) > 3
    assert counts[3] == 0 and counts[4] == 0  # the first frame that sees floor there clears it


def test_turn_in_place_keeps_every_cell_at_its_true_place() -> None:
    boxes = tuple(
        Box(r * math.cos(math.radians(a)), r * math.sin(math.radians(a)), 0.3, 0.3, 0.5)
        for r, a in ((1.5, 0), (1.2, 70), (2.0, 150), (1.6, 215), (2.4, 290))
    )
    state = new_state(MemoryParams())
    seen = set()
    for d in render_drive(Scene(boxes=boxes), QVGA, MOUNT, turn_in_place(15.0, 1.0, 25)):
        r = process(d.frame, MOUNT, StageParams(scan=ScanParams()))
        update(state, d.frame.odom, d.frame.timestamp_s, [view_of(r)])
        pts = _box_points(state, OBSTACLE)
        dist = np.min([_dist_to_box(pts, b) for b in boxes], axis=0)
        assert dist.max() <= state.params.cell_m  # within one cell of a box, every frame
        seen |= {int(np.argmin([_dist_to_box(p[None], b)[0] for b in boxes])) for p in pts}
    assert seen == set(range(len(boxes)))  # all five are remembered after the full turn
    # memory.scan from the final pose: every finite bin is a true range over its footprint (the
    # bin, and the half cell a remembered point covers; the boxes are >= 1.05 m away)
    pose = d.frame.odom
    scan = read_scan(state, pose).scan
    half = scan.angle_increment / 2 + math.atan(state.params.cell_m / 2 / 1.05)
    lo, hi = truth_obstacle_interval(Scene(boxes=boxes), scan.angles + pose[2], half, 0.05, 2.0)
    fin = np.isfinite(scan.ranges)
    assert fin.sum() >= 20 and np.isfinite(lo[fin]).all()
    assert np.all(scan.ranges[fin] >= lo[fin] - 0.01)
    assert np.all(scan.ranges[fin] <= np.minimum(hi[fin], 9.0) + 0.01)


def test_max_age_forgets_what_is_not_seen_again() -> None:
    box = Box(1.8, 0.0, 0.3, 0.3, 0.4)
    state = new_state(MemoryParams(max_age_s=1.0))
    frames = list(render_drive(Scene(boxes=(box,)), QVGA, MOUNT, turn_in_place(0.0, 2.0, 1)))
    r = process(frames[0].frame, MOUNT, StageParams(scan=ScanParams()))
    update(state, (0.0, 0.0, 0.0), 0.0, [view_of(r)])
    assert read_scan(state, (0.0, 0.0, 0.0)).obstacle_cells > 0
    update(state, (0.0, 0.0, 0.0), 0.9, [])  # nothing seen: kept for now
    assert read_scan(state, (0.0, 0.0, 0.0)).obstacle_cells > 0
    update(state, (0.0, 0.0, 0.0), 1.1, [])
    assert read_scan(state, (0.0, 0.0, 0.0)).obstacle_cells == 0


def test_drop_off_cells_are_marked_as_cliff(step_drive) -> None:
    poses, results = step_drive
    state = new_state(MemoryParams())
    update(state, poses[0], 0.0, [view_of(results[0])])
    pts = _box_points(state, CLIFF)
    # where the cliff stage puts the edge (a little short of it: the safe side), none nearer
    cs = results[0].cliff.scan
    edge_x = float(np.nanmin(cs.ranges * np.cos(cs.angles)))
    assert STEP_M - 0.05 <= edge_x <= STEP_M
    assert len(pts) > 20 and pts[:, 0].min() >= edge_x - 1e-3
    assert len(_box_points(state, OBSTACLE)) == 0


def test_a_sensor_placed_on_the_robot_marks_the_world_where_it_looks() -> None:
    # the sensor looks left (yaw 90 deg) from (0.2, 0.1) on a robot at (1, 2) heading 30 deg:
    # it looks along 120 deg in the world; a box there must be remembered where it is
    mount = Mount(0.5, 15.0, 0.0, x_m=0.2, y_m=0.1, yaw_deg=90.0)
    pose = (1.0, 2.0, math.radians(30.0))
    sx = 1.0 + 0.2 * math.cos(pose[2]) - 0.1 * math.sin(pose[2])
    sy = 2.0 + 0.2 * math.sin(pose[2]) + 0.1 * math.cos(pose[2])
    box = Box(
        sx + 1.8 * math.cos(math.radians(120)),
        sy + 1.8 * math.sin(math.radians(120)),
        0.3,
        0.3,
        0.5,
    )
    state = new_state(MemoryParams())
    (d,) = render_drive(Scene(boxes=(box,)), QVGA, mount, [(0.0, *pose)])
    r = process(d.frame, mount, StageParams(scan=ScanParams()))
    update(state, d.frame.odom, 0.0, [view_of(r, mount)])
    pts = _box_points(state, OBSTACLE)
    assert len(pts) > 3 and _dist_to_box(pts, box).max() <= state.params.cell_m
    # read back from the robot: in the base frame the box centre is at (0.2, 0.1) + 1.8 (0, 1),
    # bearing atan2(1.9, 0.2) = 84 deg on the robot's left, 1.91 m away (its near face ~0.15 m
    # nearer)
    scan = read_scan(state, pose).scan
    j = int(np.nanargmin(scan.ranges))
    assert abs(math.degrees(scan.angles[j]) - 84.0) < 5.0
    assert scan.ranges[j] == pytest.approx(math.hypot(1.9, 0.2) - 0.15, abs=0.05)


@pytest.mark.parametrize(
    "pose",
    [
        (1e19, 0.0, 0.0),
        (1e308, 0.0, 0.0),
        (0.0, math.nan, 0.0),
        (0.0, 0.0, math.inf),
        (10**400, 0, 0),
    ],
    ids=["1e19", "1e308", "nan", "inf-yaw", "400-digit"],
)
def test_a_pose_outside_the_odometry_limits_leaves_the_memory_as_it_is(step_drive, pose) -> None:
    """The memory's own guard (the daemon checks first): no OverflowError in the window's
    recentring, no numba TypingError, nothing changed; read back as unknown (NaN)."""
    _poses, results = step_drive
    state = new_state(MemoryParams())
    update(state, (0.0, 0.0, 0.0), 0.0, [view_of(results[0])])
    before = (state.grid.copy(), state.wx0, state.wy0, state.updates)
    report = update(state, pose, 0.1, [view_of(results[1])])
    assert report.refused is not None
    assert "beyond" in report.refused or "not finite" in report.refused
    assert (report.cleared, report.marked) == (0, 0)
    assert np.array_equal(state.grid, before[0])
    assert (state.wx0, state.wy0, state.updates) == before[1:]
    read = read_scan(state, pose)
    assert np.isnan(read.scan.ranges).all()
    good = read_scan(state, (0.0, 0.0, 0.0))
    assert (read.obstacle_cells, read.cliff_cells) == (good.obstacle_cells, good.cliff_cells)
    assert good.cliff_cells > 0


@pytest.mark.parametrize("offset_m", [9.9e6, -9.9e6])
def test_poses_near_the_odometry_limit_remember_as_poses_near_the_origin(
    step_drive, offset_m: float
) -> None:
    """The limits are what the memory handles: the same drive with its odometry frame moved to
    9,900 km away (a UTM-sized coordinate) reads back the same memory scan, to 1 mm."""
    poses, results = step_drive
    near, far = new_state(MemoryParams()), new_state(MemoryParams())
    for k, (pose, r) in enumerate(zip(poses, results, strict=True)):
        t = 0.1 * k
        update(near, pose, t, [view_of(r)])
        update(far, (pose[0] + offset_m, pose[1] - offset_m, pose[2]), t, [view_of(r)])
    last = poses[-1]
    a = read_scan(near, last).scan.ranges
    b = read_scan(far, (last[0] + offset_m, last[1] - offset_m, last[2])).scan.ranges
    assert np.isfinite(a).sum() > 10
    np.testing.assert_allclose(b, a, atol=1e-3, equal_nan=True)
