"""Kinect 360 accelerometer axes and units, converted to depthnav's camera frame.

The accelerometer (Kionix KXSD9 in the motor base) reports counts, 819 per g (libfreenect's
FREENECT_COUNTS_PER_G). Its axes follow the Kinect SDK sensor frame: x to the sensor's left, y up,
z forward. A level sensor at rest reads about (0, +819, 0). depthnav's camera frame is x right,
y down, z forward, so the conversion is a 180 degree turn about z: (x, y, z) -> (-x, -y, +z).
Check: pitched down by t the device reads z = -819 sin t and we report -9.81 sin t, as
drivers/base.py requires. Nobody here has verified the signs on hardware; ``AXIS_SIGNS`` is the one
place to change them.
"""

from __future__ import annotations

import math

from drivers.base import STANDARD_GRAVITY_MPS2

COUNTS_PER_G = 819.0
AXIS_SIGNS = (-1.0, -1.0, 1.0)  # raw device axis -> camera axis, see the module docstring

TILT_STATUS = {0: "stopped", 1: "at_limit", 4: "moving"}


def accel_counts_to_camera(x: int, y: int, z: int) -> tuple[float, float, float]:
    """Raw accelerometer counts (device axes) to specific force in the camera frame, m/s^2."""
    scale = STANDARD_GRAVITY_MPS2 / COUNTS_PER_G
    sx, sy, sz = AXIS_SIGNS
    return (sx * x * scale + 0.0, sy * y * scale + 0.0, sz * z * scale + 0.0)  # + 0.0: no -0.0


def camera_to_accel_counts(accel_mps2: tuple[float, float, float]) -> tuple[int, int, int]:
    """Inverse of :func:`accel_counts_to_camera`, rounded to whole counts (int16 range)."""
    scale = COUNTS_PER_G / STANDARD_GRAVITY_MPS2
    out = []
    for sign, value in zip(AXIS_SIGNS, accel_mps2, strict=True):
        if not math.isfinite(value):
            raise ValueError(f"accelerometer value {value!r} is not finite")
        out.append(max(-32768, min(32767, round(sign * value * scale))))
    return (out[0], out[1], out[2])


def tilt_status_name(code: int) -> str:
    """The motor status byte as a TiltState status string."""
    return TILT_STATUS.get(code, "unknown")
