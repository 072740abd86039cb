"""The stages' parameters: ScanParams (scan, scan_paper, scan_table), CliffParams (cliff,
cliff_table) and PoseParams (pose, pose_fit), with their checks.

A stage and its table builder both import their parameters from here, so neither has to import
the other for them (the stage modules still export them under the old names).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from depthnav_daemon.errors import ConfigError
from depthnav_daemon.pipeline.geometry import (
    MAX_MOUNT_HEIGHT_M,
    MAX_ROLL_DEG,
    MAX_TILT_DEG,
    check_int,
    check_order,
    check_range,
)

METHODS = ("exact", "paper")  # the scan's and the cliff detector's: the same two names
MIN_ANGLE_INCREMENT_DEG = 0.001  # finer gives more bins than the kernels hold (scan_table.MAX_BINS)

# Depth noise per sensor type: 1-sigma sigma(z) = k * z^2 (z: optical depth, m), k in 1/m. A
# triangulating sensor's depth error is sigma_d * z^2 / (f b) for a disparity error sigma_d (px),
# focal length f (px) and baseline b (m).
DEPTH_NOISE_PRESETS: dict[str, float] = {
    # Kinect v1 (structured light): 1.425e-3 z^2, Khoshelham & Elberink 2012, Sensors 12(2)
    "structured_light": 1.425e-3,
    # RealSense D415 (active stereo, b = 0.055 m, f ~640 px at 848x480): Intel's datasheet bounds
    # the RMS error at 2 % of 2 m, k = 0.01 (sigma_d ~0.35 px). The 0.08 px of Intel's tuning
    # guide (k = 2.3e-3) holds for a textured wall facing the camera, not for a floor seen at a
    # grazing angle; a real D415 corridor floor needed about 10 cm of margin at 5 m from ~0.6 m
    # up, which 3 sigma of k = 0.01 gives (3 * k * z * h).
    "stereo_d415": 1.0e-2,
    # RealSense D435 (b = 0.050 m, f ~430 px at 848x480): the D415's sigma_d over its f b
    "stereo_d435": 1.65e-2,
}
MAX_DEPTH_NOISE_K = 1.0  # 1/m: sigma 1 m at 1 m; no depth sensor is that bad
SHOWN_CHARS = 40  # a bad value is shown up to this long in its message


@dataclass(frozen=True, slots=True)
class ScanParams:
    """Scan parameters. Shared: method, range limits. ``exact``: height band, rows, bin width.
    ``paper``: the original laserscan_kinect parameters with its shipped params.yaml values.

    Attributes:
        method: "exact" (level-frame, the default) or "paper" (eq. 1-5 as published).
        range_min_m, range_max_m: accepted range, metres (horizontal range for exact, optical
            depth for paper, as in the original).
        min_obstacle_height_m: exact: points lower than this above the floor are floor (the
            height margin that plays the role of the paper's e_g).
        max_obstacle_height_m: exact: points higher than this are ignored (above the robot).
        row_start, row_stop: exact: image rows [row_start, row_stop) used; row_stop -1 = to the
            bottom.
        row_step, col_step: exact: pixel strides.
        angle_increment_deg: exact: bin width; 0 = the width of the centre pixel.
        scan_height: paper: rows in the band centred on cy.
        depth_img_row_step: paper: row stride in the band.
        ground_remove: paper: eq. 5 ground removal.
        ground_margin_m: paper: e_g, metres of optical depth.
        tilt_compensation: paper: eq. 4 depth scaling.
    """

    method: str = "exact"
    range_min_m: float = 0.4
    range_max_m: float = 5.0
    min_obstacle_height_m: float = 0.05
    max_obstacle_height_m: float = 2.0
    row_start: int = 0
    row_stop: int = -1
    row_step: int = 1
    col_step: int = 1
    angle_increment_deg: float = 0.0
    scan_height: int = 400
    depth_img_row_step: int = 1
    ground_remove: bool = True
    ground_margin_m: float = 0.05
    tilt_compensation: bool = True

    def __post_init__(self) -> None:
        if self.method not in METHODS:
            raise ConfigError(
                f"scan.method={self.method!r} is not known (accepted: {', '.join(METHODS)})"
            )
        check_range("scan.range_min_m", self.range_min_m, 0.0, 100.0, " m")
        check_range("scan.range_max_m", self.range_max_m, 0.01, 100.0, " m")
        check_order("scan.range_min_m", self.range_min_m, "scan.range_max_m", self.range_max_m)
        check_range("scan.min_obstacle_height_m", self.min_obstacle_height_m, -10.0, 10.0, " m")
        check_range("scan.max_obstacle_height_m", self.max_obstacle_height_m, -10.0, 10.0, " m")
        check_order(
            "scan.min_obstacle_height_m",
            self.min_obstacle_height_m,
            "scan.max_obstacle_height_m",
            self.max_obstacle_height_m,
        )
        check_int("scan.row_start", self.row_start, 0, 8191)
        check_int("scan.row_stop", self.row_stop, -1, 8192)
        if self.row_stop != -1 and self.row_stop <= self.row_start:
            raise ConfigError(
                f"scan.row_stop ({self.row_stop}) must be above scan.row_start "
                f"({self.row_start}) or -1"
            )
        check_int("scan.row_step", self.row_step, 1, 64)
        check_int("scan.col_step", self.col_step, 1, 64)
        check_range("scan.angle_increment_deg", self.angle_increment_deg, 0.0, 10.0, " deg")
        if 0.0 < self.angle_increment_deg < MIN_ANGLE_INCREMENT_DEG:  # 5e-324: 0 rad, a / 0
            raise ConfigError(
                f"scan.angle_increment_deg={self.angle_increment_deg!r} is out of range "
                f"(accepted: 0 = the centre pixel's width, or {MIN_ANGLE_INCREMENT_DEG:g}..10 deg)"
            )
        check_int("scan.scan_height", self.scan_height, 1, 8192)
        check_int("scan.depth_img_row_step", self.depth_img_row_step, 1, 256)
        check_range("scan.ground_margin_m", self.ground_margin_m, 0.0, 10.0, " m")


@dataclass(frozen=True, slots=True)
class CliffParams:
    """Cliff detector parameters; defaults are cliff_detector's shipped params.yaml values.

    Attributes:
        method: "exact" (per-pixel floor with tilt and roll, the default) or "paper" (eq. 6).
        range_min_m, range_max_m: exact: horizontal range of the pixel's floor point, metres;
            paper: optical depth of the reading, metres (as the original).
        used_depth_height: rows used, counted from the image bottom (clamped to the image height).
        block_size: side of the square blocks, pixels.
        block_points_thresh: drop-off samples a block needs to be a negative obstacle (eq. 8).
        row_step, col_step: sample strides inside a block, pixels.
        ground_margin_m: e_g; exact: metres below the floor plane; paper: metres of optical depth.
        depth_noise: exact: the sensor's depth noise, 1-sigma k * z^2 (z optical depth, metres):
            a preset name (DEPTH_NOISE_PRESETS) or k in 1/m (a number or its text; 0 = none).
        noise_sigmas: exact: a reading counts only if it lies beyond the floor's depth by more
            than this many sigmas of the floor depth's noise as well as by the ground margin.
    """

    method: str = "exact"
    range_min_m: float = 0.5
    range_max_m: float = 5.0
    used_depth_height: int = 400
    block_size: int = 16
    block_points_thresh: int = 3
    row_step: int = 8
    col_step: int = 8
    ground_margin_m: float = 0.05
    depth_noise: str | float = "structured_light"
    noise_sigmas: float = 3.0

    def __post_init__(self) -> None:
        if self.method not in METHODS:
            raise ConfigError(
                f"cliff.method={self.method!r} is not known (accepted: {', '.join(METHODS)})"
            )
        check_range("cliff.range_min_m", self.range_min_m, 0.0, 100.0, " m")
        check_range("cliff.range_max_m", self.range_max_m, 0.01, 100.0, " m")
        check_order("cliff.range_min_m", self.range_min_m, "cliff.range_max_m", self.range_max_m)
        check_int("cliff.used_depth_height", self.used_depth_height, 1, 8192)
        check_int("cliff.block_size", self.block_size, 1, 256)
        check_int("cliff.row_step", self.row_step, 1, self.block_size)
        check_int("cliff.col_step", self.col_step, 1, self.block_size)
        check_int("cliff.block_points_thresh", self.block_points_thresh, 1, self.samples_per_block)
        check_range("cliff.ground_margin_m", self.ground_margin_m, 0.0, 10.0, " m")
        _ = self.depth_noise_k  # checks depth_noise
        check_range("cliff.noise_sigmas", self.noise_sigmas, 0.0, 10.0)

    @property
    def samples_per_block(self) -> int:
        """Samples one block holds: ceil(bs / row_step) * ceil(bs / col_step)."""
        return -(-self.block_size // self.row_step) * -(-self.block_size // self.col_step)

    @property
    def depth_noise_k(self) -> float:
        """k of the depth noise model sigma(z) = k * z^2, 1/m (``depth_noise`` resolved).

        Raises:
            ConfigError: neither a preset name nor a number in range.
        """
        v = self.depth_noise
        if isinstance(v, str) and v in DEPTH_NOISE_PRESETS:
            return DEPTH_NOISE_PRESETS[v]
        accepted = f"{', '.join(DEPTH_NOISE_PRESETS)} or k in 0..{MAX_DEPTH_NOISE_K:g} 1/m"
        shown = repr(v) if len(repr(v)) <= SHOWN_CHARS else repr(v)[: SHOWN_CHARS - 3] + "..."
        try:
            if isinstance(v, bool):  # float(True) is 1.0: a TOML true is not a noise model
                raise ValueError
            k = float(v)
        except (TypeError, ValueError, OverflowError):  # OverflowError: a 400-digit integer
            raise ConfigError(
                f"cliff.depth_noise={shown} is not known (accepted: {accepted})"
            ) from None
        if not (math.isfinite(k) and 0.0 <= k <= MAX_DEPTH_NOISE_K):
            raise ConfigError(f"cliff.depth_noise={shown} is out of range (accepted: {accepted})")
        return k


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
