"""The robot's body (pipeline/footprint.py): which pixels see it and which readings are it, checked
against the scene generator's ray caster; a frame whose only readings are the body gives unknown
(NaN) everywhere, never clear; a footprint nobody could mean is one line with a hint."""

from __future__ import annotations

import numpy as np
import pytest

from depthnav_daemon.config.loader import build_config
from depthnav_daemon.errors import ConfigError, FrameError
from depthnav_daemon.pipeline import StageParams, process
from depthnav_daemon.pipeline.cliff import CliffParams
from depthnav_daemon.pipeline.footprint import Footprint, body_table, remove_body
from depthnav_daemon.pipeline.geometry import Mount
from depthnav_daemon.pipeline.scan import ScanParams
from depthnav_daemon.sim.synthetic import LABEL_BOX0, LABEL_FLOOR, Box, Scene, render
from drivers.base import Frame, Intrinsics

# asymmetric on purpose (fx != fy, cx != cy, H != W): swapped axes fail loudly
INTR = Intrinsics(320, 240, 290.0, 286.0, 161.0, 118.0)
# the robot: a camera 1.27 m up pitched 73 deg down, a little ahead of and left of the
# base origin, sees the robot's own parts 5-25 cm high, 2-15 cm from its foot
MOUNT = Mount(1.27, 73.0, 0.0, x_m=0.05, y_m=0.02)
PARTS = (
    Box(0.15, 0.02, 0.06, 0.36, 0.25, base_m=0.05),  # a bumper 7-13 cm ahead of the foot
    Box(0.05, 0.13, 0.10, 0.04, 0.20, base_m=0.05),  # an arm 9-13 cm to its left
    Box(0.03, -0.10, 0.12, 0.05, 0.12, base_m=0.05),  # a wheel guard 10-15 cm to its right
)
# a chamfered outline around them (convex, 6 vertices), 30 cm tall
POLYGON = ((0.25, 0.15), (0.18, 0.22), (-0.25, 0.22), (-0.25, -0.22), (0.18, -0.22), (0.25, -0.15))
BODY = Footprint(POLYGON, 0.3)


def _inside(points: np.ndarray, body: Footprint, margin_m: float) -> np.ndarray:
    """Points (N, 3) inside the prism shrunk by ``margin_m`` (negative: grown)."""
    ok = (points[:, 2] >= margin_m) & (points[:, 2] <= body.height_m - margin_m)
    for nx, ny, c in body.half_planes():
        n = np.hypot(nx, ny)
        ok &= (nx * points[:, 0] + ny * points[:, 1]) / n <= c / n - margin_m
    return ok


@pytest.mark.parametrize(
    ("intr", "mount"),
    [
        (INTR, MOUNT),
        # rolled, yawed and placed elsewhere, with a lens: the table's rays are the renderer's
        (
            Intrinsics(320, 240, 290.0, 286.0, 161.0, 118.0, k1=-0.08, k2=0.02),
            Mount(1.1, 65.0, 4.0, x_m=-0.04, y_m=0.06, yaw_deg=12.0),
        ),
    ],
)
def test_the_table_removes_exactly_the_readings_inside_the_body(intr, mount) -> None:
    view = render(Scene(boxes=(*PARTS, Box(0.8, 0.0, 0.15, 0.5, 0.4))), intr, mount)
    depth = view.depth_mm
    out, removed = remove_body(depth, body_table(intr, mount, BODY))
    seen = depth > 0
    pts = view.points_m  # (H, W, 3): the world is the base frame here (robot at the origin)
    gone = seen & (out == 0)
    assert removed == int(gone.sum()) > 1000
    # every reading well inside the prism is removed, every one well outside kept (2 mm: the
    # millimetre rounding of the depth and of the table, widened outward)
    inside = _inside(pts.reshape(-1, 3), BODY, 0.002).reshape(depth.shape)
    outside = ~_inside(pts.reshape(-1, 3), BODY, -0.002).reshape(depth.shape)
    assert np.all(gone[inside & seen]) and not np.any(gone[outside & seen])
    parts = (view.label >= LABEL_BOX0) & (view.label < LABEL_BOX0 + len(PARTS))
    assert parts.sum() > 500 and np.all(out[parts] == 0)  # every pixel of the robot's parts
    other = view.label == LABEL_BOX0 + len(PARTS)  # the box beyond the bumper: kept whole
    assert other.sum() > 500 and np.array_equal(out[other], depth[other])
    # the floor under the outline is part of the prism (the body hides it from a real sensor)
    assert (gone & (view.label == LABEL_FLOOR)).sum() > 1000


