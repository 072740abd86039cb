"""Seeded random worlds, sensor rigs and drives for the closed-loop safety suite (sim.contract),
built from the scene generator's primitives (synthetic: Box, Hole, wall, table, step_down,
render; drive: straight, turn_in_place, arc, odometry), and the real pipeline run along them.

A :class:`Case` is one seed's world, rig (one or two sensors), trajectory (true poses) and
odometry. :func:`run_case` renders every sensor at every pose and runs what a robot would trust:
``pipeline.process`` per sensor, the merge of two sensors' base scans, the obstacle memory and the
MAVLink OBSTACLE_DISTANCE sectors. The world frame is the odometry frame (the robot starts at the
origin, so exact odometry is the true pose).
"""

from __future__ import annotations

import dataclasses
import itertools
import math
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from depthnav_daemon.daemon.memory_keeper import sensor_view
from depthnav_daemon.pipeline import Result, StageParams, process
from depthnav_daemon.pipeline.geometry import Mount
from depthnav_daemon.pipeline.laser_scan import LaserScan
from depthnav_daemon.pipeline.memory import MemoryParams, new_state, read_scan, update
from depthnav_daemon.pipeline.merge import merge_scans
from depthnav_daemon.pipeline.params import CliffParams, ScanParams
from depthnav_daemon.sim.drive import OdometryNoise, arc, odometry, straight, turn_in_place
from depthnav_daemon.sim.synthetic import (
    Box,
    Hole,
    KinectNoise,
    Scene,
    render,
    sensor_world_pose,
    step_down,
    table,
    wall,
)
from depthnav_daemon.sinks.mavlink.sectors import (
    Sectors,
    memory_sectors,
    merge_cliff,
    obstacle_sectors,
)
from drivers.base import KINECT_V1, Frame, Intrinsics

F64 = npt.NDArray[np.float64]
Pose = tuple[float, float, float]
Rect = tuple[float, float, float, float, float]  # centre x, y, length, width (m), yaw (rad)

SMALL = KINECT_V1.scaled(160, 120)  # the CI suite's camera
QVGA = KINECT_V1.scaled(320, 240)
ROBOT_RADIUS_M = 0.35  # the robot's footprint (its sensors sit within 0.3 m of the base origin)
START_CLEAR_M = 0.5  # nothing this close to the footprint at the start pose
PATH_CLEAR_M = 0.1  # nor this close to it anywhere on the drive
FRAME_DT_S = 0.25
# how often a drive has two sensors (else one), depth noise, odometry errors, a table, a step down;
# a two-sensor rig is front and back (else left and right) half of the time
P_TWO, P_NOISE, P_ODOM, P_TABLE, P_STEP, P_FRONT_BACK = 0.3, 0.3, 0.5, 0.3, 0.4, 0.5


def rect_of(item: Box | Hole) -> Rect:
    """A box's or hole's footprint as (centre x, y, length, width, yaw rad), metres."""
    if isinstance(item, Box):
        return item.x_m, item.y_m, item.length_m, item.width_m, math.radians(item.yaw_deg)
    return (
        (item.x_min_m + item.x_max_m) / 2,
        (item.y_min_m + item.y_max_m) / 2,
        item.x_max_m - item.x_min_m,
        item.y_max_m - item.y_min_m,
        0.0,
    )


def rect_distance(points: F64, rect: Rect) -> F64:
    """Distance (N,) metres from points (N, 2) to a rectangle's footprint (0 inside)."""
    cx, cy, length, width, yaw = rect
    c, s = math.cos(yaw), math.sin(yaw)
    dx, dy = points[:, 0] - cx, points[:, 1] - cy
    lx = np.abs(c * dx + s * dy) - length / 2
    ly = np.abs(-s * dx + c * dy) - width / 2
    return np.hypot(np.maximum(lx, 0.0), np.maximum(ly, 0.0))


def perimeter(rect: Rect, step_m: float) -> F64:
    """Points (N, 2) along a rectangle's outline, about ``step_m`` apart, corners included."""
    cx, cy, length, width, yaw = rect
    hl, hw = length / 2, width / 2
    corners = np.array([[-hl, -hw], [hl, -hw], [hl, hw], [-hl, hw], [-hl, -hw]])
    pts = []
    for a, b in itertools.pairwise(corners):
        k = max(1, math.ceil(float(np.hypot(*(b - a))) / step_m))
        t = np.arange(k)[:, None] / k
        pts.append(a + t * (b - a))
    local = np.concatenate(pts)
    c, s = math.cos(yaw), math.sin(yaw)
    return np.stack(
        [cx + c * local[:, 0] - s * local[:, 1], cy + s * local[:, 0] + c * local[:, 1]], 1
    )


