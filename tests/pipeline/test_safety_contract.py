"""The closed-loop safety suite (issue 31 item 7): seeded random worlds, rigs and drives through the
real pipeline, every output judged against the truth of the scene's geometry (sim.contract states
the contract and how it is read, sim.visibility the truth, sim.worlds the worlds and drives).

How the contract is read (the lead's decisions; sim.contract's docstring has them in full):
1. Bearing resolution is one bin: a finite r on bin j is unsafe only if r > truth_j + err and
   neither neighbour bin (j - 1, j + 1) of the same output holds a finite value <= truth_j + err
   (memory and sectors alike; one sector); such bins are counted ``beside``, not unsafe. The
   same for +inf: a +inf bin whose claimed truth a neighbour reports (finite <= truth + err, or
   -inf) is ``beside`` (the table's "(held)"), not unsafe.
2. +inf on a live output is unsafe if an obstacle or drop-off edge within range_max, outside the
   lower dead zone, is in view, or its floor point projects into the rows/cols the stage reads,
   or (base-frame and merged outputs) no sensor's view covered it. Not unsafe, reported apart:
   ``overhang`` (a table top above the view's top edge over floor that is seen) and
   ``below_resolution`` (a drop-off shorter along the ray than a cliff block plus a stride).
3. +inf on the memory is unsafe if anything lies on the bin within its range_max, except table
   tops never seen (``overhang``) and what lies nearer the base origin than the memory's
   ``blind_m`` (the disc it does not judge; counted ``blind``); a table top seen before and read
   +inf later is counted as ``overhang_cleared``, asserted to stay 0 (it was 0 on every drive here
   when this was written).
-inf only with something within range_min + 5 cm: asserted for the level outputs; reported only
for base_scan and merged_scan (a sensor's -inf stays -inf in the base frame, where its obstacle
may lie up to the sensor's offset beyond the base range_min). Every output is held at 0 unsafe
bins on the CI drives. A side seen edge-on (no row of pixel centres crosses it twice) is below
pixel resolution: not in the finite truth, a range beyond it counted ``subpixel``. The CI part
judges 200 drives of 8 frames at 160x120 (about a minute); ``-m slow`` runs 1000 more and 100 at
320x240. Coverage floors (share of the bins with a visible truth whose output is within the
stated error) are the figures measured when the suite was written, minus a margin: a stage
returning NaN everywhere is safe but useless.
"""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest

from depthnav_daemon.pipeline import process
from depthnav_daemon.pipeline.geometry import Mount
from depthnav_daemon.pipeline.laser_scan import LaserScan
from depthnav_daemon.sim.contract import (
    OUTPUTS,
    Counts,
    base_claims,
    judge,
    judge_drive,
    live_claims,
    memory_claims,
    run_suite,
    table,
)
from depthnav_daemon.sim.drive import odometry, straight, turn_in_place
from depthnav_daemon.sim.synthetic import Box, Hole, Scene, render, step_down
from depthnav_daemon.sim.synthetic import table as table_top
from depthnav_daemon.sim.visibility import (
    Boundary,
    Camera,
    Claims,
    Sight,
    Truth,
    boundary,
    sight,
    truth,
)
from depthnav_daemon.sim.worlds import (
    ROBOT_RADIUS_M,
    SMALL,
    START_CLEAR_M,
    Case,
    random_case,
    rect_distance,
    rect_of,
    run_case,
    suite_params,
    view_scene,
)
from drivers.base import KINECT_V1, Frame

CI_DRIVES, FRAMES = 200, 8
# coverage measured on the CI drives when the suite was written: before the issue 31 fixes level
# 98.8 %, base 94.0 %, merged 94.2 %, cliffs 38.6-54.2 %, sectors 81.2 %, memory 83.2 %; with the
# first cliff and memory fixes level 99.1 %, base 94.5 %, merged 94.5 %, cliffs 79.8-87.1 %,
# sectors 88.3 %, memory 86.7-87.4 %. The floors keep a margin below the latter.
COVERAGE_FLOOR = {
    "level_scan": 0.95,
    "base_scan": 0.90,
    "merged_scan": 0.90,
    "level_cliff": 0.70,
    "base_cliff": 0.70,
    "merged_cliff": 0.70,
    "sectors": 0.80,
    "memory": 0.80,
    "memory_sectors": 0.80,
}


