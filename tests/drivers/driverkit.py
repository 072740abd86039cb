"""Test-only helpers for the driver tests: small synthetic frames with asymmetric intrinsics."""

from __future__ import annotations

import math
import os
import subprocess
import sys
from pathlib import Path

import numpy as np

from drivers.base import Frame, Intrinsics
from drivers.fakenect_format import disparity_to_mm_table

REPO = Path(__file__).resolve().parents[2]

# Asymmetric on purpose (fx != fy, cx != W/2, H != W) so swapped axes fail.
SMALL = Intrinsics(64, 48, 61.5, 57.25, 30.25, 22.75)
VGA = Intrinsics(640, 480, 583.0, 575.5, 318.25, 243.75)


def ramp_frames(n: int = 4, intr: Intrinsics = SMALL, seed: int = 7, accel: bool = True) -> list[Frame]:
    """``n`` frames: random uint16 depth (fixed seed), a few holes, 30 fps timestamps."""
    rng = np.random.default_rng(seed)
    frames = []
    for i in range(n):
        depth = rng.integers(400, 9000, size=(intr.height, intr.width), dtype=np.uint16)
        depth[rng.random(depth.shape) < 0.05] = 0
        tilt = math.radians(5.0 + i)
        acc = (0.1 * i, -9.81 * math.cos(tilt), -9.81 * math.sin(tilt)) if accel else None
        frames.append(Frame(seq=i, timestamp_s=i / 30.0, depth_mm=depth, intrinsics=intr, accel_mps2=acc))
    return frames


def kinect_exact_frames(n: int = 3, intr: Intrinsics = VGA, seed: int = 11) -> list[Frame]:
    """VGA frames whose depths are all exact 11-bit disparity depths, so every format is lossless."""
    rng = np.random.default_rng(seed)
    table = disparity_to_mm_table()
    raw = rng.integers(300, 1050, size=(n, intr.height, intr.width))
    raw[rng.random(raw.shape) < 0.05] = 2047
    depth = table[raw].astype(np.uint16)
    return [
        Frame(seq=i, timestamp_s=i / 30.0, depth_mm=depth[i], intrinsics=intr,
              accel_mps2=(0.0, -9.7, -1.4))
        for i in range(n)
    ]


def run_isolated(code: str, *args: str, env: dict[str, str] | None = None, timeout_s: float = 60.0
                 ) -> subprocess.CompletedProcess[str]:
    """Run Python code in a child process, so a native crash fails one test, not the run."""
    full_env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(REPO), str(Path(__file__).parent)]),
                **(env or {})}
    return subprocess.run(
        [sys.executable, "-c", code, *args], capture_output=True, text=True, timeout=timeout_s,
        env=full_env, cwd=str(REPO),
    )
