"""Types shared by all drivers, and the conventions every driver follows.

Conventions (pinned by tests/pipeline/test_conventions.py and tests/drivers/):
- Depth is uint16 millimetres along the optical axis; 0 means "no reading".
- Camera frame is RDF: x right, y down, z forward. Pixel (0, 0) is the centre of the top-left pixel.
- Accelerometer readings are specific force in m/s^2 in the camera frame: at rest and level about
  (0, -9.81, 0); pitched down by t about (0, -9.81 cos t, -9.81 sin t).
- Tilt is positive when the sensor is pitched down toward the floor; roll is positive when the
  left side is up. ``tilt_roll_to_accel`` is this convention written as a formula.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Protocol

import numpy as np
import numpy.typing as npt

DepthMM = npt.NDArray[np.uint16]  # (H, W) millimetres, 0 = no reading
STANDARD_GRAVITY_MPS2 = 9.80665  # the accelerometer convention's g (m/s^2)
MM_PER_M = 1000.0
UINT16_MAX = 65535  # the largest depth a uint16 millimetre image holds
MAX_IMAGE_SIDE = 8192  # pixels each way, for every image depthnav reads
MAX_FOCAL_PX = 1e5
PIXEL_HALF = 0.5  # pixel centres at integers: the image spans -0.5 .. size - 0.5


def tilt_roll_to_accel(
    tilt_deg: float, roll_deg: float, g_mps2: float = STANDARD_GRAVITY_MPS2
) -> tuple[float, float, float]:
    """The camera-frame specific force (m/s^2) a sensor at rest with this attitude reads.

    Pitched down by t and rolled (left side up) by r it reads
    (-g sin r cos t, -g cos r cos t, -g sin t); the inverse is
    ``depthnav_daemon.pipeline.pose.tilt_roll_from_accel``.
    """
    t, r = math.radians(tilt_deg), math.radians(roll_deg)
    return (
        -g_mps2 * math.sin(r) * math.cos(t),
        -g_mps2 * math.cos(r) * math.cos(t),
        -g_mps2 * math.sin(t),
    )


@dataclass(frozen=True, slots=True)
class Intrinsics:
    """Pinhole intrinsics of a depth image, in pixels (pixel centres at integer coordinates)."""

    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float

    def __post_init__(self) -> None:
        if not (isinstance(self.width, int) and isinstance(self.height, int)):
            raise ValueError(
                f"intrinsics width/height must be integers, got {self.width!r}x{self.height!r}"
            )
        if not (1 <= self.width <= MAX_IMAGE_SIDE and 1 <= self.height <= MAX_IMAGE_SIDE):
            raise ValueError(
                f"intrinsics size {self.width}x{self.height} is out of range "
                "(1..8192 pixels each way)"
            )
        for name in ("fx", "fy"):
            value = getattr(self, name)
            if not (math.isfinite(value) and 1.0 <= value <= MAX_FOCAL_PX):
                raise ValueError(f"intrinsics {name}={value!r} is out of range (1..100000 pixels)")
        for name, limit in (("cx", self.width), ("cy", self.height)):
            value = getattr(self, name)
            if not (math.isfinite(value) and -PIXEL_HALF <= value <= limit - PIXEL_HALF):
                raise ValueError(
                    f"intrinsics {name}={value!r} is outside the image (-0.5..{limit - 0.5} pixels)"
                )

    @classmethod
    def from_fov(
        cls, width: int, height: int, hfov_deg: float, vfov_deg: float | None = None
    ) -> Intrinsics:
        """Ideal intrinsics from a field of view, principal point at the image centre.

        Args:
            width, height: image size in pixels.
            hfov_deg: horizontal field of view, degrees.
            vfov_deg: vertical field of view, degrees; None for square pixels (fy = fx).
        """
        fx = (width / 2.0) / math.tan(math.radians(hfov_deg) / 2.0)
        fy = fx if vfov_deg is None else (height / 2.0) / math.tan(math.radians(vfov_deg) / 2.0)
        return cls(width, height, fx, fy, (width - 1) / 2.0, (height - 1) / 2.0)

    def scaled(self, width: int, height: int) -> Intrinsics:
        """The same camera at another resolution (pixel-centre convention kept)."""
        sx, sy = width / self.width, height / self.height
        return Intrinsics(
            width,
            height,
            self.fx * sx,
            self.fy * sy,
            (self.cx + 0.5) * sx - 0.5,
            (self.cy + 0.5) * sy - 0.5,
        )

    def as_array(self) -> npt.NDArray[np.float64]:
        """[fx, fy, cx, cy] as float64, the layout recordings store."""
        return np.array([self.fx, self.fy, self.cx, self.cy], dtype=np.float64)


# Kinect 360 depth camera, a common calibration (the ROS test intrinsics: 570, cx 314, cy 235)
KINECT_V1 = Intrinsics(640, 480, 580.0, 580.0, 319.5, 239.5)


@dataclass(frozen=True, slots=True)
class TiltState:
    """State of a motorised tilt mount (the Kinect 360 motor)."""

    angle_deg: float | None  # motor angle reported by the device, positive = up (device's own sign)
    status: str  # "stopped", "at_limit", "moving", or "unknown"


@dataclass(frozen=True, slots=True)
class Frame:
    """One depth frame. The depth array is read-only once constructed.

    Attributes:
        seq: frame sequence number from the driver, increasing from 0.
        timestamp_s: sensor or host monotonic time of the frame, seconds.
        depth_mm: (H, W) uint16 millimetres along the optical axis, 0 = no reading.
        intrinsics: intrinsics of ``depth_mm``.
        accel_mps2: specific force in the camera frame (m/s^2), or None without an accelerometer.
        tilt: motor state of a motorised mount, or None.
        odom: the robot's pose (x_m, y_m, yaw_rad) in the odometry frame at this frame, when the
            source has it (a recording with ``odom``), else None.
    """

    seq: int
    timestamp_s: float
    depth_mm: DepthMM
    intrinsics: Intrinsics
    accel_mps2: tuple[float, float, float] | None = None
    tilt: TiltState | None = field(default=None)
    odom: tuple[float, float, float] | None = None

    def __post_init__(self) -> None:
        expected = (self.intrinsics.height, self.intrinsics.width)
        if self.depth_mm.dtype != np.uint16 or self.depth_mm.shape != expected:
            raise ValueError(
                f"depth_mm must be uint16 {expected}, "
                f"got {self.depth_mm.dtype} {self.depth_mm.shape}"
            )
        self.depth_mm.setflags(write=False)


@dataclass(frozen=True, slots=True)
class DeviceInfo:
    """What an opened driver says about its device."""

    name: str  # "Kinect 360 (1414)", "replay: corridor_step"
    serial: str | None
    spec: str  # the canonical spec it was opened with
    intrinsics: Intrinsics | None = None
    has_accel: bool = False


class Driver(Protocol):
    """A source of depth frames.

    Constructing a driver does no I/O. ``open()`` touches the device; ``close()`` is safe to call
    twice.
    """

    def open(self) -> DeviceInfo:
        """Open the device or file and return what it is."""
        ...

    def read_frame(self, timeout_s: float = 1.0) -> Frame | None:
        """Return the next frame, or None when a finite source (replay) is exhausted.

        Raises:
            FrameTimeout: no frame arrived within ``timeout_s``.
            DeviceLost: the device went away.
            DriverError: any other failure; the message is fit to show the user.
        """
        ...

    def close(self) -> None:
        """Release the device. Safe to call more than once."""
        ...
