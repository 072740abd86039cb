"""Sensor placement on the robot (REP 103 base frame): scan, cliff points, cliff scan and MAVLink
sectors in the base frame. Values are asymmetric on purpose (x != y, both signs, yaw not 90 deg)
so a swapped sign or axis fails.

Worked numbers in the comments; the synthetic world is the base frame (robot at the origin).
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from depthnav_daemon.errors import ConfigError
from depthnav_daemon.pipeline import StageParams, process
from depthnav_daemon.pipeline.cliff import CliffParams
from depthnav_daemon.pipeline.geometry import Mount
from depthnav_daemon.pipeline.placement import points_to_base
from depthnav_daemon.pipeline.scan import ScanParams
from depthnav_daemon.sim.synthetic import (
    Box,
    Hole,
    Scene,
    in_drop_off,
    render,
    truth_drop_ranges,
    truth_obstacle_interval,
)
from depthnav_daemon.sinks.mavlink.sectors import obstacle_sectors
from drivers.base import Frame
from tests.pipeline.scenes import ASYM_640

PARAMS = StageParams(scan=ScanParams(), cliff=CliffParams())


def _run(scene: Scene, mount: Mount, params: StageParams = PARAMS):
    view = render(scene, ASYM_640, mount)
    return process(Frame(0, 0.0, view.depth_mm, ASYM_640), mount, params)


def _check_against_truth(result, scene: Scene, tol_m: float = 0.01) -> int:
    """Every finite base-frame bin lies within the true base-frame obstacle interval over its
    footprint (the bin plus the sensor bin's footprint: 1.5 bins either side, as test_scan), and
    no bin away from every box reports one."""
    scan = result.scan
    lo, hi = truth_obstacle_interval(scene, scan.angles, scan.angle_increment * 1.5, 0.05, 2.0)
    fin = np.isfinite(scan.ranges)
    assert fin.sum() > 10
    assert not (fin & ~np.isfinite(lo)).any(), "an obstacle where no box is"
    r = scan.ranges[fin]
    assert np.all(r >= lo[fin] - tol_m), np.max(lo[fin] - r)
    assert np.all(r <= np.minimum(hi[fin], 99.0) + tol_m), np.max(r - hi[fin])
    return int(fin.sum())


def test_default_placement_changes_nothing() -> None:
    scene = Scene(boxes=(Box(2.0, 0.3, 0.3, 0.3, 0.5),))
    r = _run(scene, Mount(0.5, 12.0, 0.0))
    assert r.sensor_scan is None and r.level_scan is r.scan  # no copy, no conversion
    assert "placement" not in r.timings_s


def test_yaw_only_turns_every_bearing_counter_clockwise_and_keeps_the_ranges() -> None:
    # the same scene turned by +35 deg about the sensor: the scan turns by +35 deg, ranges equal
    box = Box(2.0, -0.4, 0.3, 0.3, 0.5)
    plain = _run(Scene(boxes=(box,)), Mount(0.5, 12.0, 0.0))
    yaw = math.radians(35.0)
    c, s = math.cos(yaw), math.sin(yaw)
    turned = Box(c * 2.0 - s * -0.4, s * 2.0 + c * -0.4, 0.3, 0.3, 0.5, yaw_deg=35.0)
    placed = _run(Scene(boxes=(turned,)), Mount(0.5, 12.0, 0.0, yaw_deg=35.0))
    assert placed.scan.angle_min == pytest.approx(plain.scan.angle_min + yaw, abs=1e-12)
    assert placed.scan.angle_increment == plain.scan.angle_increment
    # the same pixels see the same (turned) box: bit-equal ranges
    np.testing.assert_array_equal(placed.scan.ranges, plain.scan.ranges)
    # the box at bearing atan2(-0.4, 2) = -11.3 deg relative to the sensor is at +23.7 deg (left)
    hit = np.degrees(placed.scan.angles[np.isfinite(placed.scan.ranges)])
    assert 17.0 < hit.min() and hit.max() < 30.0


@pytest.mark.parametrize(
    "mount",
    [
        Mount(0.5, 12.0, 0.0, x_m=0.35, y_m=-0.15, yaw_deg=40.0),
        Mount(0.45, 15.0, 3.0, x_m=-0.2, y_m=0.25, yaw_deg=-40.0),
    ],
)
def test_off_origin_sensor_reports_base_frame_ranges_and_bearings(mount: Mount) -> None:
    # boxes placed in the BASE frame: every finite bin must match the base-frame truth (ranges
    # from the base origin) within 1 cm, at its base bearing
    sign = 1.0 if mount.yaw_deg > 0 else -1.0
    scene = Scene(
        boxes=(
            Box(1.6, sign * 1.5, 0.3, 0.3, 0.5),
            Box(2.2, sign * 1.2, 0.4, 0.2, 0.7, yaw_deg=20.0),
        )
    )
    r = _run(scene, mount)
    _check_against_truth(r, scene)
    assert r.mount == mount
    # the level-frame scan is kept for the memory, and differs (it is centred on the sensor)
    assert r.sensor_scan is not None and r.sensor_scan.ranges.size != r.scan.ranges.size


def test_swapped_sign_of_y_would_fail() -> None:
    # the same scene seen from y = -0.15 and from y = +0.15 differs by centimetres in base range
    scene = Scene(boxes=(Box(1.6, 1.5, 0.3, 0.3, 0.5),))
    right = _run(scene, Mount(0.5, 12.0, 0.0, x_m=0.35, y_m=-0.15, yaw_deg=40.0))
    _check_against_truth(right, scene)
    # process a frame rendered from y=-0.15 as if the sensor were at y=+0.15: must not match
    wrong_mount = Mount(0.5, 12.0, 0.0, x_m=0.35, y_m=0.15, yaw_deg=40.0)
    view = render(scene, ASYM_640, Mount(0.5, 12.0, 0.0, x_m=0.35, y_m=-0.15, yaw_deg=40.0))
    wrong = process(Frame(0, 0.0, view.depth_mm, ASYM_640), wrong_mount, PARAMS)
    with pytest.raises(AssertionError):
        _check_against_truth(wrong, scene)


def test_cliff_points_and_cliff_scan_are_in_the_base_frame() -> None:
    # a 20 cm deep hole in the base frame, seen by a sensor at (0.3, 0.2) yawed -25 deg
    hole = Hole(1.4, 1.8, -1.0, -0.5, 0.2)
    scene = Scene(holes=(hole,))
    mount = Mount(0.55, 20.0, 0.0, x_m=0.3, y_m=0.2, yaw_deg=-25.0)
    r = _run(scene, mount)
    pts = np.asarray(r.cliff.points_m)
    assert len(pts) > 3
    # every block point lies on the hole (within a block's footprint of its rim)
    assert in_drop_off(scene, pts[:, 0], pts[:, 1], margin_m=0.1).all()
    # the level-frame points, put through the placement by hand: Rz(-25) q + (0.3, 0.2)
    q = np.asarray(r.sensor_cliff.points_m, dtype=np.float64)
    c, s = math.cos(math.radians(-25)), math.sin(math.radians(-25))
    by_hand = np.stack([c * q[:, 0] - s * q[:, 1] + 0.3, s * q[:, 0] + c * q[:, 1] + 0.2], -1)
    np.testing.assert_allclose(pts, by_hand, atol=1e-5)
    # the cliff scan: nearest drop-off per base bearing, ranges from the base origin
    cs = r.cliff.scan
    fin = np.isfinite(cs.ranges)
    assert fin.sum() > 5
    truth = truth_drop_ranges(scene, cs.angles[fin])
    # samples every 8 rows: a drop-off is found up to ~one sample spacing (~7 cm here) past the rim
    assert np.all(cs.ranges[fin] >= truth - 0.02)
    assert np.all(cs.ranges[fin] <= truth + 0.12)


def test_points_to_base_is_rotation_then_translation() -> None:
    m = Mount(0.5, 0.0, 0.0, x_m=0.1, y_m=-0.2, yaw_deg=90.0)
    # forward 1 m in the sensor frame = +y (left) in the base frame, then shifted by (0.1, -0.2)
    np.testing.assert_allclose(points_to_base(np.array([[1.0, 0.0]]), m), [[0.1, 0.8]], atol=1e-6)
    np.testing.assert_allclose(points_to_base(np.array([[0.0, 1.0]]), m), [[-0.9, -0.2]], atol=1e-6)


def test_mavlink_sectors_follow_the_base_frame() -> None:
    # a sensor yawed 40 deg left sees a box at base bearing ~+47 deg: in MAVLink's clockwise
    # (FRD) bearings that is about -47 deg, i.e. the obstacle's sector is left of forward
    mount = Mount(0.5, 12.0, 0.0, x_m=0.35, y_m=-0.15, yaw_deg=40.0)
    scene = Scene(boxes=(Box(1.6, 1.7, 0.3, 0.3, 0.5),))
    r = _run(scene, mount)
    sec = obstacle_sectors(r.scan)
    d = sec.distances_cm.astype(float)
    near = int(np.argmin(np.where(d < 65535, d, np.inf)))
    bearing_cw = sec.angle_offset_deg + near * sec.increment_f_deg
    truth_deg = -math.degrees(math.atan2(1.7, 1.45))  # the box's front-right corner, roughly
    assert bearing_cw == pytest.approx(truth_deg, abs=4.0)
    assert d[near] == pytest.approx(100 * math.hypot(1.45, 1.55), abs=6.0)


@pytest.mark.parametrize(
    ("kwargs", "text"),
    [
        ({"x_m": 11.0}, r"mount x_m=11.0 is out of range \(accepted: -10..10 m\)"),
        ({"y_m": float("nan")}, r"mount y_m=nan is out of range"),
        ({"yaw_deg": 181.0}, r"mount yaw_deg=181.0 is out of range \(accepted: -180..180 deg\)"),
    ],
)
def test_placement_out_of_range_is_one_line(kwargs: dict, text: str) -> None:
    with pytest.raises(ConfigError, match=text):
        Mount(0.5, 10.0, 0.0, **kwargs)


def test_a_sensor_looking_backwards_across_pi() -> None:
    # at the back of the robot, looking back: its bins run on past +pi (a continuous layout);
    # the boxes behind are at their base-frame bearings (about +-170 deg) and ranges
    mount = Mount(0.5, 12.0, 0.0, x_m=-0.3, y_m=0.1, yaw_deg=180.0)
    scene = Scene(boxes=(Box(-2.0, 0.45, 0.3, 0.3, 0.5), Box(-1.7, -0.5, 0.3, 0.3, 0.5)))
    r = _run(scene, mount)
    assert r.scan.angle_min < math.pi < r.scan.angle_max
    assert _check_against_truth(r, scene) > 40
