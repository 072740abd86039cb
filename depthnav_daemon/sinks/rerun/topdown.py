"""The rerun sink's top-down views (the paper's costmap figures): what a costmap receives.

- ``/topdown``, the robot's base frame (the robot stays put): the scan as a line, the cliff scan
  (the drop-offs' edges) as a thick line with each drop-off's lower floor filled, "too close"
  bearings, the obstacle memory's cells and its 360 deg scan, the robot's footprint, the sensor and
  its field of view, range rings every metre and a legend.
- ``/odom``, the odometry frame (drawn once odometry exists): the memory's cells where they are,
  the robot moving through them along its path, with its live scans.

Both are 2-D spaces in metres with x up and y to the left: a point (x forward, y left) is drawn at
(u, v) = (-y, -x) (rerun's 2-D views point v down). Colours come from ``plots.COLORS``.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING, Any

import numpy as np

from depthnav_daemon.plots import rgb
from depthnav_daemon.plots.overlays import (
    DEFAULT_FOOTPRINT_M,
    fov_xy,
    memory_cells_odom,
    memory_cells_xy,
    range_rings,
    scan_strips,
    to_odom,
    too_close_xy,
    untrusted,
)

if TYPE_CHECKING:
    from depthnav_daemon.pipeline import Result
    from depthnav_daemon.pipeline.scan import LaserScan
    from depthnav_daemon.plots.overlays import DropoffAreas

__all__ = ["DEFAULT_FOOTPRINT_M", "log_fov", "log_frame", "log_static", "view"]

TOPDOWN = "/topdown"
ODOM = "/odom"
BASE_VIEW = "Top down [m], robot frame: scan, drop-offs, memory"
ODOM_VIEW = "Top down [m], odometry frame: the robot in its memory"
SCAN_RGB = rgb("scan")
CLIFF_RGB = rgb("cliff")
# drop-offs and scan while the mount is not trusted (maybe the floor seen through a wrong mount)
UNTRUSTED_RGB = rgb("untrusted")
UNTRUSTED_CLIFF_RGB = UNTRUSTED_RGB
MEMORY_OBSTACLE_RGB = rgb("memory_obstacle")  # remembered: muted, under what is seen now
MEMORY_CLIFF_RGB = rgb("memory_cliff")
MEMORY_SCAN_RGB = rgb("memory_scan")
TOO_CLOSE_RGB = rgb("obstacle")
ROBOT_RGB = (200, 200, 200)
PATH_RGB = (230, 230, 230)
RING_RGB = (90, 90, 90)
FOV_RGBA = (74, 144, 217, 160)
AREA_ALPHA = 110  # drop-off areas: under the cliff scan line, over the memory
MAX_REACH_M = 8.0  # the view's default bounds stop here (zoom out for more)
RING_LABEL_RAD = -1.2  # ring labels on the right, past most fields of view and the legend
TOO_CLOSE_R_M = 0.25  # where a "too close" (-inf) bearing is marked
PATH_POINTS = 20_000  # the odometry path drawn (older points are dropped)
LEGEND = (
    ("laser scan", SCAN_RGB),
    ("cliff scan: drop-off edge", CLIFF_RGB),
    ("drop-off: lower floor seen", CLIFF_RGB),
    ("too close (-inf)", TOO_CLOSE_RGB),
    ("remembered obstacle", MEMORY_OBSTACLE_RGB),
    ("remembered drop-off", MEMORY_CLIFF_RGB),
    ("memory scan (360°)", MEMORY_SCAN_RGB),
    ("amber: mount not trusted", UNTRUSTED_RGB),
)


def uv(xy: np.ndarray) -> np.ndarray:
    """Level-frame (x forward, y left) points, (K, 2), as the view's (u, v) = (-y, -x)."""
    xy = np.asarray(xy, dtype=np.float32).reshape(-1, 2)
    return np.stack([-xy[:, 1], -xy[:, 0]], axis=1)


