"""Synthetic depth scenes with exact ground truth: floor, boxes, walls, table tops, steps down
and holes.

The world frame: x forward, y left, z up, floor at z = 0. The robot's base frame sits at
``robot_pose`` (x, y, yaw) in the world (default: the world origin, so world = base frame); the
sensor's foot sits at the mount's placement (x_m, y_m, yaw_deg) in the base frame, its optical
centre height_m above the floor. With the default placement and pose the world is the level frame
at the sensor's foot. A scene is ray-cast for a camera at any height, tilt and roll
(drivers.base / pipeline.geometry conventions); optional Kinect-like or stereo noise comes from a
seeded ``numpy.random.Generator``. Used by the tests, the benchmark and the bundled fixtures;
``sim.drive`` renders sequences along a robot trajectory with it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import numpy.typing as npt

from depthnav_daemon.pipeline.geometry import Mount, level_rays

# the ground truth in the horizontal plane lives in sim/truth.py; importable from here as before
from depthnav_daemon.sim.truth import (
    in_drop_off,
    truth_drop_ranges,
    truth_obstacle_interval,
    truth_obstacle_ranges,
)
from depthnav_daemon.sim.truth import slab as _slab
from drivers.base import Intrinsics

F64 = npt.NDArray[np.float64]

LABEL_NONE = 0  # the ray hit nothing within the sensor's range
LABEL_FLOOR = 1
LABEL_HOLE = 2  # the bottom or a wall of a hole / the lower floor beyond a step
LABEL_BOX0 = 3  # box i has label LABEL_BOX0 + i


@dataclass(frozen=True, slots=True)
class Box:
    """A solid box, axis-aligned up to a yaw about z.

    Attributes:
        x_m, y_m: centre of the footprint in the world frame, metres.
        length_m, width_m: footprint size along the box's own x and y (before yaw), metres.
        top_m: height of the top face above the floor, metres.
        base_m: height of the bottom face (0 = standing on the floor; > 0 for a table top).
        yaw_deg: rotation of the footprint about z, degrees, counter-clockwise.
    """

    x_m: float
    y_m: float
    length_m: float
    width_m: float
    top_m: float
    base_m: float = 0.0
    yaw_deg: float = 0.0


@dataclass(frozen=True, slots=True)
class Hole:
    """A rectangular region of the floor cut down to ``depth_m`` below it (a step down when large).

    Attributes:
        x_min_m, x_max_m, y_min_m, y_max_m: footprint in the world frame, metres.
        depth_m: how far the bottom lies below the floor, metres (> 0).
    """

    x_min_m: float
    x_max_m: float
    y_min_m: float
    y_max_m: float
    depth_m: float


def wall(
    distance_m: float, height_m: float = 2.5, thickness_m: float = 0.1, half_width_m: float = 50.0
) -> Box:
    """A wall across the view, its face ``distance_m`` ahead of the sensor."""
    return Box(distance_m + thickness_m / 2, 0.0, thickness_m, 2 * half_width_m, height_m)


def table(
    x_m: float, y_m: float, length_m: float, width_m: float, top_m: float, thickness_m: float = 0.03
) -> Box:
    """A table top (without legs) whose upper face is ``top_m`` above the floor."""
    return Box(x_m, y_m, length_m, width_m, top_m, base_m=top_m - thickness_m)


def step_down(
    distance_m: float, drop_m: float, half_width_m: float = 50.0, far_m: float = 100.0
) -> Hole:
    """A step down across the view: beyond ``distance_m`` ahead the floor is ``drop_m`` lower."""
    return Hole(distance_m, far_m, -half_width_m, half_width_m, drop_m)


@dataclass(frozen=True, slots=True)
class Scene:
    """What stands on (and is cut into) a flat floor."""

    boxes: tuple[Box, ...] = ()
    holes: tuple[Hole, ...] = ()
    floor: bool = True


@dataclass(frozen=True, slots=True)
class KinectNoise:
    """Kinect-like depth errors, applied in disparity space like the structured-light sensor.

    Depth noise grows with z^2 through a Gaussian disparity error, disparity is quantised to
    1/``subpixel`` pixel, pixels at depth edges and toward far range go missing.
    """

    focal_px: float = 580.0
    baseline_m: float = 0.075
    disparity_sigma_px: float = 0.07
    subpixel: int = 8
    edge_dropout: float = 0.5  # probability that a pixel on a depth discontinuity reads 0
    edge_jump: float = 0.04  # relative depth jump to a neighbour that counts as an edge
    far_dropout_start_m: float = 4.0  # dropout rises linearly from here to the sensor's max range
    random_dropout: float = 0.002


@dataclass(frozen=True, slots=True)
class StereoNoise:
    """Active-stereo (RealSense D4xx-like) depth errors: a Gaussian disparity error, so the depth
    error grows with z^2 (sigma_z = z^2 sigma_d / (f b)), disparity quantised to 1/``subpixel``
    pixel, and random dropout.

    The defaults are a D415 at 848x480 (f ~640 px, b = 0.055 m) with sigma_d = 0.35 px: k =
    sigma_d / (f b) ~ 0.01 1/m, Intel's datasheet bound (RMS 2 % at 2 m) and the cliff stage's
    "stereo_d415" preset. Intel's tuning guide quotes 0.08 px for a textured wall facing the
    camera; a floor at a grazing angle matches worse.
    """

    focal_px: float = 640.0
    baseline_m: float = 0.055
    disparity_sigma_px: float = 0.35
    subpixel: int = 32
    random_dropout: float = 0.002


@dataclass(frozen=True, slots=True)
class SyntheticView:
    """A rendered depth image with its ground truth.

    Attributes:
        depth_mm: (H, W) uint16 sensor output, millimetres, 0 = no reading (noise applied).
        depth_true_m: (H, W) float64 exact optical-axis depth of the hit, +inf where nothing is hit.
        points_m: (H, W, 3) float64 exact hit points in the world frame, NaN where nothing is hit.
        height_m: (H, W) float64 exact height of the hit above the floor (negative in holes), NaN
            none.
        label: (H, W) int16, LABEL_* per pixel.
    """

    depth_mm: npt.NDArray[np.uint16]
    depth_true_m: F64
    points_m: F64
    height_m: F64
    label: npt.NDArray[np.int16]
    intrinsics: Intrinsics
    mount: Mount
    scene: Scene = field(repr=False)


def _box_local(box: Box, origin: F64, dirs: F64) -> tuple[F64, F64]:
    """Ray origin and directions in the box's frame (centre of footprint, yaw removed)."""
    c, s = math.cos(math.radians(box.yaw_deg)), math.sin(math.radians(box.yaw_deg))
    rot = np.array([[c, s, 0.0], [-s, c, 0.0], [0.0, 0.0, 1.0]])  # world -> box
    o = rot @ (origin - np.array([box.x_m, box.y_m, 0.0]))
    return o, _rotate(dirs, rot)


