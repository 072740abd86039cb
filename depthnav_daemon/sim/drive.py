"""Synthetic drives: the scene generator (``synthetic.render``) along a robot trajectory, with the
exact odometry and, on request, odometry with a scale error and noise.

A trajectory is a list of (t_s, x_m, y_m, yaw_rad) poses of the robot's base frame in the world.
Odometry is integrated from the true motion between frames, expressed in the robot's frame (what
wheel encoders measure): each step's forward/left motion is scaled by ``1 + scale_error`` and gets
Gaussian noise, its turn gets Gaussian noise; the odometry frame starts at the first true pose.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Iterator, Sequence
from dataclasses import dataclass

import numpy as np

from depthnav_daemon.pipeline.geometry import Mount
from depthnav_daemon.sim.synthetic import KinectNoise, Scene, SyntheticView, render
from drivers.base import Frame, Intrinsics

Pose = tuple[float, float, float]


@dataclass(frozen=True, slots=True)
class OdometryNoise:
    """What is wrong with the odometry.

    Attributes:
        scale_error: relative error of the distance travelled (0.02 = reports 2 % too far).
        sigma_m: Gaussian noise per frame on the forward and left motion, metres.
        sigma_rad: Gaussian noise per frame on the turn, radians.
    """

    scale_error: float = 0.0
    sigma_m: float = 0.0
    sigma_rad: float = 0.0


@dataclass(frozen=True, slots=True)
class DriveFrame:
    """One frame of a drive.

    Attributes:
        frame: the depth frame; ``frame.odom`` holds the odometry pose.
        pose: the true pose of the robot in the world.
        view: the rendered view with its ground truth (world frame).
    """

    frame: Frame
    pose: Pose
    view: SyntheticView


def straight(
    speed_mps: float,
    fps: float,
    frames: int,
    start: Pose = (0.0, 0.0, 0.0),
) -> list[tuple[float, float, float, float]]:
    """A straight drive along the start heading: (t_s, x_m, y_m, yaw_rad) per frame."""
    x0, y0, yaw = start
    out = []
    for i in range(frames):
        d = speed_mps * i / fps
        out.append((i / fps, x0 + d * math.cos(yaw), y0 + d * math.sin(yaw), yaw))
    return out


def turn_in_place(
    rate_dps: float, fps: float, frames: int, start: Pose = (0.0, 0.0, 0.0)
) -> list[tuple[float, float, float, float]]:
    """A turn in place at ``rate_dps`` (counter-clockwise positive)."""
    x0, y0, yaw0 = start
    return [(i / fps, x0, y0, yaw0 + math.radians(rate_dps) * i / fps) for i in range(frames)]


def arc(
    speed_mps: float,
    rate_dps: float,
    fps: float,
    frames: int,
    start: Pose = (0.0, 0.0, 0.0),
) -> list[tuple[float, float, float, float]]:
    """Driving and turning at once: a circular arc at ``speed_mps`` turning ``rate_dps``
    (counter-clockwise positive; 0 = straight)."""
    x0, y0, a0 = start
    w = math.radians(rate_dps)
    out = []
    for i in range(frames):
        t = i / fps
        a = a0 + w * t
        if w == 0.0:
            x, y = x0 + speed_mps * t * math.cos(a0), y0 + speed_mps * t * math.sin(a0)
        else:
            r = speed_mps / w
            x = x0 + r * (math.sin(a) - math.sin(a0))
            y = y0 - r * (math.cos(a) - math.cos(a0))
        out.append((t, x, y, a))
    return out


def odometry(
    poses: Sequence[Pose],
    noise: OdometryNoise | None = None,
    rng: np.random.Generator | None = None,
) -> list[Pose]:
    """The odometry a robot would report along true ``poses`` (module docstring)."""
    noise = noise or OdometryNoise()
    if (noise.sigma_m > 0 or noise.sigma_rad > 0) and rng is None:
        raise ValueError("odometry noise needs an rng (numpy.random.Generator)")
    out: list[Pose] = [tuple(poses[0])]  # type: ignore[list-item]
    for (x0, y0, a0), (x1, y1, a1) in itertools.pairwise(poses):
        c, s = math.cos(a0), math.sin(a0)
        fwd = c * (x1 - x0) + s * (y1 - y0)
        left = -s * (x1 - x0) + c * (y1 - y0)
        turn = math.remainder(a1 - a0, 2 * math.pi)
        k = 1.0 + noise.scale_error
        fwd, left = fwd * k, left * k
        if rng is not None:
            fwd += rng.normal(0.0, noise.sigma_m) if noise.sigma_m else 0.0
            left += rng.normal(0.0, noise.sigma_m) if noise.sigma_m else 0.0
            turn += rng.normal(0.0, noise.sigma_rad) if noise.sigma_rad else 0.0
        ox, oy, oa = out[-1]
        co, so = math.cos(oa), math.sin(oa)
        out.append((ox + co * fwd - so * left, oy + so * fwd + co * left, oa + turn))
    return out


def render_drive(
    scenes: Scene | Sequence[Scene],
    intr: Intrinsics,
    mount: Mount,
    trajectory: Sequence[tuple[float, float, float, float]],
    *,
    depth_noise: KinectNoise | None = None,
    odom_noise: OdometryNoise | None = None,
    rng: np.random.Generator | None = None,
) -> Iterator[DriveFrame]:
    """Render a sensor at ``mount`` on a robot driving ``trajectory``.

    Args:
        scenes: the scene, or one scene per frame (things that move or disappear).
        intr: camera intrinsics.
        mount: the sensor's height, tilt, roll and placement on the robot.
        trajectory: (t_s, x_m, y_m, yaw_rad) per frame, true poses in the world.
        depth_noise: Kinect-like depth noise, or None for exact depth.
        odom_noise: odometry errors, or None for exact odometry.
        rng: randomness for either noise.

    Yields:
        A DriveFrame per pose; ``frame.odom`` is the (possibly noisy) odometry.
    """
    poses = [(x, y, a) for _, x, y, a in trajectory]
    odom = odometry(poses, odom_noise, rng)
    for i, (t, *pose) in enumerate(trajectory):
        scene = scenes if isinstance(scenes, Scene) else scenes[i]
        p = (float(pose[0]), float(pose[1]), float(pose[2]))
        view = render(scene, intr, mount, depth_noise, rng, robot_pose=p)
        frame = Frame(i, float(t), view.depth_mm, intr, odom=odom[i])
        yield DriveFrame(frame, p, view)
