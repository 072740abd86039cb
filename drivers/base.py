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

import functools
import math
import numbers
from dataclasses import dataclass, field
from typing import Any, Protocol

import numpy as np
import numpy.typing as npt

from drivers.values import short_repr

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


DISTORTION_KEYS = ("k1", "k2", "p1", "p2", "k3")  # OpenCV / ROS plumb_bob order
MAX_RADIAL_COEFF = 100.0  # |k1|, |k2|, |k3|: far beyond any real lens (Kinect-like: |k| < 1)
MAX_TANGENTIAL_COEFF = 1.0  # |p1|, |p2| (real lenses: |p| < 0.01)
# the lens model must stay invertible this far beyond the image's edges (pixels, share of the side)
LENS_MARGIN_PX = 16.0
LENS_MARGIN_SHARE = 0.05
_FOLD_LIMIT_R = 20.0  # ideal normalised radius (87 deg off axis) the invertibility walk stops at


def plumb_bob(
    x: npt.NDArray[np.float64], y: npt.NDArray[np.float64], coeffs: tuple[float, ...]
) -> tuple[npt.NDArray[np.float64], ...]:
    """The plumb-bob (Brown-Conrady) lens map and its Jacobian, OpenCV's formula.

    Ideal normalised coordinates (x, y) = (X/Z, Y/Z) map to distorted ones
    xd = x R + 2 p1 x y + p2 (r2 + 2 x2), yd = y R + p1 (r2 + 2 y2) + 2 p2 x y,
    R = 1 + k1 r2 + k2 r4 + k3 r6, r2 = x2 + y2; pixels are then (fx xd + cx, fy yd + cy).

    Args:
        x, y: ideal normalised coordinates, equal shapes.
        coeffs: (k1, k2, p1, p2, k3).

    Returns:
        (xd, yd, dxd/dx, dxd/dy, dyd/dx, dyd/dy), each shaped like ``x``.
    """
    k1, k2, p1, p2, k3 = coeffs
    xx, yy, xy = x * x, y * y, x * y
    r2 = xx + yy
    radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
    slope = k1 + r2 * (2.0 * k2 + 3.0 * k3 * r2)  # dR/d(r2)
    xd = x * radial + 2.0 * p1 * xy + p2 * (r2 + 2.0 * xx)
    yd = y * radial + p1 * (r2 + 2.0 * yy) + 2.0 * p2 * xy
    cross = 2.0 * xy * slope + 2.0 * p1 * x + 2.0 * p2 * y
    dxx = radial + 2.0 * xx * slope + 2.0 * p1 * y + 6.0 * p2 * x
    dyy = radial + 2.0 * yy * slope + 6.0 * p1 * y + 2.0 * p2 * x
    return xd, yd, dxx, cross, cross, dyy


@functools.lru_cache(maxsize=64)
def _distortion_problem(
    width: int, height: int, fx: float, fy: float, cx: float, cy: float, coeffs: tuple[float, ...]
) -> str | None:
    """Why this lens model cannot be inverted over the image, or None when it can.

    Walks outwards from the principal point along 94 directions in ideal normalised coordinates
    until the distorted point leaves the image (a margin beyond its edges): on the way the
    map must keep a positive Jacobian and move outwards, so every pixel has exactly one ray. A
    model that folds back (a polynomial's turning point inside the image) fails.
    """
    # 90 directions and the corners' (radial distortion keeps a point's direction)
    edges_u, edges_v = (-PIXEL_HALF, width - PIXEL_HALF), (-PIXEL_HALF, height - PIXEL_HALF)
    corners = [math.atan2(b - cy, a - cx) for a in edges_u for b in edges_v]
    theta = np.concatenate((np.linspace(0.0, 2.0 * math.pi, 90, endpoint=False), corners))
    theta = theta[:, None]
    # steps of 0.004 (2.3 pixels at fx 580) near the axis, coarser out where only a fold can be
    r = np.concatenate((np.linspace(0.0, 4.0, 1001)[1:], np.linspace(4.0, _FOLD_LIMIT_R, 81)[1:]))
    r = r[None, :]
    x, y = r * np.cos(theta), r * np.sin(theta)
    xd, yd, dxx, dxy, dyx, dyy = plumb_bob(x, y, coeffs)
    u, v = fx * xd + cx, fy * yd + cy
    # the table builders also look half a sample step past the edge pixels
    margin_u = min(LENS_MARGIN_PX, LENS_MARGIN_SHARE * width) + PIXEL_HALF
    margin_v = min(LENS_MARGIN_PX, LENS_MARGIN_SHARE * height) + PIXEL_HALF
    inside = (np.abs(u - (width - 1) / 2) <= (width - 1) / 2 + margin_u) & (
        np.abs(v - (height - 1) / 2) <= (height - 1) / 2 + margin_v
    )
    outward = np.diff(xd * np.cos(theta) + yd * np.sin(theta), axis=1, prepend=0.0) > 0
    good = (dxx * dyy - dxy * dyx > 0) & outward
    # each direction is fine up to where it first leaves the image
    first_out = np.where(inside.all(axis=1), r.shape[1], np.argmin(inside, axis=1))
    before = np.arange(r.shape[1])[None, :] < first_out[:, None]
    if np.any(before & ~good):
        return "folds back inside the image"
    if np.any(first_out == r.shape[1]):
        return "never reaches the image edge"
    return None