def random_rig(rng: np.random.Generator, two: bool = False) -> tuple[Mount, ...]:
    """One sensor anywhere within 0.3 m of the base origin looking any way, or two (front and
    back, or left and right); heights 0.3-0.9 m, tilt 5-35 deg down, roll within 3 deg."""

    def one(x: float, y: float, yaw: float) -> Mount:
        return Mount(
            float(rng.uniform(0.3, 0.9)),
            float(rng.uniform(5.0, 35.0)),
            float(rng.uniform(-3.0, 3.0)),
            x,
            y,
            float(math.remainder(yaw, 360.0)),
        )

    if not two:
        x, y = rng.uniform(-0.3, 0.3, 2)
        return (one(float(x), float(y), float(rng.uniform(-180.0, 180.0))),)
    a, b = rng.uniform(0.15, 0.3, 2)
    c, d = rng.uniform(-0.1, 0.1, 2)
    e, f = rng.uniform(-20.0, 20.0, 2)
    if rng.random() < P_FRONT_BACK:
        return one(float(a), float(c), float(e)), one(float(-b), float(d), float(180.0 + f))
    return one(float(c), float(a), float(90.0 + e)), one(float(d), float(-b), float(-90.0 + f))


def random_drive(
    rng: np.random.Generator, frames: int = 8
) -> tuple[list[tuple[float, float, float, float]], OdometryNoise | None]:
    """A trajectory of ``frames`` true poses (t_s, x_m, y_m, yaw_rad) from the origin: straight
    runs forward or in reverse, turns in place and arcs, FRAME_DT_S apart; and the odometry's
    errors (None = exact, else a scale error up to 2 % and per-frame noise)."""
    out = [(0.0, 0.0, 0.0, 0.0)]
    while len(out) < frames:
        n = int(min(rng.integers(2, 6), frames - len(out))) + 1
        kind = rng.choice(["straight", "reverse", "turn", "arc"], p=[0.4, 0.15, 0.2, 0.25])
        start = out[-1][1:]
        if kind == "straight":
            seg = straight(rng.uniform(0.4, 1.0), 1 / FRAME_DT_S, n, start)
        elif kind == "reverse":
            seg = straight(-rng.uniform(0.2, 0.5), 1 / FRAME_DT_S, n, start)
        elif kind == "turn":
            seg = turn_in_place(
                rng.choice([-1, 1]) * rng.uniform(40, 120), 1 / FRAME_DT_S, n, start
            )
        else:
            rate = rng.choice([-1, 1]) * rng.uniform(20, 60)
            seg = arc(rng.uniform(0.3, 0.8), rate, 1 / FRAME_DT_S, n, start)
        t0 = out[-1][0]
        out.extend((t0 + t, x, y, a) for t, x, y, a in seg[1:])
    noise = None
    if rng.random() < P_ODOM:
        noise = OdometryNoise(float(rng.uniform(-0.02, 0.02)), 0.003, math.radians(0.3))
    return out, noise


def _fits(
    rect: Rect, taken: list[Rect], poses: F64, gap_m: float = 0.1, start_m: float = START_CLEAR_M
) -> bool:
    """Whether a footprint keeps clear of the robot along the drive and of the other things."""
    if rect_distance(poses[:1], rect)[0] < ROBOT_RADIUS_M + start_m:
        return False
    if rect_distance(poses, rect).min() < ROBOT_RADIUS_M + PATH_CLEAR_M:
        return False
    mine = perimeter(rect, 0.05)
    for other in taken:
        if rect_distance(mine, other).min() < gap_m:
            return False
        if rect_distance(perimeter(other, 0.05), rect).min() < gap_m:
            return False
    return True


