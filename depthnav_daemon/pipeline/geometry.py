"""Camera model and sensor mount: rays, rotations into the level frame, depth checks.

Frames (DEVELOPERS.md, pinned by tests/pipeline/test_conventions.py):
- camera (RDF): x right, y down, z forward; pixel (0, 0) is the centre of the top-left pixel;
- level frame at the sensor (FLU, REP 103): x forward, y left, z up; the floor is z = -height_m.
A camera point p maps to the level frame as Ry(tilt) Rx(roll) M p, M: (right, down, forward) ->
(forward, left, up). Tilt positive = pitched down; roll positive = left side up.
- robot base frame (REP 103): x forward, y left, z up, origin on the floor under the robot's centre.
The sensor's level frame is yawed by ``yaw_deg`` (counter-clockwise) and its foot sits at
(x_m, y_m) in the base frame: a level-frame point q maps to the base frame as Rz(yaw) q + (x, y, 0).
"""

from __future__ import annotations

import dataclasses
import functools
import math
from dataclasses import dataclass
from typing import TypeVar

import numpy as np
import numpy.typing as npt

from depthnav_daemon.errors import ConfigError, FrameError
from depthnav_daemon.pipeline import lens
from drivers.base import UINT16_MAX, Intrinsics

F32 = npt.NDArray[np.float32]
F64 = npt.NDArray[np.float64]
T = TypeVar("T")

# (right, down, forward) -> (forward, left, up)
M_CAM_TO_FLU: F64 = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])
M_CAM_TO_FLU.setflags(write=False)

MAX_MOUNT_HEIGHT_M = 10.0
MAX_TILT_DEG = 89.0
MAX_ROLL_DEG = 45.0
MAX_PLACEMENT_M = 10.0  # |x_m|, |y_m| of a sensor on the robot
MAX_YAW_DEG = 180.0


def frozen_table(table: T) -> T:
    """Make every numpy array field of a dataclass read-only (a cached table shared between
    calls)."""
    for f in dataclasses.fields(table):  # type: ignore[arg-type]
        value = getattr(table, f.name)
        if isinstance(value, np.ndarray):
            value.setflags(write=False)
    return table


def check_range(name: str, value: float, lo: float, hi: float, unit: str = "") -> float:
    """Return ``value`` as float, or raise ConfigError naming it and the accepted range."""
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise ConfigError(
            f"{name}={value!r} is not a number (accepted: {lo:g}..{hi:g}{unit})"
        ) from None
    if not (math.isfinite(v) and lo <= v <= hi):
        raise ConfigError(f"{name}={value!r} is out of range (accepted: {lo:g}..{hi:g}{unit})")
    return v


def check_order(
    lo_name: str, lo: float, hi_name: str, hi: float, *, strict: bool = True, why: str = ""
) -> None:
    """Raise ConfigError unless ``lo`` < ``hi`` (``lo`` <= ``hi`` when not strict), naming both."""
    if lo >= hi if strict else lo > hi:
        rule = "be below" if strict else "not exceed"
        raise ConfigError(
            f"{lo_name} ({lo}) must {rule} {hi_name} ({hi}){': ' + why if why else ''}"
        )


def check_int(name: str, value: int, lo: int, hi: int) -> int:
    """Return ``value`` as int, or raise ConfigError naming it and the accepted range."""
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or not lo <= value <= hi:
        raise ConfigError(f"{name}={value!r} is out of range (accepted: integers {lo}..{hi})")
    return int(value)


