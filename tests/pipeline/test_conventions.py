"""Convention pins (DEVELOPERS.md): units, pixel-centre origin, RDF axes, tilt and roll signs
and bearings.

Each expected number is derived by hand in the comment beside it.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from depthnav_daemon.pipeline.geometry import Mount, cam_to_level, level_rays, pixel_rays
from depthnav_daemon.pipeline.scan import ScanParams, depth_to_scan
from depthnav_daemon.sim.synthetic import Box, Scene, render
from drivers.base import Intrinsics
from tests.pipeline.scenes import ASYM_640


def test_pixel_centre_origin_and_rdf_axes() -> None:
    intr = Intrinsics(8, 6, 10.0, 20.0, 3.0, 2.0)
    rays = pixel_rays(intr)
    # pixel (u=0, v=0) is the centre of the top-left pixel: x = (0 - cx)/fx, y = (0 - cy)/fy
    np.testing.assert_allclose(rays[0, 0], [-0.3, -0.1, 1.0])
    # u grows to the right (+x), v grows downward (+y); fx scales x only, fy scales y only
    np.testing.assert_allclose(rays[5, 7], [(7 - 3) / 10, (5 - 2) / 20, 1.0])
    assert rays[2, 3].tolist() == [0.0, 0.0, 1.0]  # the principal point looks straight ahead


def test_level_frame_is_flu_with_tilt_down_and_roll_left_up() -> None:
    # no tilt or roll: camera forward (z) -> level x, camera right (x) -> level -y,
    # camera down -> level -z
    r = cam_to_level(0.0, 0.0)
    np.testing.assert_allclose(r @ [0, 0, 1], [1, 0, 0], atol=1e-12)
    np.testing.assert_allclose(r @ [1, 0, 0], [0, -1, 0], atol=1e-12)
    np.testing.assert_allclose(r @ [0, 1, 0], [0, 0, -1], atol=1e-12)
    # tilt +30 deg = pitched down: the optical axis points 30 deg below the horizon
    r = cam_to_level(math.radians(30), 0.0)
    np.testing.assert_allclose(r @ [0, 0, 1], [math.cos(math.radians(30)), 0, -0.5], atol=1e-12)
    # roll +10 deg = left side up: the camera's right axis dips below the horizon (z < 0)
    r = cam_to_level(0.0, math.radians(10))
    np.testing.assert_allclose(
        r @ [1, 0, 0], [0, -math.cos(math.radians(10)), -math.sin(math.radians(10))], atol=1e-12
    )


def test_tilted_camera_sees_the_floor_where_trigonometry_says() -> None:
    # h = 0.8 m, tilt 30 deg down: the principal ray meets the floor at x = 0.8 / tan(30) = 1.3856
    # m, at optical depth z = 0.8 / sin(30) = 1.6 m
    intr = ASYM_640
    view = render(Scene(), intr, Mount(0.8, 30.0, 0.0))
    v, u = round(intr.cy), round(intr.cx)
    assert view.depth_true_m[v, u] == pytest.approx(1.6 * 1.0, rel=1e-3)  # cx, cy are integers here
    assert view.points_m[v, u, 0] == pytest.approx(0.8 / math.tan(math.radians(30)), rel=1e-3)
    # rows below the principal point see nearer floor (down = +v)
    assert view.depth_true_m[v + 100, u] < view.depth_true_m[v, u]


def test_roll_left_up_lowers_the_horizon_on_the_left_of_the_image() -> None:
    # with the left side up, the camera's left half looks higher: more of it sees beyond the floor
    view = render(Scene(), ASYM_640, Mount(1.0, 10.0, 8.0))
    floor = view.label == 1
    first_floor_row = floor.argmax(axis=0)  # top-most floor row per column
    assert first_floor_row[20] > first_floor_row[-20]


def test_scan_bearings_are_counter_clockwise_from_forward() -> None:
    # a box 2 m ahead and 0.5 m to the LEFT (+y) must appear at a positive bearing:
    # atan2(0.5, 2) = 14.04 deg
    mount = Mount(0.5, 10.0, 0.0)
    box = Box(2.05, 0.5, 0.1, 0.1, 0.6)
    view = render(Scene(boxes=(box,)), ASYM_640, mount)
    scan = depth_to_scan(view.depth_mm, ASYM_640, mount, ScanParams())
    hit = np.isfinite(scan.ranges)
    bearing = np.degrees(scan.angles[hit])
    assert bearing.min() > 12.0 and bearing.max() < 16.0
    # horizontal range, not optical depth: the front face at x = 2.0 -> sqrt(2.0^2 + 0.5^2) ~ 2.06 m
    assert np.nanmin(scan.ranges) == pytest.approx(math.hypot(2.0, 0.45), abs=0.01)


def test_depth_units_uint16_mm_equal_float32_m() -> None:
    intr = Intrinsics(4, 3, 2.0, 2.0, 1.5, 1.0)
    mm = np.full((3, 4), 1500, np.uint16)
    m = np.full((3, 4), 1.5, np.float32)
    p = ScanParams(range_min_m=0.1, min_obstacle_height_m=-1.0, max_obstacle_height_m=1.0)
    a = depth_to_scan(mm, intr, Mount(0.5, 0.0, 0.0), p).ranges
    b = depth_to_scan(m, intr, Mount(0.5, 0.0, 0.0), p).ranges
    np.testing.assert_array_equal(a, b)
    # a level sensor, wall 1.5 m ahead; with cx = 1.5 the nearest pixel centres sit half a pixel off
    # the axis, (u - cx)/fx = 0.25, so the nearest horizontal range is
    # 1.5 * hypot(1, 0.25) = 1.5462 m
    assert np.nanmin(a) == pytest.approx(1.5 * math.hypot(1.0, 0.25), abs=1e-3)


def test_level_rays_are_cached_and_read_only() -> None:
    a = level_rays(ASYM_640, 0.1, 0.0)
    assert a is level_rays(ASYM_640, 0.1, 0.0)
    with pytest.raises(ValueError):
        a[0, 0, 0] = 1.0