@dataclass(frozen=True, slots=True)
class Intrinsics:
    """Intrinsics of a depth image, in pixels (pixel centres at integer coordinates), with the
    plumb-bob lens model (OpenCV / ROS ``plumb_bob``: radial k1, k2, k3, tangential p1, p2;
    all 0 = an ideal pinhole). See ``plumb_bob`` for the formula; depth images of a distorting
    lens are read as recorded and their rays undistorted (pipeline/lens.py).
    """

    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float
    k1: float = 0.0
    k2: float = 0.0
    p1: float = 0.0
    p2: float = 0.0
    k3: float = 0.0

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
        if self.has_distortion:
            self._check_distortion()

    @property
    def distortion(self) -> tuple[float, float, float, float, float]:
        """(k1, k2, p1, p2, k3), the plumb_bob order of OpenCV and ROS CameraInfo D."""
        return (self.k1, self.k2, self.p1, self.p2, self.k3)

    @property
    def has_distortion(self) -> bool:
        """True when any lens coefficient is non-zero (else an ideal pinhole)."""
        return any(self.distortion)

    def _check_distortion(self) -> None:
        for name, value in zip(DISTORTION_KEYS, self.distortion, strict=True):
            limit = MAX_TANGENTIAL_COEFF if name.startswith("p") else MAX_RADIAL_COEFF
            if not (isinstance(value, (int, float)) and math.isfinite(value)):
                raise ValueError(f"intrinsics {name}={value!r} is not a finite number")
            if abs(value) > limit:
                raise ValueError(
                    f"intrinsics {name}={value!r} is out of range (-{limit:g}..{limit:g})"
                )
        coeffs = tuple(float(c) for c in self.distortion)
        problem = _distortion_problem(
            self.width, self.height, float(self.fx), float(self.fy), self.cx, self.cy, coeffs
        )
        if problem:
            listed = ", ".join(f"{k}={v:g}" for k, v in zip(DISTORTION_KEYS, coeffs, strict=True))
            raise ValueError(
                f"lens distortion ({listed}) {problem} ({self.width}x{self.height}, "
                f"fx={self.fx:g}), "
                "so it cannot be undone (check the order is k1, k2, p1, p2, k3 as OpenCV and ROS "
                "plumb_bob give it, and that the coefficients belong to this camera)"
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
        """The same camera at another resolution (pixel-centre convention kept; the lens
        coefficients act on normalised coordinates, so they carry over unchanged)."""
        sx, sy = width / self.width, height / self.height
        return Intrinsics(
            width,
            height,
            self.fx * sx,
            self.fy * sy,
            (self.cx + 0.5) * sx - 0.5,
            (self.cy + 0.5) * sy - 0.5,
            *self.distortion,
        )

    def as_array(self) -> npt.NDArray[np.float64]:
        """[fx, fy, cx, cy] as float64, the layout recordings' frames.npz stores (the lens
        coefficients go in recording.toml)."""
        return np.array([self.fx, self.fy, self.cx, self.cy], dtype=np.float64)


# Kinect 360 depth camera, a common calibration (the ROS test intrinsics: 570, cx 314, cy 235)
KINECT_V1 = Intrinsics(640, 480, 580.0, 580.0, 319.5, 239.5)


@dataclass(frozen=True, slots=True)
class TiltState:
    """State of a motorised tilt mount (the Kinect 360 motor)."""

    angle_deg: float | None  # motor angle reported by the device, positive = up (device's own sign)
    status: str  # "stopped", "at_limit", "moving", or "unknown"


# Odometry bounds: every pose the obstacle memory may use passes check_odom_pose (and every
# source's sample check_odom_time too). The limits refuse what no wheeled robot's odometry says,
# with a wide margin to what the memory's grid handles: positions stay float64 and cells int64
# (at the smallest 5 mm cell, 1e7 m is 2e9 cells; float64 resolves 2e-9 m there), so a UTM-sized
# coordinate (northing up to 1e7 m) is still taken.
ODOM_POSITION_LIMIT_M = 1e7  # |x_m|, |y_m|: 10,000 km, a quarter of the Earth's circumference
ODOM_YAW_LIMIT_RAD = 1e6  # |yaw_rad| before wrapping: 160,000 turns of an unwrapping source
ODOM_TIME_LIMIT_S = 1e10  # |t_s|: Unix time to the year 2286, any boot or monotonic clock
ODOM_REFUSAL_KINDS = ("malformed", "not_finite", "out_of_range", "out_of_order")


@dataclass(frozen=True, slots=True)
class OdomRefusal:
    """Why an odometry sample is refused.

    Attributes:
        kind: one of ODOM_REFUSAL_KINDS (malformed: not a number or not readable; not_finite: NaN
            or infinite; out_of_range: beyond the limits; out_of_order: time going back).
        reason: a short message naming the field and its (shortened) value.
    """

    kind: str
    reason: str

    def __str__(self) -> str:
        return self.reason


def _odom_number(name: str, value: Any, limit: float, unit: str) -> float | OdomRefusal:
    """``value`` as a float within +-``limit``, or why not (an integer of any size is compared
    exactly, never converted first: 10**400 is out of range, not an OverflowError)."""
    number: int | float
    if type(value) is float:  # the usual case, without the cost of the ABC checks (~1 us each)
        if -limit <= value <= limit:
            return value
        number = value
    elif isinstance(value, (bool, np.bool_)) or not isinstance(value, numbers.Real):
        return OdomRefusal("malformed", f"{name}={short_repr(value)} is not a number")
    elif isinstance(value, numbers.Integral):
        number = int(value)
    else:
        try:
            number = float(value)
        except (OverflowError, TypeError, ValueError):  # e.g. a Fraction of huge parts
            return OdomRefusal(
                "out_of_range", f"{name}={short_repr(value)} is beyond +-{limit:g}{unit}"
            )
    if isinstance(number, float) and not math.isfinite(number):
        return OdomRefusal("not_finite", f"{name}={short_repr(number)} is not finite")
    if abs(number) > limit:
        return OdomRefusal(
            "out_of_range", f"{name}={short_repr(number)} is beyond +-{limit:g}{unit}"
        )
    return float(number)


def check_odom_pose(x_m: Any, y_m: Any, yaw_rad: Any) -> tuple[float, float, float] | OdomRefusal:
    """One odometry pose checked against the limits above: (x_m, y_m, yaw_rad) as floats with the
    yaw wrapped to [-pi, pi], or the refusal (the first bad field)."""
    x = _odom_number("x_m", x_m, ODOM_POSITION_LIMIT_M, " m")
    if isinstance(x, OdomRefusal):
        return x
    y = _odom_number("y_m", y_m, ODOM_POSITION_LIMIT_M, " m")
    if isinstance(y, OdomRefusal):
        return y
    yaw = _odom_number("yaw_rad", yaw_rad, ODOM_YAW_LIMIT_RAD, " rad")
    if isinstance(yaw, OdomRefusal):
        return yaw
    return x, y, math.remainder(yaw, 2.0 * math.pi)


def check_odom_time(t_s: Any) -> float | OdomRefusal:
    """An odometry sample's time (seconds, the source's clock) as a float, or the refusal."""
    return _odom_number("t_s", t_s, ODOM_TIME_LIMIT_S, " s")


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
            source has it (a recording with ``odom``), else None. As the source gave it: the
            memory takes only a pose that passes :func:`check_odom_pose`.
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