# false too-close reported, not asserted, in the base frame (the sectors are the base scan's)
BASE_FRAME_TOO_CLOSE = ("base_scan", "merged_scan", "sectors")


def report(totals: dict[str, Counts], name: str) -> str:
    c = totals[name]
    return f"{name}: unsafe in the drives below\n{table(totals)}\n" + "\n".join(c.examples)


@pytest.fixture(scope="module")
def suite() -> dict[str, Counts]:
    return run_suite(range(CI_DRIVES), FRAMES)


# the truth's own conventions, pinned against the renderer ----------------------------------------


def test_the_contract_camera_projects_the_renderers_hits_back_onto_their_pixels() -> None:
    # asymmetric on purpose: a placed, yawed, tilted and rolled sensor on a turned robot
    intr = KINECT_V1.scaled(160, 120)
    mount = Mount(0.6, 22.0, 4.0, x_m=0.2, y_m=-0.1, yaw_deg=30.0)
    pose = (1.0, -0.5, 0.4)
    scene = Scene(boxes=(Box(3.0, 1.2, 0.5, 0.4, 0.9, yaw_deg=20.0),))
    view = render(scene, intr, mount, robot_pose=pose)
    cam = Camera.at(mount, intr, pose)
    hit = np.isfinite(view.depth_true_m)
    pts = view.points_m[hit]
    (xa, xb), (ya, yb), (za, zb) = cam.linear(pts[:, :2])
    x, y, z = xa + xb * pts[:, 2], ya + yb * pts[:, 2], za + zb * pts[:, 2]
    v, u = np.nonzero(hit)
    np.testing.assert_allclose(intr.fx * x / z + intr.cx, u, atol=1e-6)
    np.testing.assert_allclose(intr.fy * y / z + intr.cy, v, atol=1e-6)
    np.testing.assert_allclose(z, view.depth_true_m[hit], rtol=1e-9)


def test_a_box_in_view_is_visible_and_one_behind_it_is_hidden() -> None:
    mount = Mount(0.5, 15.0)
    front = Box(2.0, 0.0, 0.3, 0.6, 1.0)
    behind = Box(3.0, 0.0, 0.2, 0.2, 0.4)  # lower than the front box's shadow
    scene = Scene(boxes=(front, behind))
    sp = suite_params(SMALL)
    assert sp.cliff is not None
    bd = boundary(scene, sp.scan)
    s = sight(bd, scene, Camera.at(mount, SMALL, (0.0, 0.0, 0.0)), sp.scan, sp.cliff)
    near_face = (bd.owner == 0) & (np.abs(bd.xy[:, 0] - 1.85) < 1e-9)
    assert s.visible[near_face].all() and not s.visible[bd.owner == 1].any()
    assert s.claim[bd.owner == 1].all()  # hidden, but +inf there would still be a lie