def half_width_m(reach_m: float, half_fov_rad: float) -> float:
    """Half the view's width: the field of view's out to ``reach_m``, at least 1.5 m."""
    reach = min(reach_m, MAX_REACH_M)
    return max(1.5, reach * math.sin(min(half_fov_rad, 1.4)) + 0.6)


def view(reach_m: float, half_fov_rad: float = 0.6, name: str = "") -> Any:
    """The base-frame top-down view, framed from just behind the robot to ``reach_m`` ahead and
    as wide as the field of view there."""
    import rerun.blueprint as rrb

    reach = min(reach_m, MAX_REACH_M)
    half = half_width_m(reach_m, half_fov_rad)
    return rrb.Spatial2DView(
        name=name or BASE_VIEW,
        origin=TOPDOWN,
        visual_bounds=rrb.VisualBounds2D(x_range=[-half, half], y_range=[-reach - 0.3, 1.0]),
    )


def odom_view(start: tuple[float, float, float], reach_m: float, name: str = "") -> Any:
    """The odometry-frame top-down view, framed around the robot's first pose and the way it
    faced."""
    import rerun.blueprint as rrb

    reach = min(reach_m, MAX_REACH_M)
    ahead = np.array([start[0] + 0.5 * reach * math.cos(start[2]), start[1]])
    ahead[1] += 0.5 * reach * math.sin(start[2])
    (u, v), half = uv(ahead)[0], 0.5 * reach + 1.0
    return rrb.Spatial2DView(
        name=name or ODOM_VIEW,
        origin=ODOM,
        visual_bounds=rrb.VisualBounds2D(
            x_range=[float(u) - half, float(u) + half], y_range=[float(v) - half, float(v) + half]
        ),
    )


def log_static(
    rr: Any, rec: Any, reach_m: float, outline: np.ndarray, half_fov_rad: float = 0.6
) -> None:
    """Range rings with their labels, the robot's outline ((K, 2) base frame, closed), the
    sensor and the legend."""
    rings = range_rings(min(reach_m, MAX_REACH_M))
    rec.log(
        f"{TOPDOWN}/rings",
        rr.LineStrips2D([uv(r) for _, r in rings], radii=0.006, colors=[RING_RGB], draw_order=1),
        static=True,
    )
    a = RING_LABEL_RAD
    rec.log(
        f"{TOPDOWN}/rings/labels",
        rr.Points2D(
            uv(np.array([[d * math.cos(a), d * math.sin(a)] for d, _ in rings])),
            radii=0.001,
            colors=[RING_RGB],
            labels=[f"{d:g} m" for d, _ in rings],
            show_labels=True,
            draw_order=1,
        ),
        static=True,
    )
    rec.log(
        f"{TOPDOWN}/robot",
        rr.LineStrips2D([uv(outline)], radii=0.012, colors=[ROBOT_RGB]),
        static=True,
    )
    rec.log(
        f"{TOPDOWN}/sensor",
        rr.Points2D([[0.0, 0.0]], radii=0.04, colors=[[255, 255, 255]], draw_order=30),
        static=True,
    )
    _log_legend(rr, rec, reach_m, half_fov_rad)


def log_legend(rr: Any, rec: Any, path: str, corner_uv: tuple[float, float], height_m: float):
    """A legend at ``path``: a dot of each colour with its label, in a column whose top is at
    ``corner_uv`` (the view's units), ``height_m`` tall."""
    step = height_m / len(LEGEND)
    pos = [[corner_uv[0], corner_uv[1] + (i + 0.5) * step] for i in range(len(LEGEND))]
    rec.log(
        path,
        rr.Points2D(
            pos,
            radii=0.12 * step,
            colors=[c for _, c in LEGEND],
            labels=[t for t, _ in LEGEND],
            show_labels=True,
            draw_order=40,
        ),
        static=True,
    )


