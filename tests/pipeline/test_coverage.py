"""The view's reach on the floor per bin (coverage.floor_extent) against a projection written
here from the conventions (camera x right, y down, z forward; tilt positive down; roll about the
forward axis, left side up), not from the stage's rotations."""

from __future__ import annotations

import math

import numpy as np
import pytest

from depthnav_daemon.pipeline.coverage import floor_extent, seen_to
from depthnav_daemon.pipeline.geometry import Mount
from depthnav_daemon.pipeline.params import ScanParams
from depthnav_daemon.pipeline.scan import depth_to_scan, scan_layout
from depthnav_daemon.sim.synthetic import Scene, render
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
