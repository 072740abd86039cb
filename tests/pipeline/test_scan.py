"""The scan stage against the scene generator's exact ground truth."""

from __future__ import annotations

import math

import numpy as np
import pytest

from depthnav_daemon.errors import ConfigError, FrameError
from depthnav_daemon.pipeline.geometry import Mount
from depthnav_daemon.pipeline.scan import LaserScan, ScanParams, depth_to_scan
from depthnav_daemon.sim.synthetic import (
    LABEL_BOX0,
    Box,
    KinectNoise,
    Scene,
    SyntheticView,
    render,
    truth_obstacle_interval,
)
from drivers.base import Intrinsics
from tests.pipeline.scenes import ASYM_640, random_boxes_in_view

PARAMS = ScanParams(
    range_min_m=0.1, range_max_m=5.0, min_obstacle_height_m=0.05, max_obstacle_height_m=2.0
)


def seen_bins(view: SyntheticView, scan: LaserScan, params: ScanParams) -> np.ndarray:
    """Bins whose bearing some box pixel (in the height and range band) actually shows, (N,)
    bool."""
    pts = view.points_m
    box = view.label >= LABEL_BOX0
    h = view.height_m
    r = np.hypot(pts[..., 0], pts[..., 1])
    ok = (
        box
        & (h >= params.min_obstacle_height_m + 0.005)
        & (h <= params.max_obstacle_height_m)
        & (r >= params.range_min_m)
        & (r <= params.range_max_m)
    )
    bearing = np.arctan2(pts[..., 1][ok], pts[..., 0][ok])
    idx = np.floor((bearing - scan.angle_min) / scan.angle_increment + 0.5).astype(int)
    out = np.zeros(scan.ranges.size, dtype=bool)
    out[idx[(idx >= 0) & (idx < out.size)]] = True
    return out


def check_against_truth(
    view: SyntheticView, scan: LaserScan, params: ScanParams, rel_tol: float, abs_tol: float
) -> int:
    """Assert every bin that sees a box is within tolerance, and no other bin reports an
    obstacle."""
    half = scan.angle_increment * 1.5  # the bin plus the half-pixel footprint on either side
    lo, hi = truth_obstacle_interval(
        view.scene, scan.angles, half, params.min_obstacle_height_m, params.max_obstacle_height_m
    )
    seen = seen_bins(view, scan, params)
    covered = seen & np.isfinite(hi)  # the box fills the bin's whole footprint
    got = scan.ranges.astype(np.float64)
    assert np.all(np.isfinite(got[covered])), (
        f"box bins without a range: {np.flatnonzero(covered & ~np.isfinite(got))}"
    )
    tol = abs_tol + rel_tol * hi[covered]
    err_lo = lo[covered] - tol - got[covered]
    err_hi = got[covered] - hi[covered] - tol
    assert err_lo.max(initial=-1) <= 0 and err_hi.max(initial=-1) <= 0, (
        f"worst error {max(err_lo.max(initial=0), err_hi.max(initial=0)) + tol.max():.4f} m"
    )
    # no bin away from every box may report an obstacle (the floor must be removed)
    floor_only = ~np.isfinite(lo)
    false = floor_only & np.isfinite(got)
    assert not false.any(), (
        f"floor reported as obstacle at bins {np.flatnonzero(false)[:10]} ranges {got[false][:10]}"
    )
    return int(covered.sum())


def mounts(n: int, seed: int) -> list[Mount]:
    rng = np.random.default_rng(seed)
    out = [
        Mount(0.3, 0.0, 0.0),
        Mount(1.5, 60.0, 10.0),
        Mount(0.3, 60.0, -10.0),
        Mount(1.5, 0.0, -10.0),
    ]
    while len(out) < n:
        out.append(Mount(rng.uniform(0.3, 1.5), rng.uniform(0, 60), rng.uniform(-10, 10)))
    return out


@pytest.mark.parametrize(
    "mount",
    mounts(14, seed=2),
    ids=lambda m: f"h{m.height_m:.2f}_t{m.tilt_deg:.0f}_r{m.roll_deg:.0f}",
)
def test_exact_scan_noise_free_within_1cm(mount: Mount) -> None:
    rng = np.random.default_rng(int(mount.height_m * 1000 + mount.tilt_deg * 10))
    scene = random_boxes_in_view(rng, ASYM_640, mount, count=3, min_range_m=PARAMS.range_min_m)
    assert scene.boxes, "the scene builder found no floor in view"
    view = render(scene, ASYM_640, mount, min_range_m=0.05)
    scan = depth_to_scan(view.depth_mm, ASYM_640, mount, PARAMS)
    assert check_against_truth(view, scan, PARAMS, rel_tol=0.0, abs_tol=0.01) > 0


