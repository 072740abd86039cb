"""The view's reach on the floor per bin (coverage.floor_extent) against a projection written
here from the conventions (camera x right, y down, z forward; tilt positive down; roll about the
forward axis, left side up), not from the stage's rotations."""

from __future__ import annotations

import math

import numpy as np
import pytest

from depthnav_daemon.pipeline.cliff import detect_cliffs
from depthnav_daemon.pipeline.coverage import floor_extent, seen_to
from depthnav_daemon.pipeline.geometry import Mount
from depthnav_daemon.pipeline.params import CliffParams, ScanParams
from depthnav_daemon.pipeline.scan import depth_to_scan, scan_layout
from depthnav_daemon.sim.synthetic import Box, Scene, render
from drivers.base import Intrinsics

INTR = Intrinsics(320, 240, 290.0, 290.0, 159.5, 119.5)


def project(intr: Intrinsics, mount: Mount, fwd: np.ndarray, left: np.ndarray) -> np.ndarray:
    """(u, v) of floor points (fwd, left) in the level frame at the sensor's foot, (..., 2); NaN
    behind the camera."""
    t, r = math.radians(mount.tilt_deg), math.radians(mount.roll_deg)
    # a level-frame point relative to the optical centre, in camera axes before tilt and roll:
    # x_c = -left, y_c = +height (down), z_c = fwd; pitch down by t about x_c, then roll
    xc, yc, zc = -left, np.full_like(fwd, mount.height_m), fwd
    y1 = math.cos(t) * yc - math.sin(t) * zc
    z1 = math.sin(t) * yc + math.cos(t) * zc
    x2 = math.cos(r) * xc + math.sin(r) * y1
    y2 = -math.sin(r) * xc + math.cos(r) * y1
    with np.errstate(divide="ignore", invalid="ignore"):
        u = intr.fx * x2 / z1 + intr.cx
        v = intr.fy * y2 / z1 + intr.cy
    bad = z1 <= 0
    return np.stack([np.where(bad, np.nan, u), np.where(bad, np.nan, v)], axis=-1)


def reach(intr: Intrinsics, mount: Mount, bearing: float) -> tuple[float, float]:
    """Nearest and farthest floor range inside the image along ``bearing`` (0.5 mm steps up to
    60 m; (inf, 0) if none)."""
    r = np.arange(0.05, 60.0, 0.0005)
    uv = project(intr, mount, r * math.cos(bearing), r * math.sin(bearing))
    inside = (
        (uv[:, 0] >= -0.5)
        & (uv[:, 0] <= intr.width - 0.5)
        & (uv[:, 1] >= -0.5)
        & (uv[:, 1] <= intr.height - 0.5)
    )
    if not inside.any():
        return math.inf, 0.0
    return float(r[inside].min()), float(r[inside].max())


@pytest.mark.parametrize(
    "mount", [Mount(0.5, 15.0, 0.0), Mount(0.4, 30.0, 0.0), Mount(0.7, 22.0, 4.0)], ids=str
)
def test_floor_extent_matches_projection(mount: Mount) -> None:
    a0, inc, n = scan_layout(INTR, mount, ScanParams())
    near, far = floor_extent(INTR, mount, a0, inc, n, (0, -1, 1))
    checked = 0
    for b in range(2, n - 2, 7):
        lo, hi = reach(INTR, mount, a0 + b * inc)
        # a bin is +-inc/2 wide and its neighbours' centres bound it: conservative by at most
        # the change of reach over 1.5 bins
        lo_w = reach(INTR, mount, a0 + (b - 1.5) * inc)
        hi_w = reach(INTR, mount, a0 + (b + 1.5) * inc)
        if hi >= 59.0:  # the top rows look at the horizon: the floor is seen to the end
            assert far[b] > 50.0
            continue
        assert far[b] <= hi * 1.002 + 1e-3, (b, far[b], hi)  # never farther than the view
        if max(hi_w[1], lo_w[1]) < 10.0:  # grazing rows: half a pixel is metres of floor
            assert far[b] >= min(hi_w[1], lo_w[1]) * 0.98 - 0.01, (b, far[b], hi_w, lo_w)
        assert near[b] == pytest.approx(lo, rel=0.03, abs=0.01)
        checked += 1
    assert checked >= 3


