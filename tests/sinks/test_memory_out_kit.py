"""Test-only helpers of the memory-out tests (no tests here): a synthetic drive with exact
odometry written as a recording, and the scene's geometry to check occupied cells against.

The odometry frame starts at the first true pose (sim/drive.py), so odometry coordinates are the
world's: a remembered cell's odometry position is compared with the world's boxes and step."""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import numpy as np
import numpy.typing as npt

from depthnav_daemon.pipeline.geometry import Mount
from depthnav_daemon.sim.drive import arc, render_drive
from depthnav_daemon.sim.synthetic import Box, Scene, step_down
from drivers.base import KINECT_V1, tilt_roll_to_accel
from drivers.formats.recording_writer import write_recording

F64 = npt.NDArray[np.float64]

MOUNT = Mount(0.5, 15.0, 0.0)
FPS = 10.0
FRAMES = 24  # 2.4 s: grids at 0, 0.5, 1.0, 1.5 and 2.0 s at the default 2 Hz
START = (0.4, -0.2, 0.0)  # not the origin: the odom -> base transform is not the identity
SPEED_MPS, TURN_DPS = 0.3, 8.0  # an arc to the left: base_link turns away from odom's axes
BOXES = (
    Box(2.0, 0.35, 0.3, 0.3, 0.4),  # ahead-left
    Box(2.3, -0.75, 0.25, 0.4, 0.6),  # ahead-right
)
STEP_X_M = 3.2  # the floor drops 0.2 m beyond x = 3.2 (odometry = world), for |y| < 1.5
STEP_HALF_WIDTH_M = 1.5
SCENE = Scene(boxes=BOXES, holes=(step_down(STEP_X_M, 0.2, half_width_m=STEP_HALF_WIDTH_M),))
TRAJECTORY = arc(SPEED_MPS, TURN_DPS, FPS, FRAMES, start=START)


def drive_recording(path: Path) -> Path:
    """The drive as a depthnav recording: 320 x 240 depth (exact), accelerometer, odometry."""
    accel = tilt_roll_to_accel(MOUNT.tilt_deg, MOUNT.roll_deg)
    drive = render_drive(SCENE, KINECT_V1.scaled(320, 240), MOUNT, TRAJECTORY)
    frames = [dataclasses.replace(d.frame, accel_mps2=accel) for d in drive]
    write_recording(path, frames, description="an arc past two boxes toward a step down")
    return path


def box_distance(xy: F64) -> F64:
    """Distance (N,) metres from odometry points (N, 2) to the nearest box footprint."""
    out = np.full(len(xy), np.inf)
    for b in BOXES:
        lx = np.abs(xy[:, 0] - b.x_m) - b.length_m / 2
        ly = np.abs(xy[:, 1] - b.y_m) - b.width_m / 2
        out = np.minimum(out, np.hypot(np.maximum(lx, 0.0), np.maximum(ly, 0.0)))
    return out


def beyond_step(xy: F64) -> npt.NDArray[np.float64]:
    """How far (N,) metres odometry points lie beyond the step's edge (negative: before it)."""
    return xy[:, 0] - STEP_X_M


def true_pose(t_s: float) -> tuple[float, float, float]:
    """The robot's true (= odometry) pose at frame time ``t_s``."""
    i = round(t_s * FPS)
    _, x, y, yaw = TRAJECTORY[i]
    return x, y, yaw


def to_odom(xy_base: F64, pose: tuple[float, float, float]) -> F64:
    """Base-frame points (N, 2) into the odometry frame at ``pose``."""
    x, y, yaw = pose
    c, s = math.cos(yaw), math.sin(yaw)
    return np.stack(
        [x + c * xy_base[:, 0] - s * xy_base[:, 1], y + s * xy_base[:, 0] + c * xy_base[:, 1]],
        axis=1,
    )
