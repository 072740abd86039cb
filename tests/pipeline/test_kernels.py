"""Compiled kernels against plain numpy references: bit-exact values, identical NaN/inf patterns.

The stages' accuracy tests check the physics; these check that each fast kernel computes exactly
what a slow, obvious implementation of the same definition computes. No timings here (the bench
reports speed).
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from depthnav_daemon.pipeline import cliff_table, pose_kernels, scan_table
from depthnav_daemon.pipeline import pose_fit as pose_mod
from depthnav_daemon.pipeline import scan as scan_mod
from depthnav_daemon.pipeline.cliff import CliffParams, detect_cliffs
from depthnav_daemon.pipeline.geometry import Mount, cam_to_level
from depthnav_daemon.pipeline.pose import PoseParams, estimate_pose
from depthnav_daemon.pipeline.scan import ScanParams, depth_to_scan
from depthnav_daemon.sim.synthetic import Box, KinectNoise, Scene, render, step_down
from drivers.base import KINECT_V1, Intrinsics

MOUNTS = [
    Mount(0.55, 15.0, 0.0),
    Mount(0.5, 0.0, 0.0),
    Mount(0.5, 30.0, 5.0),
    Mount(1.0, 45.0, -8.0),
    Mount(0.3, 60.0, 10.0),
]
SMALL = Intrinsics(200, 150, 180.0, 181.0, 97.3, 77.9)


def noisy_frame(intr: Intrinsics, mount: Mount, seed: int) -> np.ndarray:
    """A corridor-like frame with noise, zero pixels, a near box and a step down, uint16 mm."""
    scene = Scene(
        boxes=(
            Box(0.3, 0.05, 0.2, 0.2, 0.4),
            Box(1.5, 0.4, 0.3, 0.3, 0.3),
            Box(2.2, -0.5, 0.4, 0.4, 0.6, yaw_deg=20),
            Box(4.0, 0.0, 0.1, 6.0, 2.5),
        ),
        holes=(step_down(3.0, 0.18),),
    )
    return render(
        scene, intr, mount, KinectNoise(), np.random.default_rng(seed), min_range_m=0.05
    ).depth_mm


def floor_range_m(intr: Intrinsics, mount: Mount, v: np.ndarray, u: np.ndarray) -> np.ndarray:
    """Horizontal range (m) of the floor point of pixels (v rows (R, 1), u columns (1, C)), +inf
    at or above the horizon, from the conventions (camera x right, y down, z forward; roll left
    side up about forward, then tilt positive down), not from the stage's tables."""
    x, y = (u - intr.cx) / intr.fx + 0.0 * v, (v - intr.cy) / intr.fy + 0.0 * u
    t, r = mount.tilt_rad, mount.roll_rad
    x1, y1 = math.cos(r) * x - math.sin(r) * y, math.sin(r) * x + math.cos(r) * y  # rolled
    fwd, down = math.cos(t) - math.sin(t) * y1, math.sin(t) + math.cos(t) * y1  # pitched
    with np.errstate(divide="ignore", invalid="ignore"):
        k = np.where(down > 0, mount.height_m / down, np.inf)
        return np.where(np.isfinite(k), k * np.hypot(fwd, x1), np.inf)


