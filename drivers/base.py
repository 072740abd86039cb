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
import numbers
from dataclasses import dataclass, field
from typing import Any, Protocol

import numpy as np
import numpy.typing as npt

# the lens maps live in drivers.lens_model; the pipeline (which imports only this module of
# drivers, tests/test_layering.py) reaches them here
from drivers.lens_model import (  # noqa: F401 - re-exported
    COEFF_KEYS,
    EQUIDISTANT,
    MODEL_KEYS,
    MODELS,
    MODELS_TEXT,
    PLUMB_BOB,
    distortion_problem,
    lens_map,
    plumb_bob,
    rational_coeffs,
    theta_d,
)
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


DISTORTION_KEYS = MODEL_KEYS[PLUMB_BOB]  # OpenCV / ROS plumb_bob order
LENS_KEYS = ("distortion_model", *COEFF_KEYS)  # every lens field of Intrinsics
MAX_RADIAL_COEFF = 100.0  # |k1| .. |k6|: far beyond any real lens (Kinect-like: |k| < 1)
MAX_TANGENTIAL_COEFF = 1.0  # |p1|, |p2| (real lenses: |p| < 0.01)


@dataclass(frozen=True, slots=True)
class Intrinsics:
    """Intrinsics of a depth image, in pixels (pixel centres at integer coordinates), with a lens
    model as ROS CameraInfo names it (``drivers.lens_model``): ``plumb_bob`` (k1, k2, p1, p2,
    k3; all 0 = an ideal pinhole, the default), ``rational_polynomial`` (k1-k6, p1, p2) or
    ``equidistant`` (fisheye, k1-k4). Coefficients outside the model must be 0. Depth images of
    a distorting lens are read as recorded and their rays undistorted (pipeline/lens.py).
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
    k4: float = 0.0
    k5: float = 0.0
    k6: float = 0.0
    distortion_model: str = PLUMB_BOB

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
        self._check_lens_fields()
        if self.has_distortion:
            self._check_distortion()

    @property
    def distortion(self) -> tuple[float, ...]:
        """The lens model's coefficients in its ROS CameraInfo D order (``distortion_keys``):
        (k1, k2, p1, p2, k3) for plumb_bob, as OpenCV orders them."""
        return tuple(getattr(self, key) for key in self.distortion_keys)

    @property
    def distortion_keys(self) -> tuple[str, ...]:
        """The names of ``distortion``'s coefficients, in order."""
        return MODEL_KEYS[self.distortion_model]

    @property
    def has_distortion(self) -> bool:
        """True unless an ideal pinhole (plumb_bob with every coefficient 0); a fisheye always
        distorts."""
        return self.distortion_model != PLUMB_BOB or any(self.distortion)

    def _check_lens_fields(self) -> None:
        """A known model, finite coefficients in range, and none set outside the model (a k4
        given with plumb_bob is refused: silently dropping it would be a wrong lens)."""
        model = self.distortion_model
        if model not in MODELS:
            raise ValueError(
                f"lens model {short_repr(model)} cannot be expressed (depthnav models "
                f"{MODELS_TEXT})"
            )
        for name in COEFF_KEYS:
            value = getattr(self, name)
            limit = MAX_TANGENTIAL_COEFF if name.startswith("p") else MAX_RADIAL_COEFF
            if not (isinstance(value, (int, float)) and math.isfinite(value)):
                raise ValueError(f"intrinsics {name}={short_repr(value)} is not a finite number")
            if abs(value) > limit:
                raise ValueError(
                    f"intrinsics {name}={value!r} is out of range (-{limit:g}..{limit:g})"
                )
            if value and name not in MODEL_KEYS[model]:
                raise ValueError(
                    f"intrinsics {name}={value!r} is not a coefficient of the {model} lens model "
                    f"({', '.join(MODEL_KEYS[model])}); depthnav models {MODELS_TEXT}: say which "
                    "with distortion_model"
                )

    def _check_distortion(self) -> None:
        coeffs = tuple(float(c) for c in self.distortion)
        problem = distortion_problem(
            self.width,
            self.height,
            float(self.fx),
            float(self.fy),
            float(self.cx),
            float(self.cy),
            self.distortion_model,
            coeffs,
        )
        if problem:
            keys, model = self.distortion_keys, self.distortion_model
            listed = ", ".join(f"{k}={v:g}" for k, v in zip(keys, coeffs, strict=True))
            named = "" if model == PLUMB_BOB else f"{model} "
            raise ValueError(
                f"lens distortion {named}({listed}) {problem} ({self.width}x{self.height}, "
                f"fx={self.fx:g}), so it cannot be undone (check the order is {', '.join(keys)} "
                f"as OpenCV and ROS {model} give it, and that the coefficients belong to this "
                "camera)"
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
            **{key: getattr(self, key) for key in LENS_KEYS},
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
class SensorPlacement:
    """Where a recording says its sensor sits on the robot (a bag's ``/tf_static``): the
    optical centre at (x_m, y_m, height_m) in the base frame (REP 103: x forward, y left, z up,
    origin on the floor), looking yaw_deg counter-clockwise, tilt_deg down, roll_deg left side
    up; ``source`` says where it came from, for the log."""

    height_m: float
    tilt_deg: float
    roll_deg: float
    x_m: float
    y_m: float
    yaw_deg: float
    source: str


@dataclass(frozen=True, slots=True)
class DeviceInfo:
    """What an opened driver says about its device."""

    name: str  # "Kinect 360 (1414)", "replay: corridor_step"
    serial: str | None
    spec: str  # the canonical spec it was opened with
    intrinsics: Intrinsics | None = None
    has_accel: bool = False
    placement: SensorPlacement | None = None  # where the recording says the sensor sits


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