@pytest.mark.parametrize(
    "mount",
    mounts(8, seed=3),
    ids=lambda m: f"h{m.height_m:.2f}_t{m.tilt_deg:.0f}_r{m.roll_deg:.0f}",
)
def test_exact_scan_with_kinect_noise_within_3_percent(mount: Mount) -> None:
    rng = np.random.default_rng(7 + int(mount.tilt_deg))
    scene = random_boxes_in_view(rng, ASYM_640, mount, count=3, min_range_m=PARAMS.range_min_m)
    view = render(scene, ASYM_640, mount, KinectNoise(), rng, min_range_m=0.05)
    scan = depth_to_scan(view.depth_mm, ASYM_640, mount, PARAMS)
    assert check_against_truth(view, scan, PARAMS, rel_tol=0.03, abs_tol=0.0) > 0


@pytest.mark.parametrize(
    "size",
    [(320, 240), (512, 424), (640, 480), (848, 480), (1280, 720)],
    ids=lambda s: f"{s[0]}x{s[1]}",
)
def test_exact_scan_any_resolution(size: tuple[int, int]) -> None:
    intr = ASYM_640.scaled(*size)
    mount = Mount(0.6, 20.0, 3.0)
    scene = Scene(boxes=(Box(1.6, 0.25, 0.3, 0.4, 0.3), Box(2.4, -0.6, 0.4, 0.3, 0.5, yaw_deg=20)))
    view = render(scene, intr, mount)
    scan = depth_to_scan(view.depth_mm, intr, mount, PARAMS)
    assert check_against_truth(view, scan, PARAMS, rel_tol=0.0, abs_tol=0.01) > 10


def test_exact_scan_has_no_empty_bins_from_binning() -> None:
    """A wall across the view fills every bin that sees it, at any tilt and roll (the original
    leaves gaps)."""
    wall_params = ScanParams(range_min_m=0.1, max_obstacle_height_m=3.0)
    for mount in (Mount(0.5, 0.0, 0.0), Mount(1.2, 45.0, 8.0), Mount(0.3, 10.0, -10.0)):
        view = render(Scene(boxes=(Box(1.5, 0.0, 0.2, 40.0, 3.0),)), ASYM_640, mount)
        scan = depth_to_scan(view.depth_mm, ASYM_640, mount, wall_params)
        seen = seen_bins(view, scan, wall_params)
        # every bin between the first and last one the wall shows must hold a range: no holes
        first, last = np.flatnonzero(seen)[[0, -1]]
        inner = slice(first, last + 1)
        assert np.isfinite(scan.ranges[inner]).all(), (
            f"{mount}: {np.flatnonzero(~np.isfinite(scan.ranges[inner]))}"
        )
        np.testing.assert_allclose(scan.ranges[inner], 1.4 / np.cos(scan.angles[inner]), atol=0.01)
        if mount.tilt_deg == 0 and mount.roll_deg == 0:
            assert np.isfinite(scan.ranges).all()


def test_scan_values_follow_rep117() -> None:
    """+inf where valid readings show no obstacle, NaN where there is no reading, -inf too close."""
    mount = Mount(0.5, 20.0, 0.0)
    view = render(Scene(), ASYM_640, mount)
    depth = view.depth_mm.copy()
    depth[:, :100] = 0  # the left of the image sees nothing
    scan = depth_to_scan(depth, ASYM_640, mount, PARAMS)
    pts = view.points_m[:, 100:]
    widest_valid = np.nanmax(np.arctan2(pts[..., 1], pts[..., 0]))
    left = scan.angles > widest_valid + 2 * scan.angle_increment
    assert left.sum() > 10 and np.isnan(scan.ranges[left]).all()
    # +inf on the bearings where the view reaches the floor out to range_max, NaN at its edge
    # where it does not (the bottom corners of a tilted image reach wide bearings only near by)
    pts_all = view.points_m[:, 100:][view.height_m[:, 100:] > -1.0]
    rng = np.hypot(pts_all[:, 0], pts_all[:, 1])
    bear = np.arctan2(pts_all[:, 1], pts_all[:, 0])
    far_side = bear[rng > PARAMS.range_max_m + 0.1].min()  # widest bearing seen far enough
    inner = scan.angles < widest_valid - 0.3
    assert np.isposinf(scan.ranges[inner & (scan.angles > far_side + 0.05)]).all()
    assert np.isnan(scan.ranges[inner & (scan.angles < far_side - 0.05)]).all()
    near = render(
        Scene(boxes=(Box(0.55, 0.0, 0.2, 3.0, 1.0),)),
        ASYM_640,
        Mount(0.5, 0.0, 0.0),
        min_range_m=0.05,
    )
    close = depth_to_scan(
        near.depth_mm, ASYM_640, Mount(0.5, 0.0, 0.0), ScanParams(range_min_m=0.6)
    )
    assert np.isneginf(close.ranges).sum() > 0.8 * close.ranges.size


