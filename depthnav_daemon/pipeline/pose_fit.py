"""The floor pose stage's two steps (the paper's eq. 9-14): floor candidate points from the depth
image within the prior (eq. 9-12), then a RANSAC plane through them and its least-squares
refinement (eq. 13-14). ``pose.estimate_pose`` composes them."""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from depthnav_daemon.pipeline.geometry import (
    F32,
    F64,
    cam_to_level,
    depth_to_mm,
    frozen_table,
    pixel_rays,
)
from depthnav_daemon.pipeline.params import PoseParams
from depthnav_daemon.pipeline.pose_kernels import (
    candidates_kernel,
    count_candidates_kernel,
    hypotheses_kernel,
    plane_moments_kernel,
    ransac_count_kernel,
)
from depthnav_daemon.pipeline.table_kernels import pose_envelope_kernel
from drivers.base import Intrinsics

SCORE_CHUNK = 32  # RANSAC hypotheses scored per batch
RANSAC_CONFIDENCE = 0.999
ENVELOPE_STEP_DEG = 4.0
PLANE_POINTS = 3  # the fewest points that define a plane


# --- candidates (eq. 9-12) ------------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class _PoseTable:
    rows: slice
    cols: slice
    zlo_mm: npt.NDArray[np.uint16]  # (Hs, Ws) candidate iff zlo <= d <= zhi
    zhi_mm: npt.NDArray[np.uint16]
    rays: F32  # (Hs, Ws, 3) camera ray per metre of depth (eq. 12)


# 16: each sensor's StageTables keeps 8 prior windows ready (daemon.stage_tables.KEEP_READY); two
# sensors' windows fit without evicting a window the frame loop counts on
@functools.lru_cache(maxsize=16)
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
    n_tilt = max(2, math.ceil((params.tilt_max_deg - params.tilt_min_deg) / ENVELOPE_STEP_DEG) + 1)
    n_roll = max(2, math.ceil(2 * params.roll_max_deg / ENVELOPE_STEP_DEG) + 1)
    tilts = np.radians(np.linspace(params.tilt_min_deg, params.tilt_max_deg, n_tilt))
    rolls = np.radians(np.linspace(-params.roll_max_deg, params.roll_max_deg, n_roll))
    rows_kz = np.array([cam_to_level(float(t), float(r))[2] for t in tilts for r in rolls])
    lo_kz = np.empty(rays.shape[:2])
    hi_kz = np.empty(rays.shape[:2])
    # -kz, metres down per metre of depth, min and max over the prior's grid of tilts and rolls;
    # compiled (numpy took 11-14 ms at 640x480 on the frame path of a new prior)
    pose_envelope_kernel(
        *(np.ascontiguousarray(rays[..., k]) for k in range(3)), rows_kz, lo_kz, hi_kz
    )
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
