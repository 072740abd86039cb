"""The bundled fixtures: synthetic recordings with exact ground truth, made by the scene generator.

``python -m depthnav_daemon.sim.fixtures [OUT_DIR]`` writes them again (they are committed under
fixtures/ so the quick start and the tests need no generation step).
"""

from __future__ import annotations

import sys
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from depthnav_daemon.pipeline.geometry import Mount
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


def main(argv: list[str] | None = None) -> int:
    out = Path((argv or sys.argv[1:] or ["fixtures"])[0])
    n = write_corridor_step(out / "corridor_step")
    print(f"wrote {n} frames to {out / 'corridor_step'}")  # noqa: T201
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