def test_scan_says_nan_not_clear_where_the_view_is_short() -> None:
    """A steep camera sees the floor only to ~1.9 m: with range_max 4 m no bin may claim clear
    (+inf); with range_max 1.5 m the middle bins may."""
    mount = Mount(0.4, 30.0, 0.0)
    depth = render(Scene(), INTR, mount).depth_mm
    far_scan = depth_to_scan(depth, INTR, mount, ScanParams(range_max_m=4.0))
    assert not np.isposinf(far_scan.ranges).any()
    assert np.isnan(far_scan.ranges).all()
    short = depth_to_scan(depth, INTR, mount, ScanParams(range_max_m=1.5))
    a0, inc, n = scan_layout(INTR, mount, ScanParams(range_max_m=1.5))
    _, far = floor_extent(INTR, mount, a0, inc, n, (0, -1, 1))
    covered = seen_to(far, 1.5)
    assert covered.sum() > n // 2
    assert np.isposinf(short.ranges[covered]).all()
    assert np.isnan(short.ranges[~covered]).all()


def _top_row_reaching(intr: Intrinsics, height_m: float, floor_m: float) -> Mount:
    """A mount whose top image row meets the floor ``floor_m`` ahead on the optical axis' bearing
    (tilt = the ray's angle below the horizon plus the top row's angle above the axis)."""
    tilt = math.atan2(height_m, floor_m) + math.atan2(intr.cy, intr.fy)
    return Mount(height_m=height_m, tilt_deg=math.degrees(tilt))


@pytest.mark.parametrize("wall_m", [None, 4.9, 6.0])
def test_clear_needs_a_reading_at_range_max(wall_m: float | None) -> None:
    """+inf needs a pixel of the bin to read at or beyond range_max: the top row meets the floor
    5.2 m ahead, a wall at 4.9 m is met by that row 3 cm up (below the 5 cm band: not an obstacle,
    and its band is above the view). What the top row read ends at 4.9 m, so straight ahead is
    unknown (NaN), not clear; with no wall, or a wall beyond range_max (6 m), it is clear."""
    mount = _top_row_reaching(INTR, 0.5, 5.2)
    params = ScanParams()  # range_max 5 m, band from 5 cm
    boxes = () if wall_m is None else (Box(wall_m + 0.05, 0.0, 0.1, 20.0, 2.0),)
    depth = render(Scene(boxes=boxes), INTR, mount).depth_mm
    scan = depth_to_scan(depth, INTR, mount, params)
    a0, inc, n = scan_layout(INTR, mount, params)
    ahead = np.abs(a0 + inc * np.arange(n)) < math.radians(5.0)
    # the wall's band (5 cm up) at 4.9 m projects above the top row: nothing there to see
    uv = project(INTR, mount, np.array([4.9]), np.array([0.0]))
    assert uv[0, 1] > 0.0  # its foot is in view; 3 cm up is row ~0: the geometry is as stated
    r = scan.ranges[ahead]
    if wall_m == 4.9:
        assert np.isnan(r).all(), r
    else:
        assert np.isposinf(r).all(), r


def test_clear_needs_readings_where_the_top_rows_read_nothing() -> None:
    """The same empty floor with the upper half of the image unread (no return, as a structured
    light sensor far away): every bin's readings end short of range_max, nothing is clear."""
    mount = _top_row_reaching(INTR, 0.5, 7.0)
    depth = render(Scene(), INTR, mount).depth_mm.copy()
    full = depth_to_scan(depth, INTR, mount, ScanParams()).ranges
    assert np.isposinf(full).sum() > 0.5 * full.size
    depth[: INTR.height // 2] = 0
    ranges = depth_to_scan(depth, INTR, mount, ScanParams()).ranges
    assert not np.isposinf(ranges).any()
    assert np.isnan(ranges).all()


def test_cliff_clear_needs_readings_in_its_highest_rows() -> None:
    """The cliff scan says "no drop-off" (+inf) on a bin only if the highest rows it reads there
    have readings: a hole whose lower floor returns nothing (out of the sensor's reach) shows as
    zeros in the rows above its edge, and the floor there is unknown (NaN), not clear."""
    mount = Mount(height_m=0.5, tilt_deg=20.0)  # row 80 meets the floor 5.3 m ahead
    params = CliffParams()  # reads the bottom 400 rows of 480, floor from 0.5 to 5 m
    intr = Intrinsics(640, 480, 580.0, 580.0, 319.5, 239.5)
    layout = scan_layout(intr, mount, ScanParams())
    depth = render(Scene(), intr, mount).depth_mm.copy()
    clear = detect_cliffs(depth, intr, mount, params, *layout).scan.ranges
    assert np.isposinf(clear).sum() > 0.5 * clear.size
    top = intr.height - params.used_depth_height
    depth[: top + 3 * params.block_size] = 0  # the highest rows read: nothing came back
    ranges = detect_cliffs(depth, intr, mount, params, *layout).scan.ranges
    assert not np.isposinf(ranges).any()
    assert np.isnan(ranges).all()