def reference_exact_scan(
    depth: np.ndarray, intr: Intrinsics, mount: Mount, params: ScanParams
) -> np.ndarray:
    """The exact scan by its definition: per row, each bin takes the min over its columns (numpy).

    Uses the stage's per-pixel thresholds and bin map (what the scan *means*), not its kernel
    tables.
    """
    t = scan_table.exact_table(intr, mount, params)
    rows = scan_table.scan_rows(intr, params)
    cols = slice(0, intr.width, params.col_step)
    v = np.arange(intr.height, dtype=np.float64)[rows][:, None]
    u = np.arange(intr.width, dtype=np.float64)[cols][None, :]
    rot = cam_to_level(mount.tilt_rad, mount.roll_rad)
    half = params.col_step / 2.0
    b_l = scan_table._bearing(intr, rot, u - half, v)
    b_r = scan_table._bearing(intr, rot, u + half, v)
    lo_b, hi_b = np.minimum(b_l, b_r), np.maximum(b_l, b_r)
    centre = scan_table._bearing(intr, rot, u + 0.0 * v, v + 0.0 * u)
    g_lo, g_hi, _, _ = scan_table._bin_map(
        centre, lo_b, hi_b, (hi_b - lo_b) < math.pi, t.angle_min, t.angle_increment, t.n_bins
    )
    d = depth[rows][:, cols]
    obstacle = (d >= t.zlo_mm) & (d <= t.zhi_mm)
    close = (d >= t.near_lo_mm) & (d <= t.near_hi_mm)
    val = np.where(obstacle, d.astype(np.float32) * t.kr_m_per_mm, np.float32(np.inf)).astype(
        np.float32
    )
    val[close] = -np.inf
    val_range = d.astype(np.float32) * t.kr_m_per_mm  # horizontal range of every reading
    fl = floor_range_m(intr, mount, v, u)  # of every pixel's floor point
    ws = d.shape[1]
    out = np.full(t.n_bins, np.inf, dtype=np.float32)
    seen = np.zeros(t.n_bins, dtype=bool)
    blocked = np.zeros(t.n_bins, dtype=bool)
    for i in range(d.shape[0]):
        for b in np.flatnonzero(g_lo[i] < ws):
            c0, c1 = int(g_lo[i, b]), int(min(g_hi[i, b], ws - 1))
            out[b] = min(out[b], val[i, c0 : c1 + 1].min())
    # +inf only where one of the bin's runs asked (the table's runs: a column's rows feeding the
    # same bins) reads at or beyond range_max at its last row whose floor point lies 2 % beyond
    # range_max (this file's projection; the margin covers depth rounding and noise): that ray
    # was seen free that far; and none of them reads something nearer there
    rm = np.float32(params.range_max_m)
    reach_m = params.range_max_m * 1.02
    for b in range(t.n_bins):
        asked = []  # the runs that look that far; the first, middle and last of them are asked
        for c, r0, r1 in t.probe[:, t.probe_start[b] : t.probe_start[b + 1]].T.astype(int):
            lim = r0 - 1
            while lim + 1 <= r1 and fl[lim + 1, c] >= reach_m:
                lim += 1
            if lim >= r0:
                asked.append((lim, c))
        for lim, c in {asked[0], asked[len(asked) // 2], asked[-1]} if asked else ():
            seen[b] |= bool(d[lim, c] != 0 and val_range[lim, c] >= rm)
            blocked[b] |= bool(d[lim, c] != 0 and val_range[lim, c] < rm)
    out[(out == np.inf) & (~seen | blocked)] = np.nan
    # the view's reach (coverage.floor_extent, tested on its own in test_coverage): a bin whose
    # floor is not seen to range_max says NaN where it found nothing
    short = np.zeros(t.n_bins, dtype=bool)
    short[t.short_view] = True
    out[(out == np.inf) & short] = np.nan
    return out


@pytest.mark.parametrize("mount", MOUNTS, ids=lambda m: f"t{m.tilt_deg:g}_r{m.roll_deg:g}")
@pytest.mark.parametrize(
    "params",
    [
        ScanParams(),
        ScanParams(range_min_m=0.4, row_start=20, row_stop=140, row_step=3, col_step=2),
        ScanParams(range_min_m=0.0, min_obstacle_height_m=-0.2, angle_increment_deg=0.9),
    ],
    ids=["defaults", "strided", "coarse_bins"],
)
def test_exact_scan_kernel_equals_per_row_binning(mount: Mount, params: ScanParams) -> None:
    depth = noisy_frame(SMALL, mount, seed=int(mount.tilt_deg))
    got = depth_to_scan(depth, SMALL, mount, params).ranges
    want = reference_exact_scan(depth, SMALL, mount, params)
    assert np.array_equal(np.isnan(got), np.isnan(want))
    assert np.array_equal(np.isposinf(got), np.isposinf(want))
    assert np.array_equal(np.isneginf(got), np.isneginf(want))
    assert np.array_equal(got, want, equal_nan=True)


@pytest.mark.parametrize("mount", MOUNTS, ids=lambda m: f"t{m.tilt_deg:g}_r{m.roll_deg:g}")
@pytest.mark.parametrize(
    "params",
    [
        ScanParams(),
        ScanParams(range_min_m=0.0, min_obstacle_height_m=-0.2, max_obstacle_height_m=0.3),
        ScanParams(
            range_min_m=3.0, range_max_m=60.0, min_obstacle_height_m=-9.0, max_obstacle_height_m=9.0
        ),
    ],
    ids=["defaults", "low_band", "far"],
)
def test_three_kernel_thresholds_classify_every_depth_as_the_four(
    mount: Mount, params: ScanParams
) -> None:
    t = scan_table.exact_table(SMALL, mount, params)
    # every depth at and around every threshold, and the ends of the uint16 range
    edges = np.stack([t.zlo_mm, t.zhi_mm, t.near_lo_mm, t.near_hi_mm]).astype(np.int64)
    for delta in (-1, 0, 1):
        for raw in [*(edges + delta), np.zeros_like(edges[0]), np.full_like(edges[0], 65535)]:
            d = np.clip(raw, 0, 65535)
            close = (t.near_lo_mm <= d) & (d <= t.near_hi_mm)
            obstacle = (t.zlo_mm <= d) & (d <= t.zhi_mm) & ~close
            assert np.array_equal((t.k_lo <= d) & (d <= t.k_mid), close)
            assert np.array_equal((t.k_mid < d) & (d <= t.k_hi), obstacle)


def numpy_bin_map(
    centre: np.ndarray,
    lo_b: np.ndarray,
    hi_b: np.ndarray,
    sane: np.ndarray,
    angle_min: float,
    inc: float,
    n: int,
) -> tuple[np.ndarray, ...]:
    """The bin map as numpy computed it before it was compiled (the reference for
    bin_map_kernel)."""
    hs, ws = centre.shape
    bidx = np.floor((centre - angle_min) / inc + 0.5).astype(np.int64)
    ii, jj = np.nonzero(sane)
    bb = np.clip(bidx[ii, jj], 0, n - 1)
    flat = ii * n + bb
    g_lo = np.full(hs * n, ws, dtype=np.int64)
    g_hi = np.full(hs * n, -1, dtype=np.int64)
    np.minimum.at(g_lo, flat, jj)
    np.maximum.at(g_hi, flat, jj)
    cb_lo = np.full((hs, ws), n, dtype=np.int64)
    cb_hi = np.full((hs, ws), -1, dtype=np.int64)
    cb_lo[ii, jj] = bb
    cb_hi[ii, jj] = bb
    g_lo = g_lo.reshape(hs, n)
    g_hi = g_hi.reshape(hs, n)
    centres = angle_min + inc * np.arange(n)
    for i in range(hs):
        ok = sane[i]
        if not ok.any():
            continue
        cols = np.flatnonzero(ok)[::-1]
        lo_r, hi_r = lo_b[i][cols], hi_b[i][cols]
        empty = np.flatnonzero(g_hi[i] < 0)
        k = np.searchsorted(lo_r, centres[empty], side="right") - 1
        kk = np.clip(k, 0, cols.size - 1)
        hit = (k >= 0) & (centres[empty] <= hi_r[kk])
        b_hit, c_hit = empty[hit], cols[kk[hit]]
        g_lo[i, b_hit] = c_hit
        g_hi[i, b_hit] = c_hit
        np.minimum.at(cb_lo[i], c_hit, b_hit)
        np.maximum.at(cb_hi[i], c_hit, b_hit)
    g_hi = np.where(g_hi < 0, ws, g_hi)
    return (
        g_lo.astype(np.int16),
        g_hi.astype(np.int16),
        cb_lo.astype(np.int16),
        cb_hi.astype(np.int16),
    )


@pytest.mark.parametrize(
    "mount", [*MOUNTS, Mount(1.2, 85.0, 30.0)], ids=lambda m: f"t{m.tilt_deg:g}_r{m.roll_deg:g}"
)
@pytest.mark.parametrize("col_step", [1, 3])
def test_bin_map_kernel_equals_numpy(mount: Mount, col_step: int) -> None:
    intr = SMALL
    v = np.arange(intr.height, dtype=np.float64)[:, None]
    u = np.arange(intr.width, dtype=np.float64)[::col_step][None, :]
    rot = cam_to_level(mount.tilt_rad, mount.roll_rad)
    half = col_step / 2.0
    b_l = scan_table._bearing(intr, rot, u - half, v)
    b_r = scan_table._bearing(intr, rot, u + half, v)
    lo_b, hi_b = np.minimum(b_l, b_r), np.maximum(b_l, b_r)
    centre = scan_table._bearing(intr, rot, u + 0.0 * v, v + 0.0 * u)
    sane = (hi_b - lo_b) < math.pi
    inc = float(np.median(hi_b - lo_b))
    angle_min = float(lo_b[sane].min()) + inc / 2
    n = math.ceil((float(hi_b[sane].max()) - float(lo_b[sane].min())) / inc)
    got = scan_table._bin_map(centre, lo_b, hi_b, sane, angle_min, inc, n)
    want = numpy_bin_map(centre, lo_b, hi_b, sane, angle_min, inc, n)
    for g, w in zip(got, want, strict=True):
        np.testing.assert_array_equal(g, w)


@pytest.mark.parametrize("mount", [Mount(0.5, 85.0, -10.0), Mount(0.5, 80.0, 3.0)])
def test_exact_scan_pixels_feeding_no_bin_leak_into_no_run(mount: Mount) -> None:
    # looking down past the vertical, footprints that straddle the +-pi seam feed no bin; their
    # readings must not reach the next run of their column
    t = scan_table.exact_table(SMALL, mount, ScanParams())
    assert ((t.fl_code >> 16) == t.n_bins).any()  # the case exists for these mounts
    rng = np.random.default_rng(7)
    for depth in (
        noisy_frame(SMALL, mount, seed=11),
        rng.integers(0, 4000, size=(SMALL.height, SMALL.width)).astype(np.uint16),
    ):
        got = depth_to_scan(depth, SMALL, mount, ScanParams()).ranges
        assert np.array_equal(
            got, reference_exact_scan(depth, SMALL, mount, ScanParams()), equal_nan=True
        )


def test_exact_scan_kernel_full_resolution_bit_exact() -> None:
    mount = MOUNTS[0]
    depth = noisy_frame(KINECT_V1, mount, seed=3)
    params = ScanParams()
    got = depth_to_scan(depth, KINECT_V1, mount, params).ranges
    assert np.array_equal(
        got, reference_exact_scan(depth, KINECT_V1, mount, params), equal_nan=True
    )


def test_exact_scan_reads_a_read_only_strided_frame() -> None:
    mount = MOUNTS[2]
    depth = noisy_frame(SMALL, mount, seed=5)
    ro = depth.copy()
    ro.setflags(write=False)
    params = ScanParams(col_step=3)
    assert np.array_equal(
        depth_to_scan(ro, SMALL, mount, params).ranges,
        depth_to_scan(depth, SMALL, mount, params).ranges,
        equal_nan=True,
    )


def test_exact_scan_kernel_compiles_without_masked_loads_or_stores() -> None:
    """The kernel's pixel loops read the range table whatever the depth and store every
    running minimum: LLVM otherwise emits masked loads and stores (vmaskmovps), ~2.4x slower
    on AMD Zen (the store form is microcoded). Checked in the machine code, not by timing; a
    CPU without AVX has no masked forms to emit."""
    from numba import njit

    from depthnav_daemon.pipeline import scan_kernels

    mount = MOUNTS[0]
    depth = noisy_frame(SMALL, mount, seed=2)
    depth_to_scan(depth, SMALL, mount, ScanParams())
    compiled = scan_kernels.exact_scan_kernel
    sig = compiled.signatures[0]
    # a fresh, uncached copy: numba shows no machine code for a kernel loaded from its cache
    options = {k: v for k, v in compiled.targetoptions.items() if k != "nopython"}
    fresh = njit(**options)(compiled.py_func)
    fresh.compile(sig)
    asm = fresh.inspect_asm(sig)
    if "ymm" not in asm:
        pytest.skip("this CPU has no AVX: no masked vector forms to guard against")
    assert "maskmov" not in asm


def reference_cliffs(
    depth: np.ndarray,
    intr: Intrinsics,
    mount: Mount,
    params: CliffParams,
    layout: tuple[float, float, int],
) -> tuple[np.ndarray, np.ndarray]:
    """Eq. 7-8 and the cliff scan by their definition (numpy).

    Returns:
        (found blocks (nbr, nbc) bool, cliff scan (n,) float32).
    """
    t = cliff_table.cliff_table(intr, mount, params, *layout)
    rows = np.sort(t.rows)[::-1]  # bottom-up: block row 0 (the lowest) first, as the original
    assert np.array_equal(np.sort(t.rows), np.unique(t.rows))
    bottom_up = np.argsort(-t.rows, kind="stable")
    lo_mm, hi_mm, range_m = t.lo_mm[bottom_up], t.hi_mm, t.range_m[bottom_up]
    d = depth[np.ix_(rows, t.cols)]
    mask = (d > lo_mm) & (d < hi_mm)
    counts = mask.reshape(t.shape4).sum(axis=(1, 3))
    found = (counts >= params.block_points_thresh) & np.isfinite(t.block_xy_m[..., 0])
    if params.method == "exact":
        # the exact method refines detected blocks to the edge per column: its plain-Python
        # definition lives with the edge tests
        from tests.pipeline.test_cliff_edges import reference_edges

        return found, reference_edges(depth, intr, mount, params, layout)[0]
    marked = (mask.reshape(t.shape4) & found[:, None, :, None]).reshape(mask.shape)
    vals = np.where(marked, range_m, np.where(d > 0, np.float32(np.inf), np.float32(np.nan)))
    # every sample covers the bins between its col_step footprint's edges
    rot = cam_to_level(mount.tilt_rad, mount.roll_rad)
    u = t.cols.astype(np.float64)[None, :]
    v = rows.astype(np.float64)[:, None]
    e = params.col_step / 2.0
    lx, ly, _ = cliff_table._floor_hits(intr, rot, u - e, v)
    rx, ry, _ = cliff_table._floor_hits(intr, rot, u + e, v)
    b_l, b_r = np.arctan2(ly, lx), np.arctan2(ry, rx)
    first, last = cliff_table._sample_bins(
        np.minimum(b_l, b_r), np.maximum(b_l, b_r), *layout[:2], layout[2]
    )
    out = np.full(layout[2], np.nan, dtype=np.float32)
    for (r, c), f in np.ndenumerate(first):
        for b in range(f, last[r, c] + 1):
            out[b] = np.fmin(out[b], vals[r, c])
    return found, out


CLIFF_PARAMS = [
    CliffParams(),
    CliffParams(block_size=8, row_step=1, col_step=1, block_points_thresh=10),
    CliffParams(
        block_size=8, row_step=2, col_step=3, block_points_thresh=4
    ),  # uneven sample columns
    CliffParams(method="paper"),
    CliffParams(
        method="paper",
        block_size=8,
        row_step=1,
        col_step=1,
        block_points_thresh=10,
        used_depth_height=90,
    ),
]


@pytest.mark.parametrize("mount", MOUNTS, ids=lambda m: f"t{m.tilt_deg:g}_r{m.roll_deg:g}")
@pytest.mark.parametrize(
    "params", CLIFF_PARAMS, ids=["defaults", "dense", "uneven", "paper", "paper_dense"]
)
def test_cliff_kernel_equals_numpy_definition(mount: Mount, params: CliffParams) -> None:
    depth = noisy_frame(SMALL, mount, seed=11 + int(mount.tilt_deg))
    layout = scan_mod.scan_layout(SMALL, mount, ScanParams())
    res = detect_cliffs(depth, SMALL, mount, params, *layout)
    found, want = reference_cliffs(depth, SMALL, mount, params, layout)
    bj, bi = np.nonzero(found)
    np.testing.assert_array_equal(
        res.blocks,
        np.stack([SMALL.height - (bj + 1) * params.block_size, bi * params.block_size], axis=-1),
    )
    assert np.array_equal(res.scan.ranges, want, equal_nan=True)


POSE_PARAMS = [
    PoseParams(),
    PoseParams(row_step=3, col_step=5, max_points=400, min_inliers=100),
    PoseParams(max_points=100_000, row_step=1, col_step=1),
]


@pytest.mark.parametrize("mount", MOUNTS[:4], ids=lambda m: f"t{m.tilt_deg:g}_r{m.roll_deg:g}")
@pytest.mark.parametrize("params", POSE_PARAMS, ids=["defaults", "thinned", "all"])
def test_floor_candidates_equal_the_numpy_definition(mount: Mount, params: PoseParams) -> None:
    depth = noisy_frame(SMALL, mount, seed=21)
    t = pose_mod._pose_table(SMALL, params)
    d = depth[t.rows, t.cols]
    ok = (d >= t.zlo_mm) & (d <= t.zhi_mm)
    want = t.rays[ok] * (d[ok].astype(np.float32) * np.float32(0.001))[:, None]
    if len(want) > params.max_points:
        want = want[np.linspace(0, len(want) - 1, params.max_points).astype(np.intp)]
    got = pose_mod.floor_candidates(depth, SMALL, params)
    assert len(want) > 0
    assert np.array_equal(got, want)


def test_ransac_counts_equal_numpy_and_the_adaptive_stop_is_pcls() -> None:
    mount = MOUNTS[0]
    pts = pose_mod.floor_candidates(noisy_frame(SMALL, mount, seed=4), SMALL, PoseParams())
    rng = np.random.default_rng(9)
    normals = rng.normal(size=(50, 3))
    normals /= np.linalg.norm(normals, axis=1)[:, None]
    normals[:25] = [0.0, -math.cos(mount.tilt_rad), -math.sin(mount.tilt_rad)]  # near the floor
    normals[:25] += rng.normal(scale=0.01, size=(25, 3))
    offsets = rng.uniform(0.3, 0.8, size=50)
    n32, d32 = normals.astype(np.float32), offsets.astype(np.float32)
    px, py, pz = (np.ascontiguousarray(pts[:, i]) for i in range(3))
    want = np.count_nonzero(
        np.abs(px[:, None] * n32[:, 0] + py[:, None] * n32[:, 1] + pz[:, None] * n32[:, 2] + d32)
        <= np.float32(0.02),
        axis=0,
    )
    counts = np.zeros(50, dtype=np.int64)
    order = np.arange(50)
    assert (
        pose_kernels.ransac_count_kernel(
            px, py, pz, n32, d32, order, np.float32(0.02), 1.0, 8, counts
        )
        == 50
    )
    np.testing.assert_array_equal(counts, want)
    # adaptive: stops after the first chunk whose best share w makes log(1-p)/log(1-w^3) <= scored
    counts[:] = 0
    scored = pose_kernels.ransac_count_kernel(
        px, py, pz, n32, d32, order, np.float32(0.02), 0.99, 8, counts
    )
    need, s = 50, 0
    while s < min(50, need):
        s += 8 if s + 8 <= 50 else 50 - s
        w = want[:s].max() / len(pts)
        if 0 < w < 1:
            need = min(need, math.ceil(math.log(1 - 0.99) / math.log(1 - w**3)))
    assert scored == s


def test_refined_plane_equals_numpy_least_squares() -> None:
    mount = MOUNTS[2]
    pts = pose_mod.floor_candidates(noisy_frame(SMALL, mount, seed=8), SMALL, PoseParams())
    start = np.array([0.0, -math.cos(mount.tilt_rad), -math.sin(mount.tilt_rad), mount.height_m])
    plane, n_in, rms = pose_mod.refine_plane(pts, start, 0.02)
    p = pts.astype(np.float64)
    want = start
    inl = np.abs(p @ want[:3] + want[3]) <= 0.02
    for _ in range(3):
        c = p[inl].mean(axis=0)
        n = np.linalg.eigh((p[inl] - c).T @ (p[inl] - c))[1][:, 0]
        d = -float(n @ c)
        n, d = (-n, -d) if d < 0 else (n, d)
        want = np.concatenate([n, [d]])
        inl = np.abs(p @ n + d) <= 0.02
    np.testing.assert_allclose(plane, want, atol=1e-9)
    assert n_in == inl.sum()
    assert rms == pytest.approx(
        float(np.sqrt(np.mean((p[inl] @ want[:3] + want[3]) ** 2))), rel=1e-9
    )


def test_warm_up_compiles_every_kernel_the_daemon_path_calls() -> None:
    from depthnav_daemon.pipeline import (
        StageParams,
        cliff_kernels,
        process,
        scan_blocks,
        scan_kernels,
        table_kernels,
    )
    from depthnav_daemon.tools import warmup
    from drivers.base import Frame

    kernels = [
        scan_kernels.exact_scan_kernel,
        scan_kernels.paper_scan_kernel,
        table_kernels.bin_map_kernel,
        cliff_kernels.cliff_kernel,
        pose_kernels.count_candidates_kernel,
        pose_kernels.candidates_kernel,
        pose_kernels.hypotheses_kernel,
        pose_kernels.ransac_count_kernel,
        pose_kernels.plane_moments_kernel,
        scan_kernels.flush_codes_kernel,
        scan_blocks.block_tables_kernel,
        table_kernels.exact_table_kernel,
        table_kernels.exact_codes_kernel,
        table_kernels.pose_envelope_kernel,
    ]
    warmup.warm_up()
    before = [len(k.signatures) for k in kernels]
    mount = MOUNTS[0]
    depth = noisy_frame(SMALL, mount, seed=1)
    frame = Frame(0, 0.0, depth.copy(), SMALL)  # read-only, as drivers deliver
    for scan in (ScanParams(), ScanParams(method="paper", scan_height=100)):
        estimate_pose(
            frame.depth_mm, SMALL, PoseParams(used_depth_height=100), np.random.default_rng(0)
        )
        # a new prior window (the daemon narrows it around a tilt sensor's reading)
        estimate_pose(
            frame.depth_mm,
            SMALL,
            PoseParams(used_depth_height=100, tilt_min_deg=5.0, tilt_max_deg=25.0),
            np.random.default_rng(0),
        )
        process(frame, mount, StageParams(scan=scan, cliff=CliffParams()))
    depth_to_scan(depth.astype(np.float32) / 1000, SMALL, mount, ScanParams())  # float metres input
    assert [len(k.signatures) for k in kernels] == before


@pytest.mark.parametrize("mount", [Mount(0.5, 30.0, 12.0), Mount(0.8, 50.0, -15.0)])
def test_cliff_scan_samples_outside_the_layout_leak_into_no_run(mount: Mount) -> None:
    # a layout narrower than the image, with roll: sample columns leave and enter the layout
    # inside a block row, so a run covering no bin is followed by one that covers bins
    params = CliffParams(block_size=8, row_step=1, col_step=1, block_points_thresh=2)
    layout = (-0.15, 0.004, 76)
    t = cliff_table.cliff_table(SMALL, mount, params, *layout)
    assert ((t.ev_code >> 16) == layout[2]).any()  # runs covering no bin exist
    rng = np.random.default_rng(3)
    depth = rng.integers(0, 9000, size=(SMALL.height, SMALL.width)).astype(np.uint16)
    res = detect_cliffs(depth, SMALL, mount, params, *layout)
    found, want = reference_cliffs(depth, SMALL, mount, params, layout)
    assert found.any()
    assert np.array_equal(res.scan.ranges, want, equal_nan=True)


# --- random cameras, mounts and parameters ----------------------------------------------------


@st.composite
def camera_and_mount(draw: st.DrawFn) -> tuple[Intrinsics, Mount]:
    w = draw(st.integers(16, 96))
    h = draw(st.integers(12, 72))
    f = draw(st.floats(0.6, 1.6)) * w
    intr = Intrinsics(
        w,
        h,
        f,
        f * draw(st.floats(0.9, 1.1)),
        draw(st.floats(0.3, 0.7)) * (w - 1),
        draw(st.floats(0.3, 0.7)) * (h - 1),
    )
    mount = Mount(
        draw(st.floats(0.15, 1.5)), draw(st.floats(-30.0, 88.9)), draw(st.floats(-30.0, 30.0))
    )
    return intr, mount


def random_depth(intr: Intrinsics, mount: Mount, seed: int, rendered: bool) -> np.ndarray:
    """A noisy rendered scene, or uniform noise with zeros (every threshold crossed anywhere)."""
    if rendered:
        return noisy_frame(intr, mount, seed)
    rng = np.random.default_rng(seed)
    depth = rng.integers(0, 7000, size=(intr.height, intr.width)).astype(np.uint16)
    depth[rng.random(depth.shape) < 0.2] = 0
    return depth


@settings(max_examples=60, deadline=None)
@given(cm=camera_and_mount(), data=st.data())
def test_exact_scan_kernel_equals_per_row_binning_anywhere(
    cm: tuple[Intrinsics, Mount], data: st.DataObject
) -> None:
    intr, mount = cm
    row_start = data.draw(st.integers(0, intr.height - 1))
    params = ScanParams(
        range_min_m=data.draw(st.sampled_from([0.0, 0.2, 0.4, 1.0])),
        range_max_m=data.draw(st.sampled_from([2.0, 5.0, 9.0])),
        min_obstacle_height_m=data.draw(st.sampled_from([-0.3, 0.0, 0.05])),
        max_obstacle_height_m=data.draw(st.sampled_from([0.3, 2.0])),
        row_start=row_start,
        row_stop=data.draw(st.sampled_from([-1, row_start + 1, intr.height])),
        row_step=data.draw(st.integers(1, 4)),
        col_step=data.draw(st.integers(1, 4)),
        angle_increment_deg=data.draw(st.sampled_from([0.0, 0.05, 0.7, 3.0])),
    )
    depth = random_depth(intr, mount, data.draw(st.integers(0, 99)), data.draw(st.booleans()))
    got = depth_to_scan(depth, intr, mount, params).ranges
    assert np.array_equal(got, reference_exact_scan(depth, intr, mount, params), equal_nan=True)


@settings(max_examples=60, deadline=None)
@given(cm=camera_and_mount(), data=st.data())
def test_cliff_kernel_equals_numpy_definition_anywhere(
    cm: tuple[Intrinsics, Mount], data: st.DataObject
) -> None:
    intr, mount = cm
    bs = data.draw(st.integers(2, min(12, intr.width, intr.height)))
    row_step = data.draw(st.integers(1, bs))
    col_step = data.draw(st.integers(1, bs))
    per_block = -(-bs // row_step) * -(-bs // col_step)
    params = CliffParams(
        method=data.draw(st.sampled_from(["exact", "paper"])),
        range_min_m=data.draw(st.sampled_from([0.0, 0.5])),
        range_max_m=data.draw(st.sampled_from([3.0, 8.0])),
        used_depth_height=data.draw(st.integers(bs, 8192)),
        block_size=bs,
        row_step=row_step,
        col_step=col_step,
        block_points_thresh=data.draw(st.integers(1, per_block)),
        ground_margin_m=data.draw(st.sampled_from([0.0, 0.05])),
    )
    if data.draw(st.booleans()):
        layout = scan_mod.scan_layout(intr, mount, ScanParams())
    else:  # a layout narrower or coarser than the image's
        layout = (
            data.draw(st.floats(-0.6, 0.1)),
            data.draw(st.floats(0.002, 0.05)),
            data.draw(st.integers(1, 200)),
        )
    depth = random_depth(intr, mount, data.draw(st.integers(0, 99)), data.draw(st.booleans()))
    res = detect_cliffs(depth, intr, mount, params, *layout)
    found, want = reference_cliffs(depth, intr, mount, params, layout)
    bj, bi = np.nonzero(found)
    np.testing.assert_array_equal(
        res.blocks, np.stack([intr.height - (bj + 1) * bs, bi * bs], axis=-1)
    )
    assert np.array_equal(res.scan.ranges, want, equal_nan=True)
