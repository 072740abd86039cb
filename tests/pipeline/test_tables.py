"""Compiled table builders against the numpy definitions they replaced: equal tables over a grid
of mounts (tilted, rolled, looking past the vertical), at 640x480 and 1280x720.

The references below are the numpy builders as they were (scan_table.exact_table and
pose_fit._pose_table before they were compiled), kept here to pin that compiling them changed
nothing.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from depthnav_daemon.pipeline import pose_fit, scan_table
from depthnav_daemon.pipeline.geometry import Mount, cam_to_level, normalized_coords, pixel_rays
from depthnav_daemon.pipeline.pose import PoseParams
from depthnav_daemon.pipeline.scan import ScanParams
from depthnav_daemon.pipeline.scan_kernels import CODE_BITS, run_flush_codes
from drivers.base import KINECT_V1, Intrinsics

HD = Intrinsics(1280, 720, 640.0, 640.0, 639.5, 359.5)
SMALL = Intrinsics(200, 150, 180.0, 181.0, 97.3, 77.9)
LENS = Intrinsics(640, 480, 580.0, 580.0, 319.5, 239.5, -0.28, 0.07, 0.001, -0.001)  # Brown-Conrady
MOUNTS = [
    Mount(0.55, 15.0, 0.0),
    Mount(0.8, 40.0, 5.0),
    Mount(1.2, 50.0, -8.0),
    Mount(0.5, 0.0, 0.0),
    Mount(0.3, -20.0, 12.0),
    Mount(2.5, 70.0, -30.0),
    Mount(0.4, 85.0, 45.0),  # footprints across the +-pi seam
    Mount(1.0, 89.0, -45.0),
]


def _depth_bounds_mm(k: np.ndarray, lo: float, hi: float) -> tuple[np.ndarray, np.ndarray]:
    with np.errstate(divide="ignore", invalid="ignore"):
        a = lo / k * 1000.0
        b = hi / k * 1000.0
    zlo = np.where(k > 0, a, np.where(k < 0, b, np.where(lo <= 0 <= hi, 0.0, np.inf)))
    zhi = np.where(k > 0, b, np.where(k < 0, a, np.where(lo <= 0 <= hi, np.inf, -np.inf)))
    return zlo, zhi


def reference_exact_table(intr: Intrinsics, mount: Mount, params: ScanParams) -> dict:
    """scan_table.exact_table as numpy computed it (its fields, by name)."""
    rows = scan_table.scan_rows(intr, params)
    cols = slice(0, intr.width, params.col_step)
    v = np.arange(intr.height, dtype=np.float64)[rows][:, None]
    u = np.arange(intr.width, dtype=np.float64)[cols][None, :]
    rot = cam_to_level(mount.tilt_rad, mount.roll_rad)
    x, y = normalized_coords(intr, u, v)
    d = np.stack((x, y, np.ones_like(x)), axis=-1) @ rot.T
    kr = np.hypot(d[..., 0], d[..., 1])
    kh = d[..., 2]
    h = mount.height_m
    hlo, hhi = _depth_bounds_mm(
        kh, params.min_obstacle_height_m - h, params.max_obstacle_height_m - h
    )
    rlo, rhi = _depth_bounds_mm(kr, params.range_min_m, params.range_max_m)
    zlo = np.maximum(np.maximum(hlo, rlo), 1.0)
    zhi = np.minimum(hhi, rhi)
    zlo_mm = np.clip(np.ceil(zlo), 1, 65535).astype(np.uint16)
    zhi_mm = np.clip(np.floor(zhi), 0, 65535).astype(np.uint16)
    near_lo_mm = np.clip(np.ceil(np.maximum(hlo, 1.0)), 1, 65535).astype(np.uint16)
    near_hi_mm = np.clip(np.ceil(np.minimum(hhi, rlo)) - 1, 0, 65535).astype(np.uint16)
    near = near_lo_mm <= near_hi_mm
    k_lo = np.where(near, near_lo_mm, zlo_mm).astype(np.uint16)
    k_mid = np.where(near, near_hi_mm, zlo_mm.astype(np.int64) - 1).astype(np.uint16)
    k_hi = np.where(zlo_mm <= zhi_mm, zhi_mm, 0).astype(np.uint16)
    half = params.col_step / 2.0
    b_left = scan_table._bearing(intr, rot, u - half, v)
    b_right = scan_table._bearing(intr, rot, u + half, v)
    lo_b = np.minimum(b_left, b_right)
    hi_b = np.maximum(b_left, b_right)
    sane = (hi_b - lo_b) < math.pi
    principal = scan_table._bearing(
        intr, rot, np.array([intr.cx - half, intr.cx + half]), np.array([intr.cy, intr.cy])
    )
    inc = (
        math.radians(params.angle_increment_deg)
        if params.angle_increment_deg > 0
        else float(abs(principal[1] - principal[0]))
    )
    edge_min = float(lo_b[sane].min())
    n = max(1, math.ceil((float(hi_b[sane].max()) - edge_min) / inc))
    angle_min = edge_min + inc / 2.0
    centre = scan_table._bearing(intr, rot, u + 0.0 * v, v + 0.0 * u)
    _, _, cb_lo, cb_hi = scan_table._bin_map(centre, lo_b, hi_b, sane, angle_min, inc, n)
    fl_start, fl_code = reference_run_flush_codes(cb_lo, cb_hi, n)
    return {
        "zlo_mm": zlo_mm,
        "zhi_mm": zhi_mm,
        "near_lo_mm": near_lo_mm,
        "near_hi_mm": near_hi_mm,
        "k_lo": k_lo,
        "k_mid": k_mid,
        "k_hi": k_hi,
        "kr_m_per_mm": (kr / 1000.0).astype(np.float32),
        "fl_start": fl_start,
        "fl_code": fl_code,
        "n_bins": n,
        "angle_min": angle_min,
        "angle_increment": inc,
    }


def assert_exact_table_equal(intr: Intrinsics, mount: Mount, params: ScanParams) -> None:
    got = scan_table.exact_table(intr, mount, params)
    want = reference_exact_table(intr, mount, params)
    for name, w in want.items():
        g = getattr(got, name)
        if isinstance(w, np.ndarray):
            assert g.dtype == w.dtype, name
            np.testing.assert_array_equal(g, w, err_msg=name)
        elif isinstance(w, float):
            # the kernel's bearings come from libm's atan2, the reference's from numpy's arctan2,
            # which numpy 2.4 computes with its own SIMD code: they differ by up to 1 ulp
            assert abs(g - w) <= 2 * np.spacing(abs(w)), name
        else:
            assert g == w, name


@pytest.mark.parametrize(
    "mount", MOUNTS, ids=lambda m: f"h{m.height_m:g}_t{m.tilt_deg:g}_r{m.roll_deg:g}"
)
@pytest.mark.parametrize("intr", [KINECT_V1, HD, LENS], ids=["640x480", "1280x720", "lens"])
def test_exact_table_equals_the_numpy_definition(intr: Intrinsics, mount: Mount) -> None:
    assert_exact_table_equal(intr, mount, ScanParams())


@pytest.mark.parametrize(
    "params",
    [
        ScanParams(col_step=3, row_step=2, row_start=10, row_stop=140),
        ScanParams(angle_increment_deg=0.5, range_min_m=0.0, range_max_m=3.0),
        # a band that puts the floor itself in range (min height below the floor): k == 0 rows
        ScanParams(min_obstacle_height_m=-1.0, max_obstacle_height_m=0.0),
        ScanParams(min_obstacle_height_m=-10.0, max_obstacle_height_m=10.0, range_max_m=100.0),
    ],
)
@pytest.mark.parametrize("mount", MOUNTS[:6], ids=lambda m: f"t{m.tilt_deg:g}_r{m.roll_deg:g}")
def test_exact_table_equals_the_numpy_definition_for_other_params(
    params: ScanParams, mount: Mount
) -> None:
    assert_exact_table_equal(SMALL, mount, params)


def test_exact_table_equals_the_numpy_definition_over_a_dense_grid_of_mounts() -> None:
    # small steps through height, tilt and roll: thresholds cross integer millimetres and
    # bearings cross bin edges many times over
    for h in (0.21, 0.55, 1.37):
        for tilt in np.arange(-30.0, 89.0, 7.3):
            for roll in (-44.5, -3.1, 0.0, 2.7, 19.9):
                assert_exact_table_equal(SMALL, Mount(h, float(tilt), roll), ScanParams())


def reference_run_ends(
    cb_lo: np.ndarray, cb_hi: np.ndarray, row_block: int = 0
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Where the runs of a run-minimum kernel end, from the bins every pixel (or sample) feeds.

    A run of column c is a stretch of rows over which c feeds the same bins; it ends after row i
    when row i + 1 feeds other bins, or i is the last row.

    Args:
        cb_lo, cb_hi: (Hs, Ws) first and last bin each pixel feeds (cb_lo > cb_hi: none);
            rows in the order the kernel walks them.
        row_block: if > 0, every run also ends after each row_block-th row (a kernel that may
            skip whole blocks of rows needs no run to cross into them).

    Returns:
        ev_start, ev_col, ev_lo, ev_hi: the runs ending after row i are ev_start[i]:ev_start[i + 1]
        ((Hs + 1,) int32); each names its column and the bins it feeds ((E,) int32 each).
    """
    hs, ws = cb_lo.shape
    ends = np.ones((hs, ws), dtype=bool)
    ends[:-1] = (cb_lo[1:] != cb_lo[:-1]) | (cb_hi[1:] != cb_hi[:-1])
    if row_block > 0:
        ends[row_block - 1 :: row_block] = True
    ii, jj = np.nonzero(ends)  # row-major: grouped by row
    ev_start = np.zeros(hs + 1, dtype=np.int32)
    np.cumsum(np.bincount(ii, minlength=hs), out=ev_start[1:])
    return (
        ev_start,
        jj.astype(np.int32),
        cb_lo[ii, jj].astype(np.int32),
        cb_hi[ii, jj].astype(np.int32),
    )