def test_remove_body_reads_only_and_keeps_no_readings_and_the_bounds() -> None:
    table = body_table(INTR, MOUNT, BODY)
    r, c = int(table.rows[7]), int(table.cols[7])
    lo, hi = int(table.lo_mm[7]), int(table.hi_mm[7])
    assert 1 <= lo <= hi
    depth = np.zeros((INTR.height, INTR.width), np.uint16)
    for value, gone in ((lo - 1, False), (lo, True), (hi, True), (hi + 1, False)):
        depth[r, c] = value
        before = depth.copy()
        out, n = remove_body(depth, table)
        assert np.array_equal(depth, before)  # the input is never written
        assert (n, int(out[r, c]) == 0) == (int(gone), gone)
        assert (out is depth) == (not gone)  # nothing removed: the frame's own array
    # a camera that sees none of the body: an empty table, the frame as it is
    away = body_table(
        INTR,
        Mount(1.27, 0.0, 0.0, x_m=0.05, yaw_deg=180.0),
        Footprint(((2.0, 0.2), (1.8, 0.2), (1.8, -0.2), (2.0, -0.2)), 0.1),
    )
    assert away.size == 0 and remove_body(depth, away) == (depth, 0)
    with pytest.raises(FrameError, match="does not fit"):
        remove_body(depth[:, :-1], table)  # never read beyond the image
    with pytest.raises(FrameError, match="does not fit"):
        remove_body(depth.astype(np.int32), table)


def test_a_frame_that_sees_only_the_body_is_unknown_everywhere_never_clear() -> None:
    """Only the robot's parts read (no floor, nothing else): every scan and cliff bin is NaN
    with the footprint, where without it the parts read too close (-inf)."""
    depth = render(Scene(boxes=PARTS, floor=False), INTR, MOUNT).depth_mm
    params = StageParams(scan=ScanParams(), cliff=CliffParams(used_depth_height=240))
    bare = process(Frame(0, 0.0, depth.copy(), INTR), MOUNT, params)
    assert np.isneginf(bare.scan.ranges).sum() > 100
    out, _ = remove_body(depth, body_table(INTR, MOUNT, BODY))
    assert not out.any()
    result = process(Frame(0, 0.0, out, INTR), MOUNT, params)
    for scan in (result.scan, result.level_scan, result.cliff.scan, result.level_cliff.scan):
        assert np.isnan(scan.ranges).all()
    assert result.cliff.points_m.shape[0] == 0


def test_polygon_kept_counter_clockwise_either_way_round() -> None:
    cw = Footprint(tuple(reversed(POLYGON)), 0.3)
    assert set(cw.polygon_m) == set(POLYGON)
    xs, ys = np.array(cw.polygon_m).T
    assert np.sum(xs * np.roll(ys, -1) - np.roll(xs, -1) * ys) > 0  # positive area: CCW
    assert body_table(INTR, MOUNT, cw).size == body_table(INTR, MOUNT, BODY).size


@pytest.mark.parametrize(
    ("sets", "says"),
    [
        (["robot.footprint_m=[[0.3, 0.2], [-0.3, 0.2]]"], "has 2 vertices"),
        (["robot.footprint_m=[[0,0],[1,1],[1,0],[0,1]]", "robot.height_m=0.3"], "not a convex"),
        (["robot.footprint_m=[[0,0],[1,0],[0.2,0.2],[0,1]]", "robot.height_m=0.3"], "not a convex"),
        # a five-pointed star: every turn the same way, but it goes round twice
        (
            [
                "robot.footprint_m=[[1,0],[-0.81,0.59],[0.31,-0.95],[0.31,0.95],[-0.81,-0.59]]",
                "robot.height_m=0.3",
            ],
            "not a convex",
        ),
        (["robot.footprint_m=[[0,0],[1,0],[2,0]]", "robot.height_m=0.3"], "not a convex"),
        (["robot.footprint_m=[[0,0],[0.005,0],[0,0.005]]", "robot.height_m=0.3"], "no area"),
        (["robot.footprint_m=[[0,0],[11,0],[0,1]]", "robot.height_m=0.3"], "out of range"),
        (["robot.footprint_m=[[0,0],[1,0],[0,'a']]", "robot.height_m=0.3"], "pair of numbers"),
        (["robot.footprint_m=[[0,0],[1,0],[0,nan]]", "robot.height_m=0.3"], "pair of numbers"),
        (["robot.footprint_m='box'", "robot.height_m=0.3"], "list of [x, y] pairs"),
        (["robot.footprint_m=[[0.3, 0.2], [-0.3, 0.2], [0, -0.2]]"], "height_m is not"),
        (["robot.height_m=0.4"], "footprint_m is empty"),
        (["robot.footprint_m=[[0.3, 0.2], [-0.3, 0.2], [0, -0.2]]", "robot.height_m=-1"], "range"),
        (["robot.footprint_m=[[0.3, 0.2], [-0.3, 0.2], [0, -0.2]]", "robot.height_m=50"], "range"),
        (["robot.width_m=0.4"], "unknown key"),
    ],
)
def test_absurd_footprints_are_one_line_with_a_hint(sets: list[str], says: str) -> None:
    with pytest.raises(ConfigError) as err:
        build_config([], sets)
    assert says in str(err.value) and "\n" not in str(err.value)
    assert err.value.hint


def test_no_footprint_by_default_and_a_box_from_config() -> None:
    assert build_config([], []).robot.footprint() is None
    cfg = build_config(
        [],
        [
            "robot.footprint_m=[[0.3, 0.25], [0.3, -0.25], [-0.3, -0.25], [-0.3, 0.25]]",
            "robot.height_m=0.4",
        ],
    )
    body = cfg.robot.footprint()
    assert body is not None and body.height_m == 0.4 and len(body.polygon_m) == 4
