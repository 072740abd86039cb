"""Synthetic drives: trajectories, the odometry a robot would report along them, and frames
rendered from the moving robot (the sensor where its placement on the robot says)."""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest

from depthnav_daemon.pipeline.geometry import Mount
from depthnav_daemon.sim.drive import OdometryNoise, arc, odometry, render_drive, straight
from depthnav_daemon.sim.synthetic import LABEL_BOX0, Box, Scene, render
from drivers.base import KINECT_V1


def test_arc_is_a_circle_of_radius_speed_over_rate() -> None:
    poses = arc(0.5, 30.0, 10.0, 61)  # 6 s at 30 deg/s: half a turn
    r = 0.5 / math.radians(30.0)
    _, x, y, a = poses[-1]
    assert (x, y) == pytest.approx((0.0, 2 * r), abs=1e-9)  # the far side of the circle
    assert math.degrees(a) == pytest.approx(180.0)
    assert arc(0.3, 0.0, 10.0, 5)[-1][1:] == pytest.approx(straight(0.3, 10.0, 5)[-1][1:])


def test_exact_odometry_is_the_true_path_and_scale_error_scales_it() -> None:
    poses = [p[1:] for p in arc(0.4, 25.0, 5.0, 40, start=(1.0, -2.0, 0.3))]
    exact = odometry(poses)
    np.testing.assert_allclose(exact, poses, atol=1e-9)
    scaled = odometry(poses, OdometryNoise(scale_error=0.02))
    path = lambda ps: sum(math.dist(a[:2], b[:2]) for a, b in itertools.pairwise(ps))  # noqa: E731
    assert path(scaled) == pytest.approx(1.02 * path(poses), rel=1e-9)
    assert scaled[-1][2] == pytest.approx(poses[-1][2])  # the heading is not scaled
    with pytest.raises(ValueError, match="needs an rng"):
        odometry(poses, OdometryNoise(sigma_m=0.01))
    noisy = odometry(poses, OdometryNoise(sigma_m=0.01, sigma_rad=0.01), np.random.default_rng(1))
    assert 0.0 < math.dist(noisy[-1][:2], poses[-1][:2]) < 1.0


def test_frames_are_rendered_from_the_robot_pose_and_the_placement() -> None:
    # a box at world (3, 1); robot at (1, 1) facing +x; sensor 0.2 m left of the base, yawed
    # -10 deg: the same image as a robot at the origin looking at a box at (2, 0) from (0, 0.2)
    mount = Mount(0.5, 10.0, 0.0, x_m=0.0, y_m=0.2, yaw_deg=-10.0)
    intr = KINECT_V1.scaled(160, 120)
    frames = list(
        render_drive(
            Scene(boxes=(Box(3.0, 1.0, 0.3, 0.3, 0.5),)), intr, mount, [(0.0, 1.0, 1.0, 0.0)]
        )
    )
    same = render(Scene(boxes=(Box(2.0, 0.0, 0.3, 0.3, 0.5),)), intr, mount)
    np.testing.assert_array_equal(frames[0].frame.depth_mm, same.depth_mm)
    assert frames[0].frame.odom == (1.0, 1.0, 0.0) and (same.label >= LABEL_BOX0).sum() > 20