def test_float_metres_input_equals_uint16_millimetres() -> None:
    mount = Mount(0.7, 25.0, 2.0)
    view = render(Scene(boxes=(Box(2.0, 0.0, 0.4, 0.4, 0.3),)), ASYM_640, mount)
    metres = np.where(view.depth_mm > 0, view.depth_mm / 1000.0, np.nan).astype(np.float32)
    for method in ("exact", "paper"):
        p = ScanParams(method=method)
        a = depth_to_scan(view.depth_mm, ASYM_640, mount, p).ranges
        b = depth_to_scan(metres, ASYM_640, mount, p).ranges
        np.testing.assert_allclose(a, b, rtol=1e-6, equal_nan=True)


# --- the paper's method ---------------------------------------------------------------------------


def paper_reference(
    depth_mm: np.ndarray, intr: Intrinsics, h: float, tilt_deg: float, p: ScanParams
) -> list[float]:
    """Eq. 1-5 evaluated pixel by pixel with the math module, independent of the vectorised code."""
    a = math.radians(tilt_deg)
    fov = math.atan(intr.cy / intr.fy) + math.atan((intr.height - 1 - intr.cy) / intr.fy)
    amax = math.atan(intr.cx / intr.fx)
    amin = -math.atan((intr.width - 1 - intr.cx) / intr.fx)
    inc = (amax - amin) / (intr.width - 1)
    out = [math.nan] * intr.width
    offset = int(intr.cy - p.scan_height / 2.0)
    for i in range(intr.width):
        best, seen = math.inf, False
        for j in range(offset, offset + p.scan_height, p.depth_img_row_step):
            if depth_mm[j, i] == 0:
                continue
            seen = True
            z = depth_mm[j, i] / 1000.0
            delta = fov * (j - intr.cy - 0.5) / (intr.height - 1)  # eq. 3
            if not p.range_min_m <= z <= p.range_max_m:
                continue
            if p.ground_remove and math.sin(delta + a) > 0:
                ground = (
                    h * math.sin(math.pi / 2 - delta) / math.cos(math.pi / 2 - delta - a)
                )  # eq. 5
                if z >= ground - p.ground_margin_m:
                    continue
            d = (
                z * math.sin(math.pi / 2 - a - delta) / math.sin(math.pi / 2 - delta)
                if p.tilt_compensation
                else z
            )  # eq. 4
            best = min(best, d)  # eq. 1
        x = (i - intr.cx) / intr.fx * best  # eq. 2
        r = math.hypot(x, best) if math.isfinite(best) else (math.inf if seen else math.nan)
        k = int((-math.atan((i - intr.cx) / intr.fx) - amin) / inc)
        out[k] = r  # laserscan_kinect's ranges[index[u]] = r: later columns overwrite
    return out


@pytest.mark.parametrize("features", [(True, True), (False, False), (True, False)])
def test_paper_scan_matches_independent_eq_1_to_5(features: tuple[bool, bool]) -> None:
    intr = Intrinsics(160, 120, 145.0, 139.0, 83.0, 57.0)
    h, tilt = 0.8, 30.0
    mount = Mount(h, tilt, 0.0)
    rng = np.random.default_rng(5)
    scene = random_boxes_in_view(rng, intr, mount, count=3)
    view = render(scene, intr, mount, KinectNoise(), rng)
    p = ScanParams(
        method="paper",
        scan_height=100,
        depth_img_row_step=2,
        ground_remove=features[0],
        tilt_compensation=features[1],
    )
    got = depth_to_scan(view.depth_mm, intr, mount, p).ranges
    want = np.array(paper_reference(view.depth_mm, intr, h, tilt, p))
    np.testing.assert_allclose(got, want, rtol=2e-6, atol=2e-6, equal_nan=True)