def _rotate(dirs: F64, rot: F64) -> F64:
    """``dirs @ rot.T`` for (N, 3) rows, column by column (numpy's matmul with an inner size of 3
    is ~10x slower than this on large N)."""
    out = np.empty_like(dirs)
    for i in range(3):
        out[:, i] = rot[i, 0] * dirs[:, 0] + rot[i, 1] * dirs[:, 1] + rot[i, 2] * dirs[:, 2]
    return out


def cast(scene: Scene, origin: F64, dirs: F64) -> tuple[F64, npt.NDArray[np.int16]]:
    """Nearest hit of each ray; (N,) ray parameters (+inf = miss) and (N,) labels.

    Args:
        scene: what to hit.
        origin: (3,) ray origin in the world frame.
        dirs: (N, 3) ray directions (any length; the parameter is in units of that length).
    """
    n = dirs.shape[0]
    t_best = np.full(n, np.inf)
    label = np.full(n, LABEL_NONE, dtype=np.int16)
    if scene.floor:
        dz = dirs[:, 2]
        down = dz < 0
        with np.errstate(divide="ignore", invalid="ignore"):
            t_floor = np.where(down, -origin[2] / np.where(down, dz, -1.0), np.inf)
        with np.errstate(invalid="ignore"):
            hit = origin[None, :] + t_floor[:, None] * dirs
        t_best = t_floor.copy()
        label[down] = LABEL_FLOOR
        for hole in scene.holes:
            inside = (
                down
                & (hit[:, 0] >= hole.x_min_m)
                & (hit[:, 0] <= hole.x_max_m)
                & (hit[:, 1] >= hole.y_min_m)
                & (hit[:, 1] <= hole.y_max_m)
            )
            lo = np.array([hole.x_min_m, hole.y_min_m, -hole.depth_m])
            hi = np.array([hole.x_max_m, hole.y_max_m, 0.0])
            _, t_exit = _slab(origin[None, :], dirs[inside], lo, hi)
            t_best[inside] = t_exit
            label[inside] = LABEL_HOLE
    for i, box in enumerate(scene.boxes):
        o, d = _box_local(box, origin, dirs)
        lo = np.array([-box.length_m / 2, -box.width_m / 2, box.base_m])
        hi = np.array([box.length_m / 2, box.width_m / 2, box.top_m])
        t_in, t_out = _slab(o[None, :], d, lo, hi)
        hit = (t_in <= t_out) & (t_in > 0) & (t_in < t_best)
        t_best[hit] = t_in[hit]
        label[hit] = LABEL_BOX0 + i
    return t_best, label


