"""Sensor height, tilt and roll from the floor (the paper's eq. 9-14), and tilt/roll from gravity.

Floor candidates (eq. 9-11) are the sampled pixels of the bottom ``used_depth_height`` rows whose
depth lies between the floor depths of the prior's extremes. Unlike the original, the envelope is
computed per pixel with the exact ray angle (not eq. 3's linear row angle) and includes the roll
prior: over the box [height_min_m, height_max_m] x [tilt_min_deg, tilt_max_deg] x [-roll_max_deg,
roll_max_deg] the floor depth of a pixel is h / -kz(tilt, roll), so the envelope is
[h_min / max(-kz), h_max / min(-kz)], the extremes of -kz taken over a grid of the angle box
with steps of at most ENVELOPE_STEP_DEG (-kz is a sinusoid in each angle, so a grid misses an
interior extreme by at most 1 - cos(step / 2), under 0.1 %).

Candidates are back-projected with the correct axes (eq. 12: x from columns and cx/fx, y from rows
and cy/fy; the original swapped them), a plane is fitted by RANSAC with an explicit Generator,
hypotheses outside the prior are rejected, and the plane is refined by least squares on its
inliers. Height is the plane's distance (eq. 14) and tilt is *signed* (eq. 13 loses the sign):
with n the unit floor normal pointing up in the camera frame, tilt = atan2(-n_z, hypot(n_x, n_y))
and roll = atan2(-n_x, -n_y), the same formulas as for an accelerometer's gravity vector.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from depthnav_daemon.errors import ConfigError
from depthnav_daemon.pipeline.geometry import (
    F32,
    F64,
    MAX_MOUNT_HEIGHT_M,
    MAX_ROLL_DEG,
    MAX_TILT_DEG,
    cam_to_level,
    check_int,
    check_order,
    check_range,
    depth_to_mm,
    frozen_table,
    pixel_rays,
)
from depthnav_daemon.pipeline.pose_kernels import (
    candidates_kernel,
    count_candidates_kernel,
    hypotheses_kernel,
    plane_moments_kernel,
    ransac_count_kernel,
)
from drivers.base import STANDARD_GRAVITY_MPS2 as G_MPS2
from drivers.base import Intrinsics

PRIOR_SLACK_DEG = 2.0  # fitted angles may exceed the prior by this much (noise at its edges)
PRIOR_SLACK_M = 0.02
SCORE_CHUNK = 32  # RANSAC hypotheses scored per batch
RANSAC_CONFIDENCE = 0.999
ENVELOPE_STEP_DEG = 4.0
PLANE_POINTS = 3  # the fewest points that define a plane


@dataclass(frozen=True, slots=True)
class PoseParams:
    """Floor pose estimator parameters (names after depth_sensor_pose, units in the names).

    Attributes:
        height_min_m, height_max_m: prior on the mount height, metres.
        tilt_min_deg, tilt_max_deg: prior on the tilt, degrees, positive = pitched down.
        roll_max_deg: prior bound on |roll|, degrees.
        range_min_m, range_max_m: accepted optical depth of candidates, metres.
        used_depth_height: rows used, counted from the image bottom (clamped to the image height).
        row_step, col_step: pixel strides of the candidate grid.
        max_points: cap on candidates; more are thinned evenly over the image.
        ransac_iterations: RANSAC hypotheses.
        inlier_dist_m: RANSAC inlier distance to the plane, metres.
        min_inliers, min_inlier_ratio: a result is confident (ok) only with at least this many
            inliers and this share of the candidates.
    """

    height_min_m: float = 0.1
    height_max_m: float = 1.5
    tilt_min_deg: float = -10.0
    tilt_max_deg: float = 60.0
    roll_max_deg: float = 10.0
    range_min_m: float = 0.5
    range_max_m: float = 5.0
    used_depth_height: int = 400
    row_step: int = 4
    col_step: int = 4
    max_points: int = 3000
    ransac_iterations: int = 500
    inlier_dist_m: float = 0.02
    min_inliers: int = 300
    min_inlier_ratio: float = 0.2

    def __post_init__(self) -> None:
        check_range("pose.height_min_m", self.height_min_m, 0.01, MAX_MOUNT_HEIGHT_M, " m")
        check_range("pose.height_max_m", self.height_max_m, 0.01, MAX_MOUNT_HEIGHT_M, " m")
        check_order(
            "pose.height_min_m",
            self.height_min_m,
            "pose.height_max_m",
            self.height_max_m,
            strict=False,
        )
        check_range("pose.tilt_min_deg", self.tilt_min_deg, -MAX_TILT_DEG, MAX_TILT_DEG, " deg")
        check_range("pose.tilt_max_deg", self.tilt_max_deg, -MAX_TILT_DEG, MAX_TILT_DEG, " deg")
        check_order(
            "pose.tilt_min_deg",
            self.tilt_min_deg,
            "pose.tilt_max_deg",
            self.tilt_max_deg,
            strict=False,
        )
        check_range("pose.roll_max_deg", self.roll_max_deg, 0.0, MAX_ROLL_DEG, " deg")
        check_range("pose.range_min_m", self.range_min_m, 0.0, 100.0, " m")
        check_range("pose.range_max_m", self.range_max_m, 0.01, 100.0, " m")
        check_order("pose.range_min_m", self.range_min_m, "pose.range_max_m", self.range_max_m)
        check_int("pose.used_depth_height", self.used_depth_height, 1, 8192)
        check_int("pose.row_step", self.row_step, 1, 256)
        check_int("pose.col_step", self.col_step, 1, 256)
        check_int("pose.max_points", self.max_points, 3, 1_000_000)
        check_int("pose.ransac_iterations", self.ransac_iterations, 1, 100_000)
        check_range("pose.inlier_dist_m", self.inlier_dist_m, 1e-4, 1.0, " m")
        check_int("pose.min_inliers", self.min_inliers, 3, 1_000_000)
        check_order(
            "pose.min_inliers",
            self.min_inliers,
            "pose.max_points",
            self.max_points,
            strict=False,
            why="the estimate could never be confident",
        )
        check_range("pose.min_inlier_ratio", self.min_inlier_ratio, 0.0, 1.0)


@dataclass(frozen=True, slots=True)
class PoseEstimate:
    """The floor pose of one frame; height/tilt/roll are NaN unless ``ok``.

    Attributes:
        ok: a confident estimate inside the prior.
        height_m: optical centre above the floor, metres.
        tilt_deg: signed pitch, positive = pitched down, degrees.
        roll_deg: roll, positive = left side up, degrees.
        inliers: candidates within inlier_dist_m of the final plane.
        inlier_ratio: inliers / candidates (0 when there are none).
        residual_m: RMS plane distance of the inliers, metres (NaN when no plane).
        candidates: floor candidates after thinning.
        reason: why the estimate is not ok ("" when ok).
    """

    ok: bool
    height_m: float
    tilt_deg: float
    roll_deg: float
    inliers: int
    inlier_ratio: float
    residual_m: float
    candidates: int
    reason: str = ""


def tilt_roll_from_normal(normal: F64) -> tuple[float, float]:
    """(tilt, roll) in degrees of a camera whose "up" direction in its own frame is ``normal`` (3,).

    Tilt positive = pitched down; roll positive = left side up. Up is (0, -1, 0) for a level camera,
    (0, -cos t, -sin t) pitched down by t, (-sin r, -cos r, 0) rolled by r.
    """
    nx, ny, nz = (float(c) for c in normal)
    return math.degrees(math.atan2(-nz, math.hypot(nx, ny))), math.degrees(math.atan2(-nx, -ny))


def tilt_roll_from_accel(accel_mps2: npt.ArrayLike) -> tuple[float, float]:
    """Tilt and roll (degrees) of a resting camera from its accelerometer's specific force.

    Args:
        accel_mps2: (3,) specific force in the camera frame (x right, y down, z forward), m/s^2.
            At rest it points up: level reads (0, -g, 0); pitched down by t,
            (0, -g cos t, -g sin t).

    Returns:
        (tilt_deg, roll_deg): tilt = atan2(-az, hypot(ax, ay)), positive down;
        roll = atan2(-ax, -ay), positive = left side up.

    Raises:
        ConfigError: not 3 finite numbers, or a magnitude outside 0.5..1.5 g (moving, wrong units).
    """
    try:
        a = np.asarray(accel_mps2, dtype=np.float64).reshape(3)
    except (TypeError, ValueError):
        raise ConfigError(
            f"accelerometer vector {accel_mps2!r} is not 3 numbers (accepted: (ax, ay, az) m/s^2)"
        ) from None
    norm = float(np.linalg.norm(a))
    if not np.isfinite(a).all() or not 0.5 * G_MPS2 <= norm <= 1.5 * G_MPS2:
        raise ConfigError(
            f"accelerometer vector {a.tolist()} has magnitude {norm:.3g} m/s^2 "
            f"(accepted: {0.5 * G_MPS2:.2f}..{1.5 * G_MPS2:.2f} m/s^2, i.e. 0.5..1.5 g at rest)"
        )
    return tilt_roll_from_normal(a)


# --- candidates (eq. 9-12) ------------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class _PoseTable:
    rows: slice
    cols: slice
    zlo_mm: npt.NDArray[np.uint16]  # (Hs, Ws) candidate iff zlo <= d <= zhi
    zhi_mm: npt.NDArray[np.uint16]
    rays: F32  # (Hs, Ws, 3) camera ray per metre of depth (eq. 12)


@functools.lru_cache(maxsize=8)
def _pose_table(intr: Intrinsics, params: PoseParams) -> _PoseTable:
    used = min(params.used_depth_height, intr.height)
    # bottom-up from the last row, as the original, so the bottom row is always used
    rows = slice(
        intr.height - 1 - ((used - 1) // params.row_step) * params.row_step,
        intr.height,
        params.row_step,
    )
    cols = slice(0, intr.width, params.col_step)
    rays = pixel_rays(intr)[rows, cols]  # (Hs, Ws, 3)
    lo_kz = np.full(rays.shape[:2], np.inf)
    hi_kz = np.full(rays.shape[:2], -np.inf)
    n_tilt = max(2, math.ceil((params.tilt_max_deg - params.tilt_min_deg) / ENVELOPE_STEP_DEG) + 1)
    n_roll = max(2, math.ceil(2 * params.roll_max_deg / ENVELOPE_STEP_DEG) + 1)
    tilts = np.radians(np.linspace(params.tilt_min_deg, params.tilt_max_deg, n_tilt))
    rolls = np.radians(np.linspace(-params.roll_max_deg, params.roll_max_deg, n_roll))
    for t in tilts:
        for r in rolls:
            # -kz: metres down per metre of depth, (Hs, Ws)
            down = -(rays @ cam_to_level(float(t), float(r))[2])
            lo_kz = np.minimum(lo_kz, down)
            hi_kz = np.maximum(hi_kz, down)
    with np.errstate(divide="ignore", invalid="ignore"):
        zlo = np.where(hi_kz > 0, params.height_min_m / hi_kz, np.inf)
        zhi = np.where(lo_kz > 0, params.height_max_m / lo_kz, np.inf)
    zlo = np.maximum(zlo, params.range_min_m)
    zhi = np.minimum(zhi, params.range_max_m)
    with np.errstate(invalid="ignore"):
        zlo_mm = np.where(np.isfinite(zlo), np.clip(np.ceil(zlo * 1000.0), 1, 65535), 65535).astype(
            np.uint16
        )
        zhi_mm = np.clip(np.floor(zhi * 1000.0), 0, 65535).astype(np.uint16)
    # cached and shared between calls
    return frozen_table(_PoseTable(rows, cols, zlo_mm, zhi_mm, rays.astype(np.float32)))


def floor_candidates(depth: np.ndarray, intr: Intrinsics, params: PoseParams) -> F32:
    """Eq. 9-12: camera-frame points (K, 3) float32 metres that may be floor under the prior."""
    mm = depth_to_mm(depth, intr)
    t = _pose_table(intr, params)
    grid = (mm, t.rows.start, t.rows.step, t.cols.start, t.cols.step, t.zlo_mm, t.zhi_mm)
    k = count_candidates_kernel(*grid)
    keep = np.empty(min(k, params.max_points) + 1, dtype=np.intp)
    if k > params.max_points:
        # evenly over the image, not bottom-up: the original's cap kept only the near field
        keep[:-1] = np.linspace(0, k - 1, params.max_points).astype(np.intp)
    else:
        keep[:-1] = np.arange(k)
    keep[-1] = -1
    out = np.empty((keep.size - 1, 3), dtype=np.float32)
    m = candidates_kernel(*grid, t.rays, keep, np.empty(t.zlo_mm.shape[1] + 1, dtype=np.intp), out)
    pts = out[:m]
    return pts


# --- plane fit (eq. 13-14) ------------------------------------------------------------------------


def ransac_plane(
    pts: F32,
    iterations: int,
    inlier_dist_m: float,
    rng: np.random.Generator,
    accept: F64 | None = None,
    adaptive: bool = True,
) -> tuple[F64, int]:
    """Best plane by RANSAC over batched hypotheses (the stage's core).

    Args:
        pts: (K, 3) points, metres.
        iterations: hypotheses drawn.
        inlier_dist_m: inlier distance, metres.
        rng: source of the samples.
        accept: optional (3, 2) bounds [[tilt_lo, tilt_hi], [|roll| hi, unused], [h_lo, h_hi]]
            (radians, metres); hypotheses outside are skipped.
        adaptive: stop early as below (False scores every hypothesis: for benchmarks).

    Stops early (in batches of SCORE_CHUNK) once, at the best inlier share w so far, an all-inlier
    sample has been drawn with probability RANSAC_CONFIDENCE: log(1 - p) / log(1 - w^3) hypotheses.

    Returns:
        (plane, inliers): plane (4,) = (n, d) with unit n pointing toward the origin's side, and its
        inlier count; inliers 0 if no hypothesis was acceptable.
    """
    idx = rng.integers(0, len(pts), size=(iterations, 3))
    pts32 = np.ascontiguousarray(pts, dtype=np.float32)
    n = np.empty((iterations, 3))
    d = np.empty(iterations)
    good = np.empty(iterations, dtype=np.bool_)
    hypotheses_kernel(
        pts32,
        idx,
        np.zeros((3, 2)) if accept is None else np.asarray(accept, dtype=np.float64),
        accept is not None,
        n,
        d,
        good,
    )
    counts = np.zeros(iterations, dtype=np.int64)
    cand = np.flatnonzero(good)
    px, py, pz = (np.ascontiguousarray(pts32[:, i]) for i in range(3))
    # adaptive stop (as PCL): enough hypotheses that an all-inlier sample was drawn with
    # probability RANSAC_CONFIDENCE, given the best inlier share so far
    scored = ransac_count_kernel(
        px,
        py,
        pz,
        n.astype(np.float32),
        d.astype(np.float32),
        cand,
        np.float32(inlier_dist_m),
        RANSAC_CONFIDENCE if adaptive else 1.0,
        SCORE_CHUNK,
        counts,
    )
    cand = cand[:scored]
    if cand.size == 0:
        return np.array([0.0, -1.0, 0.0, 0.0]), 0
    best = int(cand[np.argmax(counts[cand])])
    return np.concatenate([n[best], [d[best]]]), int(counts[best])


def refine_plane(
    pts: F32, plane: F64, inlier_dist_m: float, rounds: int = 3
) -> tuple[F64, int, float]:
    """Least-squares plane (smallest eigenvector of the inliers' scatter), re-selecting inliers.

    Args:
        pts: (K, 3) float32 points, metres.
        plane: (4,) starting plane (n, d).
        inlier_dist_m: inlier distance, metres.
        rounds: refit rounds.

    Returns:
        (plane, inliers, rms): (4,) oriented as in ``ransac_plane``, the number of points within
        inlier_dist_m of it, and their RMS distance to it in metres (NaN when none).
    """
    pts = np.asarray(pts, dtype=np.float32)
    mean = np.empty(3)
    scatter = np.empty((3, 3))
    dist = float(inlier_dist_m)
    n_in, ssd = plane_moments_kernel(
        pts, np.asarray(plane[:3], dtype=np.float64), float(plane[3]), dist, mean, scatter
    )
    for _ in range(rounds):
        if n_in < PLANE_POINTS:
            break
        n = np.linalg.eigh(scatter)[1][:, 0]
        d = -float(n @ mean)
        if d < 0:
            n, d = -n, -d
        plane = np.concatenate([n, [d]])
        n_in, ssd = plane_moments_kernel(pts, n, d, dist, mean, scatter)
    return plane, int(n_in), math.sqrt(ssd / n_in) if n_in else math.nan


def _fail(
    reason: str, inliers: int = 0, ratio: float = 0.0, residual: float = math.nan, cand: int = 0
) -> PoseEstimate:
    return PoseEstimate(False, math.nan, math.nan, math.nan, inliers, ratio, residual, cand, reason)


def estimate_pose(
    depth: np.ndarray, intr: Intrinsics, params: PoseParams, rng: np.random.Generator
) -> PoseEstimate:
    """Estimate the sensor's height, tilt and roll from the floor it sees.

    Args:
        depth: (H, W) uint16 millimetres (0 = no reading) or float32 metres.
        intr: intrinsics of ``depth``.
        params: prior and fit parameters.
        rng: randomness for RANSAC.

    Returns:
        The estimate; ``ok`` False with NaN height/tilt/roll and a ``reason`` when too little floor
        is visible or the fit is not confident.

    Raises:
        FrameError: wrong dtype or shape.
    """
    pts = floor_candidates(depth, intr, params)
    k = len(pts)
    if k < params.min_inliers:
        return _fail(
            f"too little floor: {k} candidate points (need {params.min_inliers}); point the "
            "sensor at open floor "
            f"or widen the prior (height {params.height_min_m:g}..{params.height_max_m:g} m, "
            f"tilt {params.tilt_min_deg:g}..{params.tilt_max_deg:g} deg)",
            cand=k,
        )
    s = math.radians(PRIOR_SLACK_DEG)
    accept = np.array(
        [
            [math.radians(params.tilt_min_deg) - s, math.radians(params.tilt_max_deg) + s],
            [math.radians(params.roll_max_deg) + s, 0.0],
            [params.height_min_m - PRIOR_SLACK_M, params.height_max_m + PRIOR_SLACK_M],
        ]
    )
    plane, n0 = ransac_plane(pts, params.ransac_iterations, params.inlier_dist_m, rng, accept)
    if n0 < PLANE_POINTS:
        return _fail(
            f"no floor plane inside the prior among {k} candidate points; check the prior", cand=k
        )
    plane, n_in, resid = refine_plane(pts, plane, params.inlier_dist_m)
    ratio = n_in / k
    height = float(plane[3])
    tilt, roll = tilt_roll_from_normal(plane[:3])
    if n_in < params.min_inliers or ratio < params.min_inlier_ratio:
        return _fail(
            f"too little floor: {n_in} of {k} candidate points fit one plane (need "
            f"{params.min_inliers} "
            f"and {params.min_inlier_ratio:.0%}); point the sensor at open floor",
            n_in,
            ratio,
            resid,
            k,
        )
    inside = (
        params.height_min_m - PRIOR_SLACK_M <= height <= params.height_max_m + PRIOR_SLACK_M
        and params.tilt_min_deg - PRIOR_SLACK_DEG <= tilt <= params.tilt_max_deg + PRIOR_SLACK_DEG
        and abs(roll) <= params.roll_max_deg + PRIOR_SLACK_DEG
    )
    if not inside:
        return _fail(
            f"no floor inside the prior: the best plane (height {height:.3f} m, tilt {tilt:.1f} "
            "deg, "
            f"roll {roll:.1f} deg) is outside it; widen the prior if the sensor really sits there",
            n_in,
            ratio,
            resid,
            k,
        )
    return PoseEstimate(True, height, tilt, roll, n_in, ratio, resid, k)