def test_a_side_seen_edge_on_is_below_pixel_resolution_and_judged_apart() -> None:
    mount = Mount(0.5, 15.0)
    # the left side (y = -1 mm) of the first box lies along the camera's forward ray, seen from
    # its outside within 0.01 deg: edge-on; the second box, turned 8 deg, shows its side over
    # several columns of every row that sees it
    edge_on = Box(1.5, -0.201, 0.6, 0.4, 0.5)
    turned = Box(1.6, 1.0, 0.6, 0.4, 0.5, yaw_deg=-8.0)
    scene = Scene(boxes=(edge_on, turned))
    bd, s = _one_sensor(scene, mount)
    for k in (0, 1):  # each sample knows the two corners of its side: four sides a box
        assert len(np.unique(bd.side[bd.owner == k].reshape(-1, 4), axis=0)) == 4
    side = (bd.owner == 0) & (np.abs(bd.xy[:, 1] + 0.001) < 1e-9)
    inner = side & (bd.xy[:, 0] > 1.2 + 1e-6) & (bd.xy[:, 0] < 1.8 - 1e-6)
    assert s.subpixel[inner].all() and not s.visible[inner].any()
    assert not s.subpixel[~inner].any()  # its corners, its front face and the turned box
    front = (bd.owner == 0) & (np.abs(bd.xy[:, 0] - 1.2) < 1e-9)
    assert s.visible[front].all() and s.visible[(bd.owner == 1) & ~bd.edge].any()
    assert s.claim[inner].all()  # +inf over it is still unsafe
    # the judge: a range beyond such a side is counted apart, not unsafe; nearer is fine
    # (binned from beside the side, where it spans many bins: as from an off-centre base)
    layout = (-0.6, 0.02, 61)
    t = truth(bd, live_claims(s), (1.5, 0.5, -math.pi / 2), layout, ~bd.edge)
    assert t.subpixel is not None
    j = 40  # bearing 0.2 rad: the side 0.55 m away, nothing else
    r = np.full(61, np.nan)
    r[j] = t.subpixel[j] + 0.3
    assert np.isinf(np.minimum(t.visible, t.visible_edge)[j])  # only the side is on bin j
    c = judge(r, 0.4, 5.0, t, np.full(61, 0.02), err_subpixel=np.full(61, 0.02))
    assert (c.unsafe_far, c.subpixel) == (0, 1)
    r[j] = t.subpixel[j]
    assert judge(r, 0.4, 5.0, t, np.full(61, 0.02)).subpixel == 0


def test_view_scene_leaves_the_image_as_it_is() -> None:
    for seed in range(6):
        case = random_case(seed, 3)
        for (_, x, y, a), m in itertools.product(case.trajectory, case.rig):
            full = render(case.scene, case.intr, m, robot_pose=(x, y, a))
            cut = view_scene(case.scene, case.intr, m, (x, y, a))
            np.testing.assert_array_equal(
                full.depth_mm, render(cut, case.intr, m, robot_pose=(x, y, a)).depth_mm
            )


def test_random_worlds_keep_the_start_and_the_drive_clear_and_repeat_by_seed() -> None:
    for seed in range(30):
        case = random_case(seed)
        assert case == random_case(seed)
        poses = np.array([p[1:3] for p in case.trajectory])
        for item in (*case.scene.boxes, *case.scene.holes):
            d = rect_distance(poses, rect_of(item))
            assert d[0] >= ROBOT_RADIUS_M + START_CLEAR_M and d.min() > ROBOT_RADIUS_M
        assert 1 <= len(case.rig) <= 2 and all(0.3 <= m.height_m <= 0.9 for m in case.rig)
        assert all(5 <= m.tilt_deg <= 35 and math.hypot(m.x_m, m.y_m) <= 0.43 for m in case.rig)