def _log_legend(rr: Any, rec: Any, reach_m: float, half_fov_rad: float) -> None:
    """The base-frame view's legend: left of the field of view, beside the robot (the view is
    cut at its sides when it is narrower than its bounds)."""
    half = half_width_m(reach_m, half_fov_rad)
    height = min(3.0, 0.6 * min(reach_m, MAX_REACH_M))
    log_legend(rr, rec, f"{TOPDOWN}/legend", (-0.6 * half, 0.8 - height), height)


def log_fov(rr: Any, rec: Any, scan: LaserScan, reach_m: float) -> None:
    """The scan's horizontal field of view (static; logged again when the scan layout changes)."""
    rec.log(
        f"{TOPDOWN}/fov",
        rr.LineStrips2D(
            [uv(fov_xy(scan, min(reach_m, MAX_REACH_M)))], radii=0.008, colors=[FOV_RGBA]
        ),
        static=True,
    )


def cliff_rgb(result: Result) -> tuple[int, int, int]:
    """The drop-offs' colour: CLIFF_RGB, or amber while the mount is not trusted."""
    return UNTRUSTED_RGB if untrusted(result) else CLIFF_RGB


def scan_rgb(result: Result) -> tuple[int, int, int]:
    """The scan's colour: SCAN_RGB, or amber while the mount is not trusted."""
    return UNTRUSTED_RGB if untrusted(result) else SCAN_RGB


def area_fill(areas: DropoffAreas) -> tuple[np.ndarray, np.ndarray]:
    """Drop-off areas as line segments that fill them (2-D views have no filled polygon): one per
    image column from its edge to its far end, ((K, 2, 2) segments x forward, y left; radii
    (K,)): each as thick as the column's width at its far end (at least 1 cm), so neighbours
    overlap."""
    if not areas.areas:
        return np.zeros((0, 2, 2)), np.zeros(0)
    segments, radii = [], []
    for near, far in areas.areas:
        bearing = np.arctan2(far[:, 1], far[:, 0])
        step = float(np.median(np.abs(np.diff(bearing)))) if len(far) > 1 else 0.0
        radii.append(np.maximum(0.01, 0.75 * step * np.hypot(far[:, 0], far[:, 1])))
        segments.append(np.stack([near, far], axis=1))
    return np.concatenate(segments), np.concatenate(radii)


def _log_areas(rr: Any, rec: Any, path: str, result: Result, areas: DropoffAreas, pose=None):
    """The drop-off areas at ``path`` (in the odometry frame of ``pose`` when given)."""
    segments, radii = area_fill(areas)
    if pose is not None:
        segments = to_odom(segments.reshape(-1, 2), pose).reshape(-1, 2, 2)
    rec.log(
        path,
        rr.LineStrips2D(
            uv(segments).reshape(-1, 2, 2),  # one array: a list of K small ones cost ~30 ms
            radii=radii,
            colors=[(*cliff_rgb(result), AREA_ALPHA)],
            draw_order=5,
        ),
    )


def log_frame(rr: Any, rec: Any, result: Result, areas: DropoffAreas) -> None:
    """The base-frame view of one frame: the memory under the drop-off areas under the scans."""
    log_memory(rr, rec, result)
    color = scan_rgb(result)
    strips = [uv(s) for s in scan_strips(result.scan)]
    rec.log(f"{TOPDOWN}/scan", rr.LineStrips2D(strips, radii=0.015, colors=[color], draw_order=20))
    pts = [p for s in strips for p in s]
    rec.log(
        f"{TOPDOWN}/scan/points",
        rr.Points2D(np.reshape(pts, (-1, 2)), radii=0.025, colors=[color], draw_order=20),
    )
    rec.log(
        f"{TOPDOWN}/scan/too_close",
        rr.Points2D(
            uv(too_close_xy(result.scan, TOO_CLOSE_R_M)),
            radii=0.02,
            colors=[TOO_CLOSE_RGB],
            draw_order=21,
        ),
    )
    cliff = result.cliff
    if cliff is None:
        return
    drop = cliff_rgb(result)
    _log_areas(rr, rec, f"{TOPDOWN}/cliff/area", result, areas)
    rec.log(
        f"{TOPDOWN}/cliff/scan",
        rr.LineStrips2D(
            [uv(s) for s in scan_strips(cliff.scan)], radii=0.03, colors=[drop], draw_order=15
        ),
    )
    rec.log(
        f"{TOPDOWN}/cliff",
        rr.Points2D(uv(cliff.points_m), radii=0.008, colors=[drop], draw_order=16),
    )


