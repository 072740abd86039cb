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

import dataclasses
import math
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from depthnav_daemon.errors import ConfigError
from depthnav_daemon.pipeline.geometry import F64, MAX_ROLL_DEG, MAX_TILT_DEG

# PoseParams lives apart for pose_fit; importable here as before
from depthnav_daemon.pipeline.params import PoseParams
from depthnav_daemon.pipeline.pose_fit import (
    PLANE_POINTS,
    _pose_table,
    floor_candidates,
    ransac_plane,
    refine_plane,
)
from drivers.base import STANDARD_GRAVITY_MPS2 as G_MPS2
from drivers.base import Intrinsics

PRIOR_SLACK_DEG = 2.0  # fitted angles may exceed the prior by this much (noise at its edges)
PRIOR_SLACK_M = 0.02

# Every plausible mount, for a floor search that knows nothing of the mount (``depthnav
# calibrate``; the daemon until an unconfigured mount's floor is found): a sensor on a mast or a
# pole, pitched up or looking down. The default prior (PoseParams) is narrower, for live tracking
# around a known mount. Not beyond 80 deg down: a wall seen head-on is a floor seen from straight
# above, so without a tilt sensor a steeper mount needs a prior in [pose].
WHOLE_RANGE = {
    "height_min_m": 0.05,
    "height_max_m": 3.0,
    "tilt_min_deg": -30.0,
    "tilt_max_deg": 80.0,
    "roll_max_deg": 30.0,
}
TILT_SENSOR_WINDOW_DEG = 10.0  # the wide search around a tilt sensor's tilt and roll


def wide_prior(params: PoseParams, tilt_roll: tuple[float, float] | None = None) -> PoseParams:
    """The floor search for a mount nobody gave: a prior the user's config sets (any prior field
    changed from its default) wins; else a tilt sensor's tilt and roll +-10 deg at any height;
    else the whole plausible range (:data:`WHOLE_RANGE`).

    Args:
        params: the configured pose parameters (the fit's own settings are kept).
        tilt_roll: (tilt, roll) degrees from an accelerometer or IMU, or None.
    """
    default = PoseParams()
    if any(getattr(params, k) != getattr(default, k) for k in WHOLE_RANGE):
        return params
    wide = dataclasses.replace(params, **WHOLE_RANGE)
    if tilt_roll is None:
        return wide
    tilt, roll = round(tilt_roll[0]), abs(round(tilt_roll[1]))
    w = TILT_SENSOR_WINDOW_DEG
    return dataclasses.replace(
        wide,
        tilt_min_deg=max(-MAX_TILT_DEG, tilt - w),
        tilt_max_deg=min(MAX_TILT_DEG, tilt + w),
        roll_max_deg=min(MAX_ROLL_DEG, roll + w),
    )


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


def _fail(
    reason: str, inliers: int = 0, ratio: float = 0.0, residual: float = math.nan, cand: int = 0
) -> PoseEstimate:
    return PoseEstimate(False, math.nan, math.nan, math.nan, inliers, ratio, residual, cand, reason)


def prepare_pose(intr: Intrinsics, params: PoseParams) -> None:
    """Build and cache the floor candidates' table of this camera and prior window (what the
    first :func:`estimate_pose` with them would build: 4-14 ms at 640x480), e.g. on a worker."""
    _pose_table(intr, params)


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