def reference_run_flush_codes(
    cb_lo: np.ndarray, cb_hi: np.ndarray, n_bins: int, row_block: int = 0
) -> tuple[np.ndarray, np.ndarray]:
    """``run_ends`` as one packed code per (run, bin): what the exact scan kernel reads.

    One int32 per flush instead of separate column, bin and reset lists: the kernel's flush loop
    is bound by its loads and stores (~1 ns a flush against ~2-3 ns with three lists).

    Args:
        cb_lo, cb_hi: (Hs, Ws) first and last bin each pixel feeds (cb_lo > cb_hi: none);
            Ws and the bins below 32768.
        n_bins: bins of the scan; a run feeding none is flushed into bin n_bins (a scratch slot
            the kernel's output has beyond the scan), so that its column starts again too.
        row_block: as in ``run_ends``.

    Returns:
        fl_start: (Hs + 1,) the flushes after row i are fl_start[i]:fl_start[i + 1];
        fl_code: (F,) ``col | last << 15 | bin << 16``: column col's run minimum goes into bin; a
        run's bins are consecutive, and its last carries ``last`` (the column starts a new run).
    """
    hs = cb_lo.shape[0]
    rs_start, rs_col, lo, hi = reference_run_ends(cb_lo, cb_hi, row_block)
    row = np.repeat(np.arange(hs), np.diff(rs_start))
    lo = lo.astype(np.int64)
    none = hi < lo
    lo[none] = n_bins
    span = np.where(none, 1, hi.astype(np.int64) - lo + 1)
    k = np.repeat(np.arange(rs_col.size), span)
    within = np.arange(k.size) - np.repeat(np.cumsum(span) - span, span)
    fl_start = np.zeros(hs + 1, dtype=np.int32)
    np.cumsum(np.bincount(row[k], minlength=hs), out=fl_start[1:])
    last = within == span[k] - 1
    code = (
        rs_col[k].astype(np.int64)
        | (last.astype(np.int64) << CODE_BITS)
        | ((lo[k] + within) << (CODE_BITS + 1))
    )
    return fl_start, code.astype(np.int32)