def random_world(
    rng: np.random.Generator, keep_clear: Sequence[Pose] = ((0.0, 0.0, 0.0),)
) -> Scene:
    """Boxes, walls, a table, steps down and holes around the poses ``keep_clear`` (the drive;
    the first is the start): nothing within START_CLEAR_M of the robot's footprint at the start,
    nor within PATH_CLEAR_M of it along the drive; some boxes placed just beside the path."""
    poses = np.array([p[:2] for p in keep_clear], dtype=np.float64)
    yaws = [p[2] for p in keep_clear]
    boxes: list[Box] = []
    holes: list[Hole] = []
    taken: list[Rect] = []

    def near_path(lo: float, hi: float, beside: bool = False) -> tuple[float, float]:
        i = int(rng.integers(len(poses)))
        a = (
            yaws[i] + rng.choice([-1, 1]) * math.pi / 2
            if beside
            else rng.uniform(-math.pi, math.pi)
        )
        d = rng.uniform(lo, hi)
        return float(poses[i, 0] + d * math.cos(a)), float(poses[i, 1] + d * math.sin(a))

    def place(make: Callable[[], Box | Hole], tries: int = 30) -> None:
        for _ in range(tries):
            item = make()
            rect = rect_of(item)
            if _fits(rect, taken, poses):
                taken.append(rect)
                (boxes if isinstance(item, Box) else holes).append(item)
                return

    def box(beside: bool) -> Box:
        x, y = near_path(0.7, 1.4) if beside else near_path(0.8, 4.5)
        size = rng.uniform(0.12, 0.8, 2)
        top = float(rng.uniform(0.15, 1.2))
        return Box(x, y, float(size[0]), float(size[1]), top, yaw_deg=float(rng.uniform(0, 90)))

    def a_wall() -> Box:
        x, y = near_path(1.5, 5.0)
        w = wall(0.0, float(rng.uniform(0.8, 2.5)), 0.1, float(rng.uniform(1.0, 3.0)))
        return dataclasses.replace(w, x_m=x, y_m=y, yaw_deg=float(rng.uniform(-90, 90)))

    def a_table() -> Box:
        x, y = near_path(1.0, 3.5)
        size = rng.uniform(0.5, 1.2, 2)
        return dataclasses.replace(
            table(x, y, float(size[0]), float(size[1]), float(rng.uniform(0.5, 0.8)), 0.04),
            yaw_deg=float(rng.uniform(0, 90)),
        )

    def a_step() -> Hole:  # a step down across one of the world's axes
        x, y = near_path(1.0, 4.0)
        s = step_down(0.0, float(rng.uniform(0.1, 0.4)), float(rng.uniform(1.5, 4.0)), 4.0)
        axis = int(rng.integers(4))
        x0, x1, y0, y1 = (s.x_min_m, s.x_max_m, s.y_min_m, s.y_max_m)
        ext = [(x0, x1, y0, y1), (-x1, -x0, y0, y1), (y0, y1, x0, x1), (y0, y1, -x1, -x0)][axis]
        return Hole(x + ext[0], x + ext[1], y + ext[2], y + ext[3], s.depth_m)

    def a_hole() -> Hole:
        x, y = near_path(0.8, 4.0)
        w, d = rng.uniform(0.3, 1.0, 2)
        return Hole(x - w / 2, x + w / 2, y - d / 2, y + d / 2, float(rng.uniform(0.1, 0.5)))

    for _ in range(int(rng.integers(1, 3))):
        place(lambda: box(True))
    for _ in range(int(rng.integers(2, 5))):
        place(lambda: box(False))
    for _ in range(int(rng.integers(0, 3))):
        place(a_wall)
    if rng.random() < P_TABLE:
        place(a_table)
    if rng.random() < P_STEP:
        place(a_step)
    for _ in range(int(rng.integers(0, 2))):
        place(a_hole)
    return Scene(boxes=tuple(boxes), holes=tuple(holes))


def _corners(rect: Rect) -> F64:
    cx, cy, length, width, yaw = rect
    c, s = math.cos(yaw), math.sin(yaw)
    loc = np.array([[1, 1], [1, -1], [-1, 1], [-1, -1]]) * [length / 2, width / 2]
    return np.stack([cx + c * loc[:, 0] - s * loc[:, 1], cy + s * loc[:, 0] + c * loc[:, 1]], 1)


def view_scene(scene: Scene, intr: Intrinsics, mount: Mount, pose: Pose) -> Scene:
    """``scene`` without the boxes and holes no ray of this camera can reach (outside the bearings
    of its image's corner rays, with 3 deg to spare): the same image, rendered faster."""
    t, r = mount.tilt_rad, mount.roll_rad
    u = np.array([-0.5, intr.width - 0.5, -0.5, intr.width - 0.5])
    v = np.array([-0.5, -0.5, intr.height - 0.5, intr.height - 0.5])
    xn, yn = (u - intr.cx) / intr.fx, (v - intr.cy) / intr.fy
    # level-frame direction of (right xn, down yn, forward 1): see contract.Camera
    fwd = -xn * math.sin(r) * math.sin(t) - yn * math.cos(r) * math.sin(t) + math.cos(t)
    left = -xn * math.cos(r) + yn * math.sin(r)
    b = np.arctan2(left, fwd)
    lo, hi = float(b.min()) - math.radians(3), float(b.max()) + math.radians(3)
    sx, sy, syaw = sensor_world_pose(mount, pose)

    def seen(item: Box | Hole) -> bool:
        rect = rect_of(item)
        if rect_distance(np.array([[sx, sy]]), rect)[0] == 0.0:
            return True
        c = _corners(rect)
        mid = math.atan2(rect[1] - sy, rect[0] - sx)
        rel = np.remainder(np.arctan2(c[:, 1] - sy, c[:, 0] - sx) - mid + math.pi, 2 * math.pi)
        a, z = float(rel.min()) - math.pi, float(rel.max()) - math.pi
        gap = math.remainder(mid - syaw + (a + z) / 2 - (lo + hi) / 2, 2 * math.pi)
        return abs(gap) <= (z - a) / 2 + (hi - lo) / 2

    return Scene(
        boxes=tuple(bx for bx in scene.boxes if seen(bx)),
        holes=tuple(h for h in scene.holes if seen(h)),
        floor=scene.floor,
    )