def test_paper_scan_keeps_the_originals_empty_bins() -> None:
    """The original's truncating column->bin map leaves NaN bins even on a full wall (for
    comparison)."""
    mount = Mount(0.5, 0.0, 0.0)
    view = render(Scene(boxes=(Box(1.5, 0.0, 0.2, 40.0, 3.0),)), ASYM_640, mount)
    scan = depth_to_scan(view.depth_mm, ASYM_640, mount, ScanParams(method="paper"))
    assert 0 < np.isnan(scan.ranges).sum() < 0.1 * scan.ranges.size


# --- bad input ------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("depth", "match"),
    [
        (np.zeros((480, 640), np.float64), "dtype float64"),
        (np.zeros((480, 640), np.int32), "dtype int32"),
        (np.zeros((640, 480), np.uint16), r"shape \(640, 480\) does not match"),
        (np.zeros((480, 640, 1), np.uint16), "shape"),
        ([[1, 2]], "numpy array"),
    ],
)
def test_bad_frames_give_one_line_errors(depth: object, match: str) -> None:
    with pytest.raises(FrameError, match=match) as info:
        depth_to_scan(depth, ASYM_640, Mount(), ScanParams())  # type: ignore[arg-type]
    assert "\n" not in str(info.value)


@pytest.mark.parametrize(
    ("make", "match"),
    [
        (lambda: Mount(height_m=-0.5), r"height_m=-0.5 is out of range \(accepted: 0.01..10 m\)"),
        (lambda: Mount(tilt_deg=95), r"tilt_deg=95 is out of range \(accepted: -89..89 deg\)"),
        (lambda: Mount(roll_deg=float("nan")), "roll_deg=nan"),
        (lambda: ScanParams(method="fast"), "accepted: exact, paper"),
        (lambda: ScanParams(range_min_m=5, range_max_m=1), "must be below"),
        (
            lambda: ScanParams(row_step=0),
            r"row_step=0 is out of range \(accepted: integers 1..64\)",
        ),
        (lambda: ScanParams(min_obstacle_height_m=0.5, max_obstacle_height_m=0.1), "must be below"),
    ],
)
def test_nonsense_parameters_name_the_value_and_range(make, match: str) -> None:
    with pytest.raises(ConfigError, match=match):
        make()


def test_paper_band_too_tall_for_image_is_a_config_error() -> None:
    small = Intrinsics(320, 240, 290.0, 280.0, 160.0, 118.0)
    with pytest.raises(ConfigError, match=r"scan_height=400 is too large .* \(accepted: 1..236\)"):
        depth_to_scan(np.ones((240, 320), np.uint16), small, Mount(), ScanParams(method="paper"))


def test_all_zero_frame_gives_all_nan_scan() -> None:
    """No reading anywhere is a defined result, not a crash: every bin is NaN (no data)."""
    for method in ("exact", "paper"):
        scan = depth_to_scan(
            np.zeros((480, 640), np.uint16), ASYM_640, Mount(), ScanParams(method=method)
        )
        assert np.isnan(scan.ranges).all()
    nan_frame = np.full((480, 640), np.nan, np.float32)
    assert np.isnan(depth_to_scan(nan_frame, ASYM_640, Mount(), ScanParams()).ranges).all()


def test_paper_scan_keeps_the_later_column_where_two_share_a_bin() -> None:
    # laserscan_kinect writes ranges[index[u]] = r for u = 0..W-1: the later column overwrites
    intr = ASYM_640
    amax = math.atan(intr.cx / intr.fx)
    amin = -math.atan((intr.width - 1 - intr.cx) / intr.fx)
    inc = (amax - amin) / (intr.width - 1)
    index = [int((-math.atan((u - intr.cx) / intr.fx) - amin) / inc) for u in range(intr.width)]
    pairs = [(u, u + 1) for u in range(intr.width - 1) if index[u] == index[u + 1]]
    assert pairs  # the truncating map sends two columns into one bin near the edges
    u1, u2 = pairs[0]
    depth = np.zeros((intr.height, intr.width), np.uint16)
    depth[:, u1] = 1000  # the nearer column comes first ...
    depth[:, u2] = 3000  # ... and the farther one last: the original keeps this one
    p = ScanParams(method="paper", ground_remove=False, tilt_compensation=False)
    scan = depth_to_scan(depth, intr, Mount(0.5, 0.0, 0.0), p)
    want = 3.0 * math.hypot(1.0, (u2 - intr.cx) / intr.fx)
    assert scan.ranges[index[u2]] == pytest.approx(want, rel=1e-6)
