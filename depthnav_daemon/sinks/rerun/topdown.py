"""The rerun sink's top-down view (the paper's costmap figures): the scan as a line, drop-offs as
filled cells, the robot's footprint, the sensor and its field of view, range rings every metre.

A 2-D space of its own, ``/topdown``, in metres with forward up and left on the left: a level-frame
point (x forward, y left) is drawn at (u, v) = (-y, -x) (rerun's 2-D views point v down).
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING, Any

import numpy as np

from depthnav_daemon.plots.overlays import (
    DEFAULT_FOOTPRINT_M,
    cliff_cell_sizes_m,
    footprint_xy,
    fov_xy,
    memory_cells_xy,
    range_rings,
    scan_strips,
)

if TYPE_CHECKING:
    from depthnav_daemon.pipeline import Result
    from depthnav_daemon.pipeline.scan import LaserScan

__all__ = ["DEFAULT_FOOTPRINT_M", "log_fov", "log_frame", "log_static", "view"]

TOPDOWN = "/topdown"
SCAN_RGB = (0, 200, 80)
CLIFF_RGB = (230, 0, 230)
# drop-offs while the mount is not trusted (maybe the floor seen through a wrong mount): amber
UNTRUSTED_CLIFF_RGB = (255, 170, 0)
MEMORY_OBSTACLE_RGB = (150, 150, 40)  # remembered: muted, under what is seen now
MEMORY_CLIFF_RGB = (120, 40, 120)
RING_RGB = (90, 90, 90)
FOV_RGBA = (74, 144, 217, 160)
MAX_REACH_M = 8.0  # the view's default bounds stop here (zoom out for more)
RING_LABEL_RAD = 0.75  # the ring labels sit on the right, outside most fields of view


def uv(xy: np.ndarray) -> np.ndarray:
    """Level-frame (x forward, y left) points, (K, 2), as the view's (u, v) = (-y, -x)."""
    xy = np.asarray(xy, dtype=np.float32).reshape(-1, 2)
    return np.stack([-xy[:, 1], -xy[:, 0]], axis=1)


def view(reach_m: float) -> Any:
    """The top-down view, framed from just behind the robot to ``reach_m`` ahead."""
    import rerun.blueprint as rrb

    reach = min(reach_m, MAX_REACH_M)
    half = max(1.5, 0.75 * reach)  # the ring labels on the right fit
    return rrb.Spatial2DView(
        name="Top down [m]: scan, drop-offs, robot",
        origin=TOPDOWN,
        visual_bounds=rrb.VisualBounds2D(x_range=[-half, half], y_range=[-reach - 0.3, 0.8]),
    )


def log_static(rr: Any, rec: Any, reach_m: float, footprint_m: tuple[float, float]) -> None:
    """Range rings with their labels, the robot's footprint and the sensor."""
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
            uv(np.array([[d * math.cos(-a), d * math.sin(-a)] for d, _ in rings])),
            radii=0.001,
            colors=[RING_RGB],
            labels=[f"{d:g} m" for d, _ in rings],
            show_labels=True,
        ),
        static=True,
    )
    rec.log(
        f"{TOPDOWN}/robot",
        rr.LineStrips2D(
            [uv(footprint_xy(*footprint_m))],
            radii=0.012,
            colors=[[200, 200, 200]],
            labels=["robot"],
        ),
        static=True,
    )
    rec.log(
        f"{TOPDOWN}/sensor",
        rr.Points2D([[0.0, 0.0]], radii=0.04, colors=[[255, 255, 255]]),
        static=True,
    )


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
    """The drop-offs' colour: CLIFF_RGB, or UNTRUSTED_CLIFF_RGB while the mount is not trusted."""
    trust = result.mount_trust
    return CLIFF_RGB if trust is None or trust.dropoffs_trusted else UNTRUSTED_CLIFF_RGB


def log_frame(rr: Any, rec: Any, result: Result) -> None:
    """The scan (lines and points) and the cliff cells of one frame, over the memory's cells."""
    log_memory(rr, rec, result)
    strips = [uv(s) for s in scan_strips(result.scan)]
    rec.log(f"{TOPDOWN}/scan", rr.LineStrips2D(strips, radii=0.015, colors=[SCAN_RGB]))
    pts = [p for s in strips for p in s]
    rec.log(
        f"{TOPDOWN}/scan/points",
        rr.Points2D(np.reshape(pts, (-1, 2)), radii=0.025, colors=[SCAN_RGB]),
    )
    cliff = result.cliff
    if cliff is None:
        return
    sides = cliff_cell_sizes_m(result)
    # a box outline as thick as half the box is a filled square (Boxes2D has no fill mode)
    quarter = np.repeat((sides / 4)[:, None], 2, axis=1)
    rec.log(
        f"{TOPDOWN}/cliff",
        rr.Boxes2D(
            centers=uv(cliff.points_m),
            half_sizes=quarter,
            radii=sides / 4 * 1.15,  # thicker: no hole in the middle
            colors=[cliff_rgb(result)],
            draw_order=5,
        ),
    )


def log_memory(rr: Any, rec: Any, result: Result) -> None:
    """The obstacle memory's remembered cells, filled and muted under what is seen now."""
    obstacles, cliffs, cell = memory_cells_xy(result)
    for name, xy, rgb in (
        ("obstacles", obstacles, MEMORY_OBSTACLE_RGB),
        ("cliffs", cliffs, MEMORY_CLIFF_RGB),
    ):
        rec.log(
            f"{TOPDOWN}/memory/{name}",
            rr.Boxes2D(
                centers=uv(xy),
                half_sizes=np.full((len(xy), 2), cell / 4),
                radii=cell / 4 * 1.15,  # a thick outline fills the square (no fill mode)
                colors=[rgb],
                draw_order=2,
            ),
        )