def test_the_judge_counts_each_kind_of_lie() -> None:
    inf, nan = np.inf, np.nan
    # 0 ok, 1 far but held by bin 0 (beside), 2 unknown, 3 far (unsafe), 4 +inf over a visible
    # box bin 3 holds (beside, held), 5-8 +inf over an overhang, a drop-off below resolution, a
    # seen table top (overhang_cleared) and nothing, 9 too close, 10 false too-close, 11 +inf
    # over a box bin 10's -inf reports (beside, held), 12 +inf over a box no neighbour reports
    # (unsafe), 13 +inf over the memory's blind disc, 14 far, held only round the circle (by 0)
    r = np.array([1.01, 1.2, nan, 3.0, inf, inf, inf, inf, inf, -inf, -inf, inf, inf, inf, 1.1])
    vis = np.array([1.0, 1.0, inf, 2.0, 4.0, inf, inf, inf, inf, inf, inf, 2.0, 2.0, inf, 1.0])
    none = np.full(15, inf)

    def at(i: int, v: float) -> np.ndarray:
        a = none.copy()
        a[i] = v
        return a

    t = Truth(
        visible=vis,
        visible_edge=none,
        claim=vis,
        any=np.minimum(vis, at(9, 0.3)),
        overhang=np.minimum(at(5, 2.0), at(7, 1.0)),
        below=at(6, 1.0),
        cleared=at(7, 1.0),
        blind=at(13, 0.2),
    )
    c = judge(r, 0.4, 5.0, t, np.full(15, 0.02))
    assert (c.unsafe_far, c.unsafe_clear, c.clear_held, c.beside) == (2, 1, 2, 3)
    assert (c.overhang, c.below_resolution, c.overhang_cleared, c.blind) == (1, 1, 1, 1)
    assert (c.false_too_close, c.nan, c.with_truth, c.covered) == (1, 1, 7, 1)
    assert judge(r, 0.4, 5.0, t, np.full(15, 0.02), circular=True).unsafe_far == 1


def _one_sensor(scene: Scene, mount: Mount) -> tuple[Boundary, Sight]:
    sp = suite_params(SMALL)
    assert sp.cliff is not None
    bd = boundary(scene, sp.scan)
    return bd, sight(bd, scene, Camera.at(mount, SMALL, (0.0, 0.0, 0.0)), sp.scan, sp.cliff)


def test_the_claims_follow_the_contracts_reading() -> None:
    mount = Mount(0.5, 30.0)  # the top row meets the floor 2.9 m ahead
    near_table = table_top(1.5, 0.0, 0.6, 0.6, 0.75)  # its top is above the view
    far_box = Box(4.0, 0.0, 0.3, 0.3, 0.5)  # its floor is past the view's top edge
    beside = Box(1.0, 2.0, 0.3, 0.3, 0.5)  # left of the image
    narrow = Hole(1.3, 1.32, -0.6, -0.2, 0.3)  # 2 cm across: below the cliff's resolution
    wide = Hole(1.0, 1.6, 0.2, 0.6, 0.3)
    scene = Scene(boxes=(near_table, far_box, beside), holes=(narrow, wide))
    bd, s = _one_sensor(scene, mount)
    live, base = live_claims(s), base_claims([s])
    box, hole = ~bd.edge, bd.edge

    def of(owner: int, edge: bool) -> np.ndarray:
        return (bd.owner == owner) & (hole if edge else box)

    assert s.overhang[of(0, False)].any() and not live.claim[of(0, False)].any()
    assert not base.claim[of(0, False) & s.overhang].any()  # seen floor under it: not judged
    assert not live.claim[of(1, False)].any() and base.claim[of(1, False)].all()  # (c)
    assert not live.claim[of(2, False)].any() and base.claim[of(2, False)].all()
    assert s.below[of(0, True)].any() and not live.claim[of(0, True)].any()
    near_edge = of(1, True) & (bd.xy[:, 0] < 1.0 + 1e-9) & (bd.xy[:, 1] < 0.4)  # long way in
    assert live.claim[near_edge].all() and not live.claim[of(1, True) & (bd.xy[:, 0] > 1.59)].any()
    mem = memory_claims(bd, s.seen)
    assert not mem.claim[of(0, False)].any() and mem.claim[box & ~of(0, False)].all()


# the random drives -------------------------------------------------------------------------------


@pytest.mark.parametrize("name", OUTPUTS)
def test_no_output_lies_on_random_drives(suite: dict[str, Counts], name: str) -> None:
    c = suite[name]
    assert c.bins > 0, f"{name} was never judged"
    assert c.unsafe == 0, report(suite, name)
    if name not in BASE_FRAME_TOO_CLOSE:
        assert c.false_too_close == 0, report(suite, name)
    assert c.overhang_cleared == 0, report(suite, name)  # 0 on these drives when written