def render(
    scene: Scene,
    intr: Intrinsics,
    mount: Mount,
    noise: KinectNoise | StereoNoise | None = None,
    rng: np.random.Generator | None = None,
    min_range_m: float = 0.35,
    max_range_m: float = 8.0,
    robot_pose: tuple[float, float, float] = (0.0, 0.0, 0.0),
) -> SyntheticView:
    """Ray-cast ``scene`` for a sensor at ``mount`` on a robot at ``robot_pose``.

    Args:
        scene: floor, boxes and holes.
        intr: camera intrinsics (any resolution).
        mount: sensor height, tilt (positive down) and roll (positive left side up), and its
            placement on the robot (x_m, y_m, yaw_deg in the base frame).
        noise: Kinect-like or stereo noise model, or None for exact depth.
        rng: randomness for the noise; required when ``noise`` is given.
        min_range_m, max_range_m: the sensor reads 0 outside this optical-axis depth range.
        robot_pose: (x_m, y_m, yaw_rad) of the robot's base frame in the world.

    Returns:
        The depth image and its ground truth (points in the world frame).
    """
    dirs = level_rays(intr, mount.tilt_rad, mount.roll_rad).reshape(-1, 3)  # per unit optical depth
    sx, sy, syaw = sensor_world_pose(mount, robot_pose)
    if syaw != 0.0:
        c, s = math.cos(syaw), math.sin(syaw)
        dirs = _rotate(dirs, np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]))
    origin = np.array([sx, sy, mount.height_m])
    t, label = cast(scene, origin, dirs)
    shape = (intr.height, intr.width)
    t = t.reshape(shape)
    label = label.reshape(shape)
    with np.errstate(invalid="ignore"):
        points = origin + t[..., None] * dirs.reshape(*shape, 3)
    points[~np.isfinite(t)] = np.nan
    label[~np.isfinite(t)] = LABEL_NONE

    z = t.copy()
    if noise is not None:
        if rng is None:
            raise ValueError("render() with noise needs an rng (numpy.random.Generator)")
        if isinstance(noise, StereoNoise):
            z = _apply_stereo_noise(z, noise, rng)
        else:
            z = _apply_noise(z, noise, rng, max_range_m)
    in_range = np.isfinite(z) & (z >= min_range_m) & (z <= max_range_m)
    depth_mm = np.where(in_range, np.rint(np.where(in_range, z, 0) * 1000.0), 0).astype(np.uint16)
    label = np.where(np.isfinite(t) & (t <= max_range_m), label, LABEL_NONE).astype(np.int16)
    return SyntheticView(depth_mm, t, points, points[..., 2].copy(), label, intr, mount, scene)


