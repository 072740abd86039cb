"""The base-frame scan of an off-centre sensor keeps the safety contract (README, Conventions)
against truth from the scene's geometry (robot at the origin of the scene): +inf only where the
whole base ray was in the sensor's view, no holes between the bins of a near obstacle, too close
stays too close."""

from __future__ import annotations

import math

import numpy as np
import pytest

from depthnav_daemon.pipeline import StageParams, process
from depthnav_daemon.pipeline.cliff import CliffParams
from depthnav_daemon.pipeline.geometry import Mount
from depthnav_daemon.pipeline.scan import ScanParams
from depthnav_daemon.sim.synthetic import Box, Scene, render
from depthnav_daemon.sim.truth import truth_obstacle_ranges
from drivers.base import Frame, Intrinsics

INTR = Intrinsics(320, 240, 290.0, 290.0, 159.5, 119.5)
PARAMS = StageParams(scan=ScanParams(), cliff=CliffParams())


def _base_scan(scene: Scene, mount: Mount, params: StageParams = PARAMS):
    view = render(scene, INTR, mount, min_range_m=0.05)
    return process(Frame(0, 0.0, view.depth_mm, INTR), mount, params).scan


def _truth(scan, scene: Scene, params: ScanParams) -> np.ndarray:
    """Nearest box per base bin over its width (5 bearings), from the base origin."""
    ang = scan.angle_min + scan.angle_increment * np.arange(scan.ranges.size)
    sub = ang[:, None] + scan.angle_increment * np.linspace(-0.5, 0.5, 5)[None, :]
    t = truth_obstacle_ranges(
        scene, sub.reshape(-1), params.min_obstacle_height_m, params.max_obstacle_height_m
    )
    return t.reshape(sub.shape).min(axis=1)


def test_a_box_outside_the_image_is_not_called_clear() -> None:
    """Sensor at y = -0.3 m, yaw 0; a box 0.9-1.2 m left of the base at 2.0-2.2 m, outside the
    image (measured on an earlier main: 165 of 234 base bins on its bearings read +inf)."""
    mount = Mount(0.5, 15.0, 0.0, x_m=0.0, y_m=-0.3, yaw_deg=0.0)
    scene = Scene(boxes=(Box(2.1, 1.05, 0.2, 0.3, 0.5),))
    scan = _base_scan(scene, mount)
    truth = _truth(scan, scene, PARAMS.scan)
    on_box = truth < scan.range_max
    assert on_box.sum() > 10
    assert not np.isposinf(scan.ranges[on_box]).any()
    # what the image shows of its corner is never farther than it is; the rest is unknown
    r, t = scan.ranges[on_box], truth[on_box]
    assert (r[np.isfinite(r)] <= t[np.isfinite(r)] + 0.02).all()
    assert np.isnan(r).sum() > 0.8 * r.size
    # and the view still says clear somewhere (not NaN everywhere)
    assert np.isposinf(scan.ranges).sum() > 0.2 * scan.ranges.size


@pytest.mark.parametrize(
    "mount",
    [
        Mount(0.5, 15.0, 0.0, x_m=0.2, y_m=0.25, yaw_deg=30.0),
        Mount(0.4, 20.0, 2.0, x_m=-0.15, y_m=-0.3, yaw_deg=-25.0),
        Mount(0.6, 12.0, 0.0, x_m=0.3, y_m=0.0, yaw_deg=0.0),
    ],
    ids=["left_yawed", "back_right_rolled", "ahead"],
)
def test_near_box_from_the_side_no_holes_never_farther(mount: Mount) -> None:
    """A box 1 m away seen from an off-centre sensor: every base bin over it is finite (no +inf or
    NaN holes between the arcs) and never farther than the truth plus 2 cm; no bin anywhere says
    clear where the truth has the box."""
    yaw = math.radians(mount.yaw_deg)
    cx = mount.x_m + 1.1 * math.cos(yaw)
    cy = mount.y_m + 1.1 * math.sin(yaw)
    scene = Scene(boxes=(Box(cx, cy, 0.4, 0.6, 0.6, yaw_deg=mount.yaw_deg + 10.0),))
    scan = _base_scan(scene, mount)
    truth = _truth(scan, scene, PARAMS.scan)
    r = scan.ranges
    fin = np.isfinite(r)
    assert fin.sum() > 20
    assert (r[fin] <= truth[fin] + 0.02).all(), np.max(r[fin] - truth[fin])
    assert not (np.isposinf(r) & (truth < scan.range_max)).any()
    idx = np.flatnonzero(fin)
    span = r[idx[0] : idx[-1] + 1]
    assert np.isfinite(span).all(), (np.isposinf(span).sum(), np.isnan(span).sum())