@pytest.mark.parametrize("name", OUTPUTS)
def test_every_output_covers_what_is_visible(suite: dict[str, Counts], name: str) -> None:
    c = suite[name]
    assert c.coverage >= COVERAGE_FLOOR[name], report(suite, name)


# unsafe (far + clear) bins measured on the slow drives, seeds 1000-1999 at 160x120 (seeds
# 5000-5099 at 320x240: 0 everywhere): the CI's seeds are not the only worlds there are, and
# these are what is left beyond them (docs/safety-contract.md, "Beyond the CI drives")
SLOW_CEILING = {
    "level_scan": 14,
    "level_cliff": 3,
    "base_scan": 3,
    "base_cliff": 5,
    "merged_scan": 0,
    "merged_cliff": 1,
    "sectors": 2,
    "memory": 0,
    "memory_sectors": 0,
}


@pytest.mark.slow
@pytest.mark.parametrize(
    ("first", "drives", "size"), [(1000, 1000, (160, 120)), (5000, 100, (320, 240))]
)
def test_no_output_lies_on_many_more_drives(first: int, drives: int, size: tuple[int, int]) -> None:
    totals = run_suite(range(first, first + drives), FRAMES, KINECT_V1.scaled(*size))
    ceiling = SLOW_CEILING if size == (160, 120) else {}
    for name in OUTPUTS:
        c = totals[name]
        assert c.unsafe <= ceiling.get(name, 0), report(totals, name)
        if name not in BASE_FRAME_TOO_CLOSE:
            assert c.false_too_close == 0, report(totals, name)
        assert c.overhang_cleared == 0, report(totals, name)  # 0 on these drives when written
        assert c.coverage >= COVERAGE_FLOOR[name], report(totals, name)


# the named scenarios (VGA, the shipped parameters) ---------------------------------------


def _case(scene: Scene, mount: Mount, trajectory: list[tuple[float, float, float, float]]) -> Case:
    """An exact drive (no depth or odometry noise) of one sensor on the Kinect v1 image."""
    odom = odometry([p[1:] for p in trajectory])
    return Case(0, scene, (mount,), tuple(trajectory), tuple(odom), KINECT_V1, None, None)


def _bins_near(scan: LaserScan, lo_rad: float, hi_rad: float) -> np.ndarray:
    """Indices of the bins whose footprint overlaps [lo, hi] (radians)."""
    a = scan.angles
    half = scan.angle_increment / 2
    return np.flatnonzero((a + half >= lo_rad) & (a - half <= hi_rad))


def test_a_box_passed_on_the_left_stays_in_memory_and_a_step_edge_survives_a_turn() -> None:
    """(a) Straight past a box 0.7-1.0 m to the left, 2.0-2.3 m ahead at the start (sensor 0.5 m
    high, 15 deg down, exact odometry), then a 90 deg turn in place 1 m before a step down: the
    memory never lies, holds the box within 5 cm while it is beside the robot, and the step's
    edge where it was after the turn."""
    mount = Mount(0.5, 15.0)
    box = Box(2.15, 0.85, 0.3, 0.3, 0.5)
    scene = Scene(boxes=(box,), holes=(step_down(4.0, 0.2, 3.0, 7.0),))
    drive = straight(1.0, 4.0, 13)  # 0.25 m a frame to x = 3
    turn = turn_in_place(60.0, 4.0, 7, start=drive[-1][1:])  # 15 deg a frame to 90 deg
    trajectory = drive + [(drive[-1][0] + t, x, y, a) for t, x, y, a in turn[1:]]
    case = _case(scene, mount, trajectory)
    steps = list(run_case(case))
    counts = judge_drive(case, steps)["memory"]
    assert (counts.unsafe_far, counts.unsafe_clear) == (0, 0), counts.line("memory")

    bd = boundary(scene, suite_params(KINECT_V1).scan)
    every = np.ones(len(bd.xy), bool)
    beside = [s for s in steps if 2.0 <= s.pose[0] <= 2.3 and s.pose[2] == 0.0]
    assert beside
    for s in beside:  # the box is 0.7 m to the left, out of the sensor's view
        bins = _bins_near(s.memory, math.radians(60), math.radians(120))
        every_claim = Claims(every, every, ~every, ~every, ~every)
        box_r = truth(bd, every_claim, s.pose, _layout(s.memory), ~bd.edge).visible[bins]
        got = np.asarray(s.memory.ranges[bins], dtype=float)[np.isfinite(box_r)]
        assert got.size and np.all(np.abs(got - box_r[np.isfinite(box_r)]) <= 0.05), (s.index, got)

    last = steps[-1]
    assert last.pose[2] == pytest.approx(math.pi / 2)
    edge = 4.0 - last.pose[0]  # 1 m to the robot's right now
    bins = _bins_near(last.memory, math.radians(-100), math.radians(-80))
    got = np.asarray(last.memory.ranges[bins], dtype=float)
    want = edge / np.abs(np.cos(last.memory.angles[bins] + math.pi / 2))
    assert np.all(np.abs(got - want) <= 0.05), (got, want)


