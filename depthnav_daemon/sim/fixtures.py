"""The bundled fixtures: synthetic recordings with exact ground truth, made by the scene generator.

``python -m depthnav_daemon.sim.fixtures [OUT_DIR]`` writes them again (they are committed under
fixtures/ so the quick start and the tests need no generation step).
"""

from __future__ import annotations

import dataclasses
import sys
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from depthnav_daemon.pipeline.geometry import Mount
from depthnav_daemon.sim.drive import render_drive, straight
from depthnav_daemon.sim.synthetic import Box, Hole, KinectNoise, Scene, render, step_down
from drivers.base import KINECT_V1, Frame, Intrinsics, tilt_roll_to_accel
from drivers.formats.recording_writer import write_recording

CORRIDOR_MOUNT = Mount(0.55, 15.0, 0.0)
CORRIDOR_STEP_M = 2.0
CORRIDOR_SCENE = Scene(
    boxes=(
        Box(1.6, 0.55, 0.3, 0.3, 0.35),  # a box on the left
        Box(1.3, -0.45, 0.25, 0.25, 0.15, yaw_deg=25),  # a low box on the right
        Box(1.9, 1.3, 4.0, 0.1, 1.2),  # the corridor's left wall
        Box(1.9, -1.2, 4.0, 0.1, 1.2),  # and its right wall
    ),
    holes=(step_down(CORRIDOR_STEP_M, 0.18, half_width_m=1.15), Hole(1.0, 1.2, 0.1, 0.3, 0.25)),
)


def accel_for(
    mount: Mount, rng: np.random.Generator, sigma_mps2: float = 0.02
) -> tuple[float, float, float]:
    """Specific force a still sensor at ``mount`` reads in the camera frame, with a little noise."""
    a = np.array(tilt_roll_to_accel(mount.tilt_deg, mount.roll_deg))
    a += rng.normal(0.0, sigma_mps2, 3)
    return (float(a[0]), float(a[1]), float(a[2]))


def synthetic_frames(
    scene: Scene, intr: Intrinsics, mount: Mount, n: int, seed: int, fps: float = 30.0
) -> Iterator[Frame]:
    """``n`` noisy frames of a still scene, each with its accelerometer reading."""
    rng = np.random.default_rng(seed)
    for i in range(n):
        view = render(scene, intr, mount, KinectNoise(), rng)
        yield Frame(i, i / fps, view.depth_mm, intr, accel_for(mount, rng))


def write_corridor_step(out: Path, n: int = 12) -> int:
    m = CORRIDOR_MOUNT
    truth = {
        "mount_height_m": m.height_m,
        "tilt_deg": m.tilt_deg,
        "roll_deg": m.roll_deg,
        "cliff_distance_m": CORRIDOR_STEP_M,
        "step_drop_m": 0.18,
        "hole_x_m": [1.0, 1.2],
        "hole_y_m": [0.1, 0.3],
        "box_left_front_m": [1.45, 0.55],
        "box_right_front_m": [1.175, -0.45],
    }
    return write_recording(
        out,
        synthetic_frames(CORRIDOR_SCENE, KINECT_V1, m, n, seed=2026),
        description="Synthetic corridor, 18 cm step down at 2.0 m, a 20 cm hole, two boxes; "
        "Kinect v1 intrinsics, 0.55 m high, pitched 15 degrees down; Kinect-like noise",
        truth=truth,
        device="synthetic (depthnav_daemon.sim.fixtures)",
    )


# the drive: 0.3 m/s toward a 15 cm step 3 m ahead, sensor 0.5 m high, 15 deg down
DRIVE_MOUNT = Mount(0.5, 15.0, 0.0)
DRIVE_STEP_M = 3.0
DRIVE_SPEED_MPS = 0.3
DRIVE_BOX = Box(1.6, 0.75, 0.3, 0.3, 0.4)  # a box the robot passes on its left
DRIVE_SCENE = Scene(boxes=(DRIVE_BOX,), holes=(step_down(DRIVE_STEP_M, 0.15),))
DRIVE_INTRINSICS = KINECT_V1.scaled(320, 240)  # downsampled: the fixture stays small


def drive_frames(n: int = 12, seed: int = 2027) -> list[Frame]:
    """The drive toward the step, one frame every 0.25 m (0.83 s) from 3.0 m to 0.25 m of the
    edge, Kinect-like noise, exact odometry on every frame, accelerometer readings."""
    rng = np.random.default_rng(seed)
    fps = DRIVE_SPEED_MPS / 0.25
    out = []
    for d in render_drive(
        DRIVE_SCENE,
        DRIVE_INTRINSICS,
        DRIVE_MOUNT,
        straight(DRIVE_SPEED_MPS, fps, n),
        depth_noise=KinectNoise(),
        rng=rng,
    ):
        out.append(dataclasses.replace(d.frame, accel_mps2=accel_for(DRIVE_MOUNT, rng)))
    return out


def write_drive_step(out: Path, n: int = 12) -> int:
    m = DRIVE_MOUNT
    truth = {
        "mount_height_m": m.height_m,
        "tilt_deg": m.tilt_deg,
        "roll_deg": m.roll_deg,
        "step_distance_m": DRIVE_STEP_M,
        "step_drop_m": 0.15,
        "speed_mps": DRIVE_SPEED_MPS,
        "box_m": [DRIVE_BOX.x_m, DRIVE_BOX.y_m, DRIVE_BOX.length_m, DRIVE_BOX.width_m],
        "box_top_m": DRIVE_BOX.top_m,
        "odometry": "exact (the true pose of every frame)",
    }
    return write_recording(
        out,
        drive_frames(n),
        description="Synthetic drive at 0.3 m/s toward a 15 cm step down 3 m ahead, passing a box "
        "on the left; 320x240 (Kinect v1 downsampled), 0.5 m high, pitched 15 degrees down; "
        "Kinect-like noise; odometry per frame",
        truth=truth,
        device="synthetic (depthnav_daemon.sim.fixtures)",
    )


def main(argv: list[str] | None = None) -> int:
    out = Path((argv or sys.argv[1:] or ["fixtures"])[0])
    for name, write in (("corridor_step", write_corridor_step), ("drive_step", write_drive_step)):
        if (out / name).exists():
            print(f"{out / name} exists; remove it to write it again")  # noqa: T201
            continue
        n = write(out / name)
        print(f"wrote {n} frames to {out / name}")  # noqa: T201
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