def test_too_close_stays_too_close_in_the_base_frame() -> None:
    """A wall 0.45 m ahead of an off-centre sensor with range_min 0.6 m: the base bins over it
    are -inf, none +inf."""
    mount = Mount(0.5, 10.0, 0.0, x_m=0.2, y_m=-0.2, yaw_deg=-20.0)
    yaw = math.radians(mount.yaw_deg)
    scene = Scene(
        boxes=(
            Box(
                mount.x_m + 0.55 * math.cos(yaw),
                mount.y_m + 0.55 * math.sin(yaw),
                0.2,
                3.0,
                1.0,
                yaw_deg=mount.yaw_deg,
            ),
        )
    )
    params = StageParams(scan=ScanParams(range_min_m=0.6), cliff=CliffParams())
    scan = _base_scan(scene, mount, params)
    assert np.isneginf(scan.ranges).sum() > 0.5 * scan.ranges.size
    assert not np.isposinf(scan.ranges).any()


def test_two_sensor_merge_never_clear_over_a_wall() -> None:
    """Two yawed, off-centre sensors and a wall 2.5 m ahead with a box before it: the merged
    scan is never clear where the truth has something within its range_max, and never farther
    than the truth plus 2 cm."""
    from depthnav_daemon.pipeline.merge import merge_scans

    scene = Scene(boxes=(Box(2.55, 0.0, 0.1, 8.0, 1.5), Box(1.4, -0.5, 0.3, 0.3, 0.4)))
    mounts = [
        Mount(0.5, 15.0, 0.0, x_m=0.1, y_m=0.2, yaw_deg=28.0),
        Mount(0.45, 18.0, 0.0, x_m=0.15, y_m=-0.25, yaw_deg=-31.0),
    ]
    merged = merge_scans([_base_scan(scene, m) for m in mounts])
    truth = _truth(merged, scene, PARAMS.scan)
    r = merged.ranges
    fin = np.isfinite(r)
    assert fin.sum() > 0.5 * r.size
    assert (r[fin] <= truth[fin] + 0.02).all(), np.max(r[fin] - truth[fin])
    assert not (np.isposinf(r) & (truth < merged.range_max)).any()


@pytest.mark.parametrize("side", [1.0, -1.0], ids=["left", "right"])
def test_a_wall_at_a_slant_reads_its_nearest_point_in_every_base_bin(side: float) -> None:
    """A long wall seen at a slant from a sensor 0.3 m off the origin runs through each sensor
    bin's wedge over tens of cm of range, and the far part of a wedge falls in the next base
    bin: mapped from the level scan's bins alone, that base bin read the next wedge's nearest
    point, 1-18 cm beyond the wall (a generated drive: 4.641 m at a true 4.462 m). The obstacle
    pixels binned in the base frame give each base bin the wall's own nearest point."""
    mount = Mount(0.6, 10.0, 0.0, x_m=0.21, y_m=-0.21 * side, yaw_deg=20.0 * side)
    # a wall 3 m long, 12 cm thick, at 15 deg to the sensor's axis, centred 3.8 m ahead (from the
    # level scan's bins: 13 bins 1-4 cm too far on the left, 4 on the right)
    yaw = math.radians(mount.yaw_deg)
    cx = mount.x_m + 3.8 * math.cos(yaw)
    cy = mount.y_m + 3.8 * math.sin(yaw)
    scene = Scene(boxes=(Box(cx, cy, 3.0, 0.12, 0.8, yaw_deg=mount.yaw_deg + 15.0 * side),))
    scan = _base_scan(scene, mount)
    truth = _truth(scan, scene, PARAMS.scan)
    r = scan.ranges
    fin = np.isfinite(r) & (truth < scan.range_max)
    assert fin.sum() > 40
    assert (r[fin] <= truth[fin] + 0.02).all(), np.max(r[fin] - truth[fin])
    # and it covers the wall: most bins over it within 2 cm (not just safe, also useful)
    on = truth < scan.range_max - 0.1
    good = np.isfinite(r) & (np.abs(np.where(np.isfinite(r), r, 0.0) - truth) <= 0.02)
    assert good[on].mean() > 0.9, good[on].mean()