def test_a_box_outside_the_image_is_never_free_in_the_base_scan() -> None:
    """(b) A sensor at y = -0.3 m (yaw 0) and a box 2.0-2.1 m ahead, 0.95-1.2 m left of the base,
    entirely outside its image: no +inf on the box's bearings in the base-frame scan."""
    mount = Mount(0.5, 15.0, y_m=-0.3)
    box = Box(2.05, 1.075, 0.1, 0.25, 0.5)
    scene = Scene(boxes=(box,))
    sp = suite_params(KINECT_V1)
    assert sp.cliff is not None
    bd = boundary(scene, sp.scan)
    s = sight(bd, scene, Camera.at(mount, KINECT_V1, (0.0, 0.0, 0.0)), sp.scan, sp.cliff)
    assert not s.covered.any()  # the premise: no part of the box (nor its floor) is in the image
    assert base_claims([s]).claim.all() and not live_claims(s).claim.any()
    frame = Frame(0, 0.0, render(scene, KINECT_V1, mount).depth_mm, KINECT_V1)
    scan = process(frame, mount, sp).scan
    corners = np.arctan2([0.95, 1.2, 0.95, 1.2], [2.0, 2.0, 2.1, 2.1])
    bins = _bins_near(scan, float(corners.min()), float(corners.max()))
    got = np.asarray(scan.ranges[bins], dtype=float)
    assert not np.any(got == np.inf), f"+inf over the box at {np.degrees(scan.angles[bins])}"
    t = truth(bd, base_claims([s]), (0, 0, 0), _layout(scan))
    assert (
        judge(scan.ranges, scan.range_min, scan.range_max, t, np.full(t.any.size, 0.02)).unsafe == 0
    )


def _layout(scan: LaserScan) -> tuple[float, float, int]:
    return float(scan.angle_min), float(scan.angle_increment), int(scan.ranges.size)