def log_memory(rr: Any, rec: Any, result: Result) -> None:
    """The obstacle memory's remembered cells, filled and muted, and its 360 deg scan."""
    obstacles, cliffs, cell = memory_cells_xy(result)
    _log_cells(rr, rec, f"{TOPDOWN}/memory", uv(obstacles), uv(cliffs), cell)
    scan = result.memory.scan if result.memory is not None else None
    strips = [] if scan is None else [uv(s) for s in scan_strips(scan)]
    rec.log(
        f"{TOPDOWN}/memory/scan",
        rr.LineStrips2D(strips, radii=0.01, colors=[MEMORY_SCAN_RGB], draw_order=3),
    )


def _log_cells(
    rr: Any, rec: Any, path: str, obstacles: np.ndarray, cliffs: np.ndarray, cell: float
) -> None:
    for name, pts, color in (
        ("obstacles", obstacles, MEMORY_OBSTACLE_RGB),
        ("cliffs", cliffs, MEMORY_CLIFF_RGB),
    ):
        rec.log(
            f"{path}/{name}",
            rr.Boxes2D(
                centers=pts,
                half_sizes=np.full((len(pts), 2), cell / 4),
                radii=cell / 4 * 1.15,  # a thick outline fills the square (no fill mode)
                colors=[color],
                draw_order=2,
            ),
        )


def log_odom_frame(
    rr: Any,
    rec: Any,
    result: Result,
    areas: DropoffAreas,
    path: list[tuple[float, float]],
    outline: np.ndarray,
) -> None:
    """The odometry-frame view of one frame with a memory pose: the memory's cells where they
    are, the robot at its pose with its path, the live scan and cliff scan."""
    mem = result.memory
    if mem is None or mem.pose is None:
        return
    pose = mem.pose
    obstacles, cliffs, cell = memory_cells_odom(result)
    _log_cells(rr, rec, f"{ODOM}/memory", uv(obstacles), uv(cliffs), cell)
    if mem.scan is not None:
        rec.log(
            f"{ODOM}/memory/scan",
            rr.LineStrips2D(
                [uv(to_odom(s, pose)) for s in scan_strips(mem.scan)],
                radii=0.01,
                colors=[MEMORY_SCAN_RGB],
                draw_order=3,
            ),
        )
    rec.log(
        f"{ODOM}/path",
        rr.LineStrips2D([uv(np.asarray(path))], radii=0.01, colors=[PATH_RGB], draw_order=4),
    )
    rec.log(
        f"{ODOM}/robot",
        rr.LineStrips2D(
            [uv(to_odom(outline, pose))],
            radii=0.012,
            colors=[ROBOT_RGB],
            draw_order=25,
        ),
    )
    rec.log(
        f"{ODOM}/scan",
        rr.LineStrips2D(
            [uv(to_odom(s, pose)) for s in scan_strips(result.scan)],
            radii=0.015,
            colors=[scan_rgb(result)],
            draw_order=20,
        ),
    )
    if result.cliff is not None:
        _log_areas(rr, rec, f"{ODOM}/cliff/area", result, areas, pose)
        rec.log(
            f"{ODOM}/cliff/scan",
            rr.LineStrips2D(
                [uv(to_odom(s, pose)) for s in scan_strips(result.cliff.scan)],
                radii=0.03,
                colors=[cliff_rgb(result)],
                draw_order=15,
            ),
        )
