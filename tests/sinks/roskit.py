"""Test-only helpers of the ROS sinks: a recording whose scans hold NaN, +inf and -inf, and checks
of decoded ROS messages against the stdout JSON."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np

from depthnav_daemon.pipeline.geometry import Mount
from depthnav_daemon.sim.synthetic import Box, Scene, render, step_down
from depthnav_daemon.sinks.json.message import decode_ranges
from drivers.base import KINECT_V1, Frame, tilt_roll_to_accel
from drivers.formats.recording_writer import write_recording

MOUNT = Mount(height_m=0.5, tilt_deg=12.0, roll_deg=0.0)


def special_recording(path: Path, n: int = 6, size: tuple[int, int] = (320, 240)) -> Path:
    """Frames whose scans have all three REP 117 codes: a box closer than range_min (-inf), a
    narrow wall (+inf beside it), pixels without depth across the band (NaN), a step down."""
    intr = KINECT_V1.scaled(*size)
    scene = Scene(
        boxes=(Box(0.3, 0.25, 0.1, 0.1, 0.4), Box(2.0, 0.0, 0.1, 1.0, 1.0)),
        holes=(step_down(1.4, 0.3, half_width_m=0.4),),
    )
    frames = []
    for i in range(n):
        depth = render(scene, intr, MOUNT).depth_mm.copy()
        depth[:, int(size[0] * 0.8) : int(size[0] * 0.85)] = 0  # no reading: NaN bearings
        accel = tilt_roll_to_accel(MOUNT.tilt_deg, MOUNT.roll_deg)
        frames.append(Frame(i, 0.5 + i / 15.0, depth, intr, accel_mps2=accel))
    write_recording(path, frames, description="NaN, +inf and -inf in every scan")
    return path


def same_ranges(ros: Any, json_ranges: list) -> None:
    """ROS float32 ranges equal the JSON ones: NaN, +inf, -inf where they are, values to 1 mm."""
    want = decode_ranges(json_ranges)
    have = np.asarray(ros, dtype=np.float64)
    assert have.shape == want.shape
    for code in (np.isnan, np.isposinf, np.isneginf):
        np.testing.assert_array_equal(code(have), code(want))
    finite = np.isfinite(want)
    np.testing.assert_allclose(have[finite], want[finite], atol=0.0005 + 1e-6)


def has_all_codes(json_ranges: list) -> bool:
    r = decode_ranges(json_ranges)
    return bool(np.isnan(r).any() and np.isposinf(r).any() and np.isneginf(r).any())


def rotate(q: tuple[float, float, float, float], v: tuple[float, float, float]) -> np.ndarray:
    """Rotate ``v`` by the quaternion (x, y, z, w)."""
    x, y, z, w = q
    u = np.array([x, y, z])
    vec = np.asarray(v, dtype=np.float64)
    return vec + 2.0 * np.cross(u, np.cross(u, vec) + w * vec)


def optical_axis_in_base(tilt_deg: float) -> np.ndarray:
    """Where a camera pitched down by ``tilt_deg`` (no roll) looks, in the base frame."""
    t = math.radians(tilt_deg)
    return np.array([math.cos(t), 0.0, -math.sin(t)])