def test_the_live_cliff_scan_holds_a_step_edge_from_the_dead_zone_to_3_m() -> None:
    """(c) Toward a 30 cm step 3 m ahead (sensor 0.6 m high, 20 deg down, x_m = 0.15): straight
    ahead the live cliff scan is within 5 cm of the edge (never farther) on every frame where the
    edge is in view, from the dead zone out to 3 m; level frame and base frame alike."""
    mount = Mount(0.6, 20.0, x_m=0.15)
    scene = Scene(holes=(step_down(3.0, 0.3, 3.0, 6.0),))
    case = _case(scene, mount, straight(0.4, 4.0, 23))  # 0.1 m a frame
    sp = suite_params(KINECT_V1)
    assert sp.cliff is not None
    bd = boundary(scene, sp.scan)
    ahead = int(np.argmin(np.hypot(bd.xy[:, 0] - 3.0, bd.xy[:, 1])))
    seen, bad = [], []
    for s in run_case(case):
        cam = Camera.at(mount, KINECT_V1, s.pose)
        if not sight(bd, scene, cam, sp.scan, sp.cliff).visible[ahead]:
            continue
        edge = 3.0 - s.pose[0]
        seen.append(edge)
        res = s.results[0]
        assert res.cliff is not None and res.level_cliff is not None
        for name, scan, want in (
            ("base", res.cliff.scan, edge),
            ("level", res.level_cliff.scan, edge - mount.x_m),
        ):
            r = float(scan.ranges[int(np.argmin(np.abs(scan.angles)))])
            if not abs(r - want) <= 0.05:
                bad.append(f"{name} edge {want:.2f} m: {r:.3f}")
    assert seen and min(seen) < 1.0 and max(seen) > 2.9, seen
    assert bad == [], "\n".join(bad)


def test_a_drop_off_whose_lower_floor_lies_past_range_max_is_not_read_clear() -> None:
    """Seed 1006 (outside the CI drives): a pit's edge 4.1-4.9 m away, its floor seen beyond the
    cliff stage's range_max (5 m). Its drop-off samples were too few to make a block, and the
    bins read +inf because a sample in their highest row read something: the pit itself, or a
    box 2 m away standing in front of the floor there (51 level and 7 base-frame bins). A +inf
    now needs a reach sample that reads the floor and none that reads a drop-off or something
    standing; no drop-off sample in its sample columns or those beside them (the edge crosses
    some bins at a slant between two sample columns: 13 bins read +inf without this); and the
    reach samples include the first sample row past range_max (at 160x120 the highest row
    within it ends up to 0.3 m short of it, and the edge lay between: 7 bins)."""
    totals = judge_drive(random_case(1006, FRAMES, KINECT_V1.scaled(160, 120)))
    assert totals["level_cliff"].unsafe == 0, totals["level_cliff"].examples
    assert totals["base_cliff"].unsafe_clear == 0, totals["base_cliff"].examples
    assert totals["sectors"].unsafe == 0, totals["sectors"].examples


def test_a_box_too_close_to_read_in_the_dead_zone_is_not_clear_in_the_base_frame() -> None:
    """Seed 1801 (outside the CI drives): a sensor 0.34 m off the base origin, yawed 139 deg
    right, with a tall box 0.33 m in front of its lens: inside the floor's dead zone (the bottom
    row meets the floor 0.67 m out) and too close to read (the image's lower left is all 0).
    The level scan says NaN there; the base bins whose rays pass the sensor's foot and cross
    those wedges inside the dead zone read +inf over the box 0.67 m away (6 bins). A wedge
    whose view reaches range_max and that read NaN now makes a dead-zone crossing unknown."""
    mount = Mount(0.3925, 7.82, -1.18, x_m=-0.2622, y_m=-0.2146, yaw_deg=-139.16)
    box = Box(1.2497, -0.8698, 0.525, 0.3554, 0.8349, yaw_deg=71.06)
    pose = (1.4592, 0.0329, 0.3108)
    case = Case(0, Scene(boxes=(box,)), (mount,), ((0.0, *pose),), (pose,), SMALL, None, None)
    step = next(run_case(case))
    view = render(case.scene, SMALL, mount, robot_pose=pose)
    assert (view.depth_mm[60:, :40] == 0).all()  # the box, too close to read
    totals = judge_drive(case, [step])
    assert totals["base_scan"].unsafe == 0, totals["base_scan"].examples
    assert totals["sectors"].unsafe == 0, totals["sectors"].examples
    # the bins over the box (base bearings -134..-132 deg) are unknown, not clear
    scan = step.results[0].scan
    over = _bins_near(scan, math.radians(-134.0), math.radians(-132.0))
    assert np.isnan(scan.ranges[over]).all()