def sensor_world_pose(
    mount: Mount, robot_pose: tuple[float, float, float] = (0.0, 0.0, 0.0)
) -> tuple[float, float, float]:
    """(x_m, y_m, yaw_rad) of the sensor's foot in the world: the robot's pose composed with the
    mount's placement on the robot."""
    rx, ry, ryaw = robot_pose
    c, s = math.cos(ryaw), math.sin(ryaw)
    return (
        rx + c * mount.x_m - s * mount.y_m,
        ry + s * mount.x_m + c * mount.y_m,
        ryaw + mount.yaw_rad,
    )


def _apply_noise(z: F64, noise: KinectNoise, rng: np.random.Generator, max_range_m: float) -> F64:
    """Kinect-like noise on exact depth ``z`` (H, W) metres; dropped pixels become NaN."""
    fb = noise.focal_px * noise.baseline_m
    with np.errstate(divide="ignore"):
        disp = fb / z
    disp = disp + rng.normal(0.0, noise.disparity_sigma_px, z.shape)
    disp = np.round(disp * noise.subpixel) / noise.subpixel
    with np.errstate(divide="ignore", invalid="ignore"):
        out = np.where(disp > 0, fb / disp, np.nan)
    out[~np.isfinite(z)] = np.nan
    # depth discontinuities: compare with the 4-neighbours of the exact image
    zf = np.where(np.isfinite(z), z, 1e6)
    jump = np.zeros(z.shape, dtype=bool)
    rel = noise.edge_jump
    dv = np.abs(np.diff(zf, axis=0)) > rel * np.minimum(zf[1:], zf[:-1])
    dh = np.abs(np.diff(zf, axis=1)) > rel * np.minimum(zf[:, 1:], zf[:, :-1])
    jump[1:] |= dv
    jump[:-1] |= dv
    jump[:, 1:] |= dh
    jump[:, :-1] |= dh
    drop = jump & (rng.random(z.shape) < noise.edge_dropout)
    far = np.clip(
        (z - noise.far_dropout_start_m) / max(max_range_m - noise.far_dropout_start_m, 1e-6), 0, 1
    )
    drop |= rng.random(z.shape) < np.nan_to_num(far, nan=1.0)
    drop |= rng.random(z.shape) < noise.random_dropout
    out[drop] = np.nan
    return out


def _apply_stereo_noise(z: F64, noise: StereoNoise, rng: np.random.Generator) -> F64:
    """Stereo noise on exact depth ``z`` (H, W) metres; dropped pixels become NaN."""
    fb = noise.focal_px * noise.baseline_m
    with np.errstate(divide="ignore"):
        disp = fb / z
    disp = disp + rng.normal(0.0, noise.disparity_sigma_px, z.shape)
    disp = np.round(disp * noise.subpixel) / noise.subpixel
    with np.errstate(divide="ignore", invalid="ignore"):
        out = np.where(disp > 0, fb / disp, np.nan)
    out[~np.isfinite(z)] = np.nan
    out[rng.random(z.shape) < noise.random_dropout] = np.nan
    return out


__all__ = [
    "Box",
    "Hole",
    "KinectNoise",
    "Scene",
    "StereoNoise",
    "SyntheticView",
    "cast",
    "in_drop_off",
    "render",
    "sensor_world_pose",
    "step_down",
    "table",
    "truth_drop_ranges",
    "truth_obstacle_interval",
    "truth_obstacle_ranges",
    "wall",
]
