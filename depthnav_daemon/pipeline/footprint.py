"""The robot's own body: readings inside its footprint prism become "no reading" before the stages.

The body is a prism in the robot's base frame (REP 103: x forward, y left, z up, origin on the
floor under the robot): a convex polygon on the floor (the footprint), extruded from the floor up
to the robot's height. A sensor on the robot sees parts of it (a bumper, a mast, a wheel) at a few
centimetres: the scan would report them as obstacles (-inf, "too close", on every frame) and the
memory would remember them around the robot.

Per camera and mount, :func:`body_table` finds once, for each pixel, the depth interval (mm along
the optical axis) over which its ray lies inside the prism; only the pixels whose interval is not
empty are kept (those that see the body's parts or the floor under its outline: 50k of 640x480 on
the issue's steep camera, none when the body is out of view). Per
frame, :func:`remove_body` sets the readings that fall inside their pixel's interval to 0 ("no
reading"), which every stage already treats as unknown: a bin whose only readings were the body
reads NaN (unknown), never +inf (clear).
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from depthnav_daemon.errors import ConfigError, FrameError
from depthnav_daemon.pipeline._jit import kernel
from depthnav_daemon.pipeline.geometry import (
    MAX_MOUNT_HEIGHT_M,
    MAX_PLACEMENT_M,
    Mount,
    cam_to_level,
    frozen_table,
    normalized_coords,
    rot_z,
)
from drivers.base import Intrinsics

I32 = npt.NDArray[np.int32]
U16 = npt.NDArray[np.uint16]

MIN_VERTICES, MAX_VERTICES = 3, 64
MIN_AREA_M2 = 1e-4  # 1 cm x 1 cm: a smaller polygon is a typo, not a robot
MIN_HEIGHT_M = 0.01
TURN_TOLERANCE_RAD = 1e-6  # a convex outline turns once round: 2 pi
SHOWN_CHARS = 80  # of a bad value quoted in a message


@dataclass(frozen=True, slots=True)
class Footprint:
    """The robot's body: a convex polygon on the floor in the base frame, up to a height.

    Attributes:
        polygon_m: vertices (x, y) in the base frame, metres, in order around the polygon
            (either direction; kept counter-clockwise), at least 3, convex, |x|, |y| <= 10.
        height_m: the body's top above the floor, metres (0 < h <= 10).

    Raises:
        ConfigError: too few or too many vertices, a vertex out of range, a polygon that is not
            convex (or crosses itself, or has no area), a height out of range.
    """

    polygon_m: tuple[tuple[float, float], ...]
    height_m: float

    def __post_init__(self) -> None:
        object.__setattr__(self, "polygon_m", checked_polygon(self.polygon_m))
        h = self.height_m
        if isinstance(h, bool) or not isinstance(h, (int, float)):
            raise ConfigError(f"robot.height_m={h!r} is not a number")
        if not (math.isfinite(h) and MIN_HEIGHT_M <= h <= MAX_MOUNT_HEIGHT_M):
            raise ConfigError(
                f"robot.height_m={h!r} is out of range "
                f"(accepted: {MIN_HEIGHT_M:g}..{MAX_MOUNT_HEIGHT_M:g} m)",
                hint="the height of the robot's top above the floor",
            )
        object.__setattr__(self, "height_m", float(h))

    def half_planes(self) -> tuple[tuple[float, float, float], ...]:
        """The polygon as half-planes (nx, ny, c): a point p is inside where nx px + ny py <= c
        for every edge (outward normals of the counter-clockwise polygon)."""
        pts = self.polygon_m
        out = []
        for (x0, y0), (x1, y1) in zip(pts, pts[1:] + pts[:1], strict=True):
            nx, ny = y1 - y0, x0 - x1  # the edge turned clockwise: outward for a CCW polygon
            out.append((nx, ny, nx * x0 + ny * y0))
        return tuple(out)


def checked_polygon(value: object) -> tuple[tuple[float, float], ...]:
    """``value`` (a sequence of [x, y] pairs, metres) as a counter-clockwise tuple of float pairs.

    Raises:
        ConfigError: not a list of pairs of numbers, fewer than 3 or more than MAX_VERTICES
            vertices, a vertex out of range, not convex, crossing itself, no area.
    """
    hint = "e.g. robot.footprint_m = [[0.3, 0.25], [-0.3, 0.25], [-0.3, -0.25], [0.3, -0.25]]"
    if not isinstance(value, (list, tuple)) or not all(_is_pair(p) for p in value):
        raise ConfigError(
            f"robot.footprint_m={_short(value)} is not a list of [x, y] pairs", hint=hint
        )
    if not MIN_VERTICES <= len(value) <= MAX_VERTICES:
        raise ConfigError(
            f"robot.footprint_m has {len(value)} vertices "
            f"(accepted: {MIN_VERTICES}..{MAX_VERTICES})",
            hint=hint,
        )
    pts: list[tuple[float, float]] = []
    for p in value:
        for v in p:
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
                raise ConfigError(
                    f"robot.footprint_m vertex {_short(p)} is not a pair of numbers", hint=hint
                )
            if abs(v) > MAX_PLACEMENT_M:
                raise ConfigError(
                    f"robot.footprint_m vertex {_short(p)} is out of range (accepted: "
                    f"-{MAX_PLACEMENT_M:g}..{MAX_PLACEMENT_M:g} m)",
                    hint="metres in the base frame, origin on the floor under the robot",
                )
        pts.append((float(p[0]), float(p[1])))
    n = len(pts)
    area2 = sum(pts[i][0] * pts[i - n + 1][1] - pts[i - n + 1][0] * pts[i][1] for i in range(n))
    if area2 < 0:  # clockwise: turn it round
        pts.reverse()
    turning = 0.0
    for i in range(n):
        ax, ay = pts[i - 1][0] - pts[i - 2][0], pts[i - 1][1] - pts[i - 2][1]
        bx, by = pts[i][0] - pts[i - 1][0], pts[i][1] - pts[i - 1][1]
        cross, dot = ax * by - ay * bx, ax * bx + ay * by
        if (ax == 0 and ay == 0) or cross < -1e-12 * (abs(dot) + 1e-12):
            turning = math.nan  # a repeated vertex, or a right turn in a CCW polygon
            break
        turning += math.atan2(cross, dot)
    if (
        not abs(turning - 2 * math.pi) < TURN_TOLERANCE_RAD
    ):  # once round: no star that crosses itself
        raise ConfigError(
            f"robot.footprint_m={_short(value)} is not a convex polygon",
            hint="give its convex outline (every vertex once, in order round the robot)",
        )
    if abs(area2) / 2 < MIN_AREA_M2:
        raise ConfigError(
            f"robot.footprint_m has no area ({abs(area2) / 2:.2g} m^2)",
            hint="the vertices (metres) go round the robot's outline",
        )
    return tuple(pts)


def _is_pair(p: object) -> bool:
    return isinstance(p, (list, tuple)) and len(p) == len("xy")


def _short(value: object) -> str:
    text = repr(value)
    return text if len(text) <= SHOWN_CHARS else text[: SHOWN_CHARS - 3] + "..."


@dataclass(frozen=True, slots=True)
class BodyTable:
    """The pixels whose ray crosses the body, and where (one camera and mount).

    Attributes:
        shape: (H, W) of the camera's images.
        rows, cols: (N,) int32 pixel coordinates.
        lo_mm, hi_mm: (N,) uint16, the closed interval of readings (mm of optical-axis depth)
            that lie inside the body for that pixel, widened to whole millimetres outward.
    """

    shape: tuple[int, int]
    rows: I32
    cols: I32
    lo_mm: U16
    hi_mm: U16

    @property
    def size(self) -> int:
        return int(self.rows.size)


@kernel
def _body_interval_kernel(x, y, rot, origin, planes, height_m, lo_mm, hi_mm):  # pragma: no cover
    """Per pixel, the optical depths (mm) where its ray is inside the prism: Cyrus-Beck clipping
    of the ray origin + z * (rot @ (x, y, 1)) against the slab 0 <= height <= height_m and the
    polygon's half-planes. Writes lo_mm > hi_mm where the ray misses it; returns how many pixels
    it does not miss.

    x, y: (H, W) float64 normalised coordinates; rot: (3, 3) camera -> base; origin: (3,) the
    optical centre in the base frame (m); planes: (K, 3) rows (nx, ny, c); lo_mm, hi_mm: (H, W)
    int32 outputs.
    """
    h, w = x.shape
    ox, oy, oz = origin[0], origin[1], origin[2]
    n = 0
    for r in range(h):
        for c in range(w):
            xn, yn = x[r, c], y[r, c]
            dx = rot[0, 0] * xn + rot[0, 1] * yn + rot[0, 2]
            dy = rot[1, 0] * xn + rot[1, 1] * yn + rot[1, 2]
            dz = rot[2, 0] * xn + rot[2, 1] * yn + rot[2, 2]
            t0, t1 = 0.0, math.inf
            if dz != 0.0:
                ta, tb = -oz / dz, (height_m - oz) / dz
                t0 = max(t0, min(ta, tb))
                t1 = min(t1, max(ta, tb))
            elif not 0.0 <= oz <= height_m:
                t1 = -1.0
            for k in range(planes.shape[0]):
                if t0 >= t1:  # missed already: most rays, after an edge or two
                    break
                den = planes[k, 0] * dx + planes[k, 1] * dy
                num = planes[k, 2] - planes[k, 0] * ox - planes[k, 1] * oy
                if den > 0.0:
                    t1 = min(t1, num / den)
                elif den < 0.0:
                    t0 = max(t0, num / den)
                elif num < 0.0:
                    t1 = -1.0
            lo, hi = 1, 0
            if t0 < t1:
                lo = max(1, math.floor(t0 * 1000.0))
                hi = int(min(65535.0, math.ceil(t1 * 1000.0)))
                if lo <= hi:
                    n += 1
            lo_mm[r, c], hi_mm[r, c] = lo, hi
    return n


@kernel
def _compact_kernel(lo_mm, hi_mm, rows, cols, lo16, hi16):  # pragma: no cover
    """The pixels of (H, W) lo_mm, hi_mm whose interval is not empty, in row-major order, into
    the (N,) outputs (N: their number)."""
    h, w = lo_mm.shape
    i = 0
    for r in range(h):
        for c in range(w):
            if lo_mm[r, c] <= hi_mm[r, c]:
                rows[i], cols[i] = r, c
                lo16[i], hi16[i] = lo_mm[r, c], hi_mm[r, c]
                i += 1


@functools.lru_cache(maxsize=4)
def _ray_grid(intr: Intrinsics) -> tuple[npt.NDArray[np.float64], npt.NDArray[np.float64]]:
    """The normalised coordinates of every pixel, (H, W) float64 each, read-only (per camera:
    10 ms at 1280x720, which a new mount would otherwise pay again)."""
    u = np.arange(intr.width, dtype=np.float64)[None, :]
    v = np.arange(intr.height, dtype=np.float64)[:, None]
    xn, yn = normalized_coords(intr, u, v)
    x = np.ascontiguousarray(np.broadcast_to(xn, (intr.height, intr.width)), dtype=np.float64)
    y = np.ascontiguousarray(np.broadcast_to(yn, (intr.height, intr.width)), dtype=np.float64)
    x.setflags(write=False)
    y.setflags(write=False)
    return x, y


@functools.lru_cache(maxsize=16)
def body_table(intr: Intrinsics, mount: Mount, footprint: Footprint) -> BodyTable:
    """The pixels of camera ``intr`` at ``mount`` (with its placement on the robot) that can read
    the body, and the readings that do (cached per camera, mount and footprint).

    Rays come from ``geometry.normalized_coords``, so a lens model is applied. Two compiled
    passes that release the interpreter (the table worker builds it beside the frame loop).
    """
    x, y = _ray_grid(intr)
    rot = np.ascontiguousarray(rot_z(mount.yaw_rad) @ cam_to_level(mount.tilt_rad, mount.roll_rad))
    origin = np.array([mount.x_m, mount.y_m, mount.height_m])
    planes = np.array(footprint.half_planes(), dtype=np.float64).reshape(-1, 3)
    lo = np.empty((intr.height, intr.width), dtype=np.int32)
    hi = np.empty_like(lo)
    n = int(_body_interval_kernel(x, y, rot, origin, planes, footprint.height_m, lo, hi))
    rows, cols = np.empty(n, dtype=np.int32), np.empty(n, dtype=np.int32)
    lo16, hi16 = np.empty(n, dtype=np.uint16), np.empty(n, dtype=np.uint16)
    _compact_kernel(lo, hi, rows, cols, lo16, hi16)
    return frozen_table(BodyTable((intr.height, intr.width), rows, cols, lo16, hi16))


@kernel
def _remove_body_kernel(depth, rows, cols, lo_mm, hi_mm, out):  # pragma: no cover
    """Zero in ``out`` (a writable copy of ``depth``, both (H, W) uint16) the table's pixels whose
    reading lies in their interval; returns how many."""
    n = 0
    for i in range(rows.size):
        r, c = rows[i], cols[i]
        d = depth[r, c]
        if lo_mm[i] <= d <= hi_mm[i]:
            out[r, c] = 0
            n += 1
    return n


def remove_body(depth_mm: U16, table: BodyTable) -> tuple[U16, int]:
    """``depth_mm`` with the readings of the body set to 0 ("no reading").

    Args:
        depth_mm: (H, W) uint16 depth, mm along the optical axis, 0 = no reading; not written.
        table: :func:`body_table` for this camera and mount.

    Returns:
        The depth (a new array when a reading was removed, else ``depth_mm`` itself) and the
        number of readings removed.

    Raises:
        FrameError: ``depth_mm`` is not a uint16 image of the table's camera.
    """
    if depth_mm.shape != table.shape or depth_mm.dtype != np.uint16:
        raise FrameError(
            f"depth image {depth_mm.dtype} {depth_mm.shape} does not fit the robot body's table "
            f"(uint16 {table.shape})"
        )
    if table.size == 0:
        return depth_mm, 0
    out = np.array(depth_mm, order="C")  # (H, W), writable: ~0.05 ms at 640x480
    n = int(_remove_body_kernel(depth_mm, table.rows, table.cols, table.lo_mm, table.hi_mm, out))
    return (out, n) if n else (depth_mm, 0)