@pytest.mark.parametrize("row_block", [0, 1, 4, 7])
@pytest.mark.parametrize("dtype", [np.int16, np.int32])
def test_run_flush_codes_equal_the_numpy_definition(row_block: int, dtype: type) -> None:
    rng = np.random.default_rng(row_block)
    for shape in [(1, 1), (5, 9), (40, 64), (33, 200)]:
        n = 50
        # slowly changing bins down each column (as a tilted camera's), some feeding none
        lo = np.cumsum(rng.random(shape) < 0.3, axis=0) + rng.integers(0, 10, shape[1])
        hi = lo + rng.integers(-1, 3, shape)  # -1: feeds no bin
        lo, hi = np.minimum(lo, n - 1).astype(dtype), np.minimum(hi, n - 1).astype(dtype)
        got = run_flush_codes(lo, hi, n, row_block)
        want = reference_run_flush_codes(lo, hi, n, row_block)
        for g, w in zip(got, want, strict=True):
            assert g.dtype == w.dtype == np.int32
            np.testing.assert_array_equal(g, w)


def reference_pose_table(intr: Intrinsics, params: PoseParams) -> tuple[np.ndarray, ...]:
    """pose_fit._pose_table as numpy computed it: (zlo_mm, zhi_mm, rays)."""
    used = min(params.used_depth_height, intr.height)
    rows = slice(
        intr.height - 1 - ((used - 1) // params.row_step) * params.row_step,
        intr.height,
        params.row_step,
    )
    cols = slice(0, intr.width, params.col_step)
    rays = pixel_rays(intr)[rows, cols]
    lo_kz = np.full(rays.shape[:2], np.inf)
    hi_kz = np.full(rays.shape[:2], -np.inf)
    step = pose_fit.ENVELOPE_STEP_DEG
    n_tilt = max(2, math.ceil((params.tilt_max_deg - params.tilt_min_deg) / step) + 1)
    n_roll = max(2, math.ceil(2 * params.roll_max_deg / step) + 1)
    tilts = np.radians(np.linspace(params.tilt_min_deg, params.tilt_max_deg, n_tilt))
    rolls = np.radians(np.linspace(-params.roll_max_deg, params.roll_max_deg, n_roll))
    for t in tilts:
        for r in rolls:
            down = -(rays @ cam_to_level(float(t), float(r))[2])
            lo_kz = np.minimum(lo_kz, down)
            hi_kz = np.maximum(hi_kz, down)
    with np.errstate(divide="ignore", invalid="ignore"):
        zlo = np.where(hi_kz > 0, params.height_min_m / hi_kz, np.inf)
        zhi = np.where(lo_kz > 0, params.height_max_m / lo_kz, np.inf)
    zlo = np.maximum(zlo, params.range_min_m)
    zhi = np.minimum(zhi, params.range_max_m)
    with np.errstate(invalid="ignore"):
        zlo_mm = np.where(np.isfinite(zlo), np.clip(np.ceil(zlo * 1000.0), 1, 65535), 65535)
        zhi_mm = np.clip(np.floor(zhi * 1000.0), 0, 65535)
    return zlo_mm.astype(np.uint16), zhi_mm.astype(np.uint16), rays.astype(np.float32)


@pytest.mark.parametrize(
    "params",
    [
        PoseParams(),
        PoseParams(row_step=1, col_step=1, used_depth_height=480),
        PoseParams(tilt_min_deg=20.0, tilt_max_deg=40.0, roll_max_deg=0.0),
        PoseParams(tilt_min_deg=-89.0, tilt_max_deg=89.0, roll_max_deg=45.0, height_min_m=1.0),
        PoseParams(tilt_min_deg=33.0, tilt_max_deg=33.0, height_min_m=0.9, height_max_m=1.5),
    ],
)
@pytest.mark.parametrize("intr", [KINECT_V1, HD, LENS], ids=["640x480", "1280x720", "lens"])
def test_pose_table_equals_the_numpy_definition(intr: Intrinsics, params: PoseParams) -> None:
    got = pose_fit._pose_table(intr, params)
    for g, w in zip(
        (got.zlo_mm, got.zhi_mm, got.rays), reference_pose_table(intr, params), strict=True
    ):
        assert g.dtype == w.dtype
        np.testing.assert_array_equal(g, w)