@dataclass(frozen=True, slots=True)
class Case:
    """One seed's drive: world, rig, true poses, odometry and the camera."""

    seed: int
    scene: Scene
    rig: tuple[Mount, ...]
    trajectory: tuple[tuple[float, float, float, float], ...]
    odom: tuple[Pose, ...]
    intr: Intrinsics
    depth_noise: KinectNoise | None
    odom_noise: OdometryNoise | None


def random_case(seed: int, frames: int = 8, intr: Intrinsics = SMALL) -> Case:
    """The case of a seed: a rig (two sensors in 3 of 10), a drive, a world kept clear of it,
    Kinect-like depth noise in 3 of 10 and odometry errors in half of the drives."""
    rng = np.random.default_rng(seed)
    rig = random_rig(rng, two=bool(rng.random() < P_TWO))
    traj, odom_noise = random_drive(rng, frames)
    scene = random_world(rng, [p[1:] for p in traj])
    noise = KinectNoise() if rng.random() < P_NOISE else None
    odom = odometry([p[1:] for p in traj], odom_noise, rng)
    return Case(seed, scene, rig, tuple(traj), tuple(odom), intr, noise, odom_noise)


def suite_params(intr: Intrinsics) -> StageParams:
    """The shipped defaults, the cliff detector's pixel sizes scaled to the image width (the
    defaults are for 640 pixels)."""
    k = intr.width / 640.0
    step = max(1, round(8 * k))
    cliff = CliffParams(
        used_depth_height=max(1, round(400 * k)),
        block_size=max(2, round(16 * k)),
        row_step=step,
        col_step=step,
        block_points_thresh=3,
    )
    return StageParams(scan=ScanParams(), cliff=cliff)


@dataclass(frozen=True, slots=True)
class Step:
    """What the robot gets at one pose of a drive.

    Attributes:
        pose, odom: the true pose and the odometry's, (x_m, y_m, yaw_rad).
        results: one pipeline Result per sensor (level and base-frame scans, cliff).
        scan, cliff: the robot's base-frame scans (the merge with two sensors), REP 117.
        memory: the 360 deg memory scan after this frame.
        sectors: the live OBSTACLE_DISTANCE payload (obstacles with drop-offs folded in).
        memory_sectors: the payload from the memory scan.
    """

    index: int
    pose: Pose
    odom: Pose
    results: tuple[Result, ...]
    scan: LaserScan
    cliff: LaserScan | None
    memory: LaserScan
    sectors: Sectors
    memory_sectors: Sectors


def run_case(
    case: Case, params: StageParams | None = None, memory: MemoryParams | None = None
) -> Iterator[Step]:
    """Render every sensor at every pose of ``case`` and run the pipeline on it (module
    docstring); depth noise draws from a generator seeded with the case's seed."""
    params = params or suite_params(case.intr)
    state = new_state(memory or MemoryParams())
    rng = np.random.default_rng([case.seed, 1])
    for i, (t, x, y, yaw) in enumerate(case.trajectory):
        pose = (x, y, yaw)
        results = []
        for m in case.rig:
            scene = view_scene(case.scene, case.intr, m, pose)
            view = render(scene, case.intr, m, case.depth_noise, rng, robot_pose=pose)
            frame = Frame(i, t, view.depth_mm, case.intr, odom=case.odom[i])
            results.append(process(frame, m, params))
        scans = [r.scan for r in results]
        cliffs = [r.cliff.scan for r in results if r.cliff is not None]
        scan = scans[0] if len(scans) == 1 else merge_scans(scans)
        cliff = None if not cliffs else cliffs[0] if len(cliffs) == 1 else merge_scans(cliffs)
        update(state, case.odom[i], t, [sensor_view(r, params) for r in results])
        mread = read_scan(state, case.odom[i])
        mem = mread.scan
        sectors = obstacle_sectors(scan)
        if cliff is not None:
            sectors = merge_cliff(sectors, cliff)
        yield Step(
            i,
            pose,
            case.odom[i],
            tuple(results),
            scan,
            cliff,
            mem,
            sectors,
            memory_sectors(mem, hidden=mread.hidden),
        )