@dataclass(frozen=True, slots=True)
class Mount:
    """Pose of the depth sensor over the floor and on the robot.

    Attributes:
        height_m: height of the optical centre above the floor, metres (0 < h <= 10).
        tilt_deg: pitch, positive = pitched down toward the floor, degrees (|tilt| <= 89).
        roll_deg: roll about the optical axis, positive = left side up, degrees (|roll| <= 45).
        x_m, y_m: the optical centre's position in the robot's base frame (REP 103: x forward,
            y left, origin on the floor under the robot's centre), metres (|x|, |y| <= 10).
        yaw_deg: heading of the sensor on the robot, counter-clockwise, 0 = looking forward,
            degrees (-180..180).

    The floor pose estimate gives height, tilt and roll; x, y and yaw come from the config.
    """

    height_m: float = 0.5
    tilt_deg: float = 0.0
    roll_deg: float = 0.0
    x_m: float = 0.0
    y_m: float = 0.0
    yaw_deg: float = 0.0

    def __post_init__(self) -> None:
        check_range("mount height_m", self.height_m, 0.01, MAX_MOUNT_HEIGHT_M, " m")
        check_range("mount tilt_deg", self.tilt_deg, -MAX_TILT_DEG, MAX_TILT_DEG, " deg")
        check_range("mount roll_deg", self.roll_deg, -MAX_ROLL_DEG, MAX_ROLL_DEG, " deg")
        check_range("mount x_m", self.x_m, -MAX_PLACEMENT_M, MAX_PLACEMENT_M, " m")
        check_range("mount y_m", self.y_m, -MAX_PLACEMENT_M, MAX_PLACEMENT_M, " m")
        check_range("mount yaw_deg", self.yaw_deg, -MAX_YAW_DEG, MAX_YAW_DEG, " deg")

    @property
    def tilt_rad(self) -> float:
        return math.radians(self.tilt_deg)

    @property
    def roll_rad(self) -> float:
        return math.radians(self.roll_deg)

    @property
    def yaw_rad(self) -> float:
        return math.radians(self.yaw_deg)

    @property
    def placed(self) -> bool:
        """True when the sensor is not at the base origin looking forward (x, y or yaw set)."""
        return self.x_m != 0.0 or self.y_m != 0.0 or self.yaw_deg != 0.0

    def level_part(self) -> Mount:
        """This mount without its placement on the robot (what the sensor-frame stages use)."""
        if not self.placed:
            return self
        return _level_mount(self.height_m, self.tilt_deg, self.roll_deg)

    def with_level(self, height_m: float, tilt_deg: float, roll_deg: float) -> Mount:
        """This placement with another height, tilt and roll (a floor or tilt sensor estimate)."""
        return Mount(height_m, tilt_deg, roll_deg, self.x_m, self.y_m, self.yaw_deg)


@functools.lru_cache(maxsize=64)
def _level_mount(height_m: float, tilt_deg: float, roll_deg: float) -> Mount:
    """Mount(height, tilt, roll), made once (its checks cost microseconds on the frame path)."""
    return Mount(height_m, tilt_deg, roll_deg)


def rot_x(angle_rad: float) -> F64:
    """Right-hand rotation about x, (3, 3)."""
    c, s = math.cos(angle_rad), math.sin(angle_rad)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


def rot_z(angle_rad: float) -> F64:
    """Right-hand rotation about z, (3, 3)."""
    c, s = math.cos(angle_rad), math.sin(angle_rad)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def rot_y(angle_rad: float) -> F64:
    """Right-hand rotation about y, (3, 3)."""
    c, s = math.cos(angle_rad), math.sin(angle_rad)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def cam_to_level(tilt_rad: float, roll_rad: float) -> F64:
    """Rotation taking camera (RDF) vectors to the level frame (FLU), (3, 3)."""
    return rot_y(tilt_rad) @ rot_x(roll_rad) @ M_CAM_TO_FLU


def normalized_coords(intr: Intrinsics, u: npt.ArrayLike, v: npt.ArrayLike) -> tuple[F64, F64]:
    """Ideal normalised image coordinates (x = X/Z, y = Y/Z) of the rays through pixel
    coordinates (u, v) (pixels; broadcastable arrays), each shaped like ``u + v``.

    The one place where pixel coordinates become rays: every table builder (exact scan, cliff,
    pose) and ``pixel_rays`` go through it, so the lens model applied here (the plumb-bob
    coefficients of ``intr``, undone by ``lens.undistort``) reaches every stage. Its callers build
    tables once per camera, so undistorting costs nothing per frame. Without distortion this is
    the plain pinhole arithmetic, bit for bit. The paper's stages (scan_paper.py, ``paper_*``
    below) keep the original C++'s pinhole formulas on purpose: they reproduce it exactly.
    """
    u0, v0 = np.asarray(u, dtype=np.float64), np.asarray(v, np.float64)
    if not intr.has_distortion:
        u_arr, v_arr = np.broadcast_arrays(u0, v0)
        return (u_arr - intr.cx) / intr.fx, (v_arr - intr.cy) / intr.fy
    if u0.size + v0.size > _CACHED_COORDS:  # full grids: undistort them as they come
        return _undistorted(intr, u0, v0)
    # the builders pass a row of columns and a column of rows: remembered per camera, so a
    # table rebuilt for a new mount does not undistort again
    x, y = _undistorted_cached(intr, u0.shape, u0.tobytes(), v0.shape, v0.tobytes())
    return x.copy(), y.copy()


_CACHED_COORDS = 4 * 8192  # u.size + v.size up to which normalized_coords remembers its result


def _undistorted(intr: Intrinsics, u: F64, v: F64) -> tuple[F64, F64]:
    u_arr, v_arr = np.broadcast_arrays(u, v)
    return lens.undistort((u_arr - intr.cx) / intr.fx, (v_arr - intr.cy) / intr.fy, intr)


@functools.lru_cache(maxsize=32)
def _undistorted_cached(
    intr: Intrinsics, u_shape: tuple[int, ...], u: bytes, v_shape: tuple[int, ...], v: bytes
) -> tuple[F64, F64]:
    x, y = _undistorted(intr, np.frombuffer(u).reshape(u_shape), np.frombuffer(v).reshape(v_shape))
    x.setflags(write=False)
    y.setflags(write=False)
    return x, y


@functools.lru_cache(maxsize=8)
def pixel_rays(intr: Intrinsics) -> F64:
    """Camera rays per unit depth: (x, y, 1) of ``normalized_coords`` for every pixel,
    (H, W, 3), read-only."""
    x, y = normalized_coords(
        intr,
        np.arange(intr.width, dtype=np.float64)[None, :],
        np.arange(intr.height, dtype=np.float64)[:, None],
    )
    rays = np.empty((intr.height, intr.width, 3))
    rays[..., 0] = x
    rays[..., 1] = y
    rays[..., 2] = 1.0
    rays.setflags(write=False)
    return rays


@functools.lru_cache(maxsize=8)
def level_rays(intr: Intrinsics, tilt_rad: float, roll_rad: float) -> F64:
    """Level-frame (FLU) displacement per metre of optical-axis depth for every pixel, (H, W, 3).

    A pixel with depth z (metres) sees the point ``z * level_rays[v, u]`` relative to the sensor.
    """
    out = pixel_rays(intr) @ cam_to_level(tilt_rad, roll_rad).T
    out.setflags(write=False)
    return out


def check_depth(depth: np.ndarray, intr: Intrinsics) -> None:
    """Raise FrameError unless ``depth`` is a (H, W) uint16 (mm) or float32 (m) image of
    ``intr``."""
    if not isinstance(depth, np.ndarray):
        raise FrameError(f"depth must be a numpy array, got {type(depth).__name__}")
    if depth.dtype not in (np.uint16, np.float32):
        raise FrameError(
            f"depth dtype {depth.dtype} is not accepted "
            "(accepted: uint16 millimetres or float32 metres)"
        )
    if depth.shape != (intr.height, intr.width):
        raise FrameError(
            f"depth shape {depth.shape} does not match the intrinsics "
            f"({intr.height}, {intr.width}) (rows, columns)",
            hint="give the intrinsics of this image "
            "(scale them with Intrinsics.scaled for another resolution)",
        )


def depth_to_mm(depth: np.ndarray, intr: Intrinsics) -> npt.NDArray[np.uint16]:
    """Checked depth as uint16 millimetres, (H, W); float32 metres are converted, NaN/inf/<=0 ->
    0."""
    check_depth(depth, intr)
    if depth.dtype == np.uint16:
        return depth
    with np.errstate(invalid="ignore"):
        mm = np.rint(depth * 1000.0)
        ok = np.isfinite(mm) & (mm > 0) & (mm <= UINT16_MAX)
    return np.where(ok, mm, 0).astype(np.uint16)


def paper_vertical_fov_rad(intr: Intrinsics) -> float:
    """Vertical field of view as depth_nav_tools computes it: angle(top, centre) + angle(centre,
    bottom). Pinhole on purpose, like every ``paper_*`` formula: lens distortion is ignored, as
    the original does."""
    return math.atan(intr.cy / intr.fy) + math.atan((intr.height - 1 - intr.cy) / intr.fy)


def paper_row_angles_rad(intr: Intrinsics) -> F64:
    """Eq. 3: the paper's linear row angle delta_j = theta (j - cy - 1/2) / (n - 1), (H,), radians.

    Positive below the centre row (the ray points further down than the optical axis).
    """
    j = np.arange(intr.height, dtype=np.float64)
    return paper_vertical_fov_rad(intr) * (j - intr.cy - 0.5) / (intr.height - 1)


def paper_floor_depth_m(height_m: float, tilt_rad: float, delta_rad: F64) -> F64:
    """Eqs. 5, 6, 9, 10: optical-axis depth of the floor seen at row angle delta, (H,), metres.

    h sin(pi/2 - delta) / cos(pi/2 - delta - alpha) = h cos(delta) / sin(delta + alpha), with
    alpha positive = pitched down; +inf where the row's ray does not reach the floor.
    """
    s = np.sin(delta_rad + tilt_rad)
    with np.errstate(divide="ignore"):
        return np.where(s > 0, height_m * np.cos(delta_rad) / np.where(s > 0, s, 1.0), np.inf)
