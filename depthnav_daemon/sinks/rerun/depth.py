"""The rerun sink's depth image and what is drawn on it: the depth palette of every figure (near
= light, far = dark, ``plots.DEPTH_CMAP`` reversed; no reading blue-grey) under strong colours
(red obstacle pixels, the drop-offs' lower floor in magenta, amber while the mount is not
trusted, in one segmentation image; the pixel each scan reading came from in green or amber),
the detector's blocks outlined, and the scan's row band when it is not the whole image."""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

import numpy as np

from depthnav_daemon.plots import DEPTH_CMAP, rgb
from depthnav_daemon.plots.overlays import obstacle_pixels_of, untrusted
from depthnav_daemon.sinks.rerun.topdown import scan_rgb

if TYPE_CHECKING:
    from depthnav_daemon.pipeline import Result
    from depthnav_daemon.plots.overlays import DropoffAreas
    from depthnav_daemon.sinks.rerun.layout import LayoutState
    from drivers.base import Frame

DEPTH = "/world/sensor/depth"
CLASS_OBSTACLE = 1
CLASS_CLIFF = 2
CLASS_CLIFF_UNTRUSTED = 3
CLASS_NO_READING = 4
OBSTACLE_RGBA = (*rgb("obstacle"), 200)
CLIFF_RGBA = (*rgb("cliff"), 200)
UNTRUSTED_RGBA = (*rgb("untrusted"), 220)
NO_READING_RGBA = (*rgb("no_reading"), 255)  # opaque: never a depth colour
CLASSES = (
    (0, "", (0, 0, 0, 0)),  # class 0 must be transparent explicitly, or rerun tints the image
    (CLASS_OBSTACLE, "obstacle (scan)", OBSTACLE_RGBA),
    (CLASS_CLIFF, "drop-off: lower floor", CLIFF_RGBA),
    (CLASS_CLIFF_UNTRUSTED, "drop-off, mount not trusted", UNTRUSTED_RGBA),
    (CLASS_NO_READING, "no reading", NO_READING_RGBA),
)
BAND_RGB = (255, 212, 0)
BLOCK_EDGE_RGB = (110, 0, 110)  # the detector's blocks, thin outlines
BLOCK_EDGE_PX = 0.5


def log_depth(
    rr: Any, rec: Any, frame: Frame, result: Result, state: LayoutState, areas: DropoffAreas
) -> None:
    """The depth image (near = light, far = dark) and its overlays."""
    intr = frame.intrinsics
    far_mm = max(1000.0, state.reach_m * 1000.0)
    rec.log(
        DEPTH,
        # a reversed range reverses the colour map: near light, range_max and beyond dark
        rr.DepthImage(frame.depth_mm, meter=1000.0, colormap=DEPTH_CMAP, depth_range=[far_mm, 0.0]),
    )
    first, stop = result.scan_band
    whole = (first, stop) == (0, intr.height)  # every row: a box around the image says nothing
    rec.log(
        f"{DEPTH}/band",
        rr.Boxes2D(
            mins=np.empty((0, 2)) if whole else [[-0.5, first - 0.5]],
            sizes=np.empty((0, 2)) if whole else [[intr.width, stop - first]],
            colors=[BAND_RGB],
            labels=[] if whole else ["scan rows"],
        ),
    )
    params = state.context.scan_params if state.context is not None else None
    mask, src = obstacle_pixels_of(frame.depth_mm, result, params)
    classes = _classes(frame, result, areas, mask)
    rec.log(f"{DEPTH}/obstacles", rr.SegmentationImage(classes, opacity=1.0))
    rec.log(
        f"{DEPTH}/scan_pixels",
        rr.Points2D(src[:, ::-1].astype(np.float32), radii=1.5, colors=[scan_rgb(result)]),
    )
    _log_cliff_blocks(rr, rec, result, state)


def _classes(
    frame: Frame, result: Result, areas: DropoffAreas, mask: np.ndarray | None
) -> np.ndarray:
    """(H, W) uint8: CLASS_NO_READING where the depth is 0, CLASS_CLIFF (or _UNTRUSTED) on the
    drop-offs' lower floor, CLASS_OBSTACLE on obstacle pixels (they win), 0 elsewhere."""
    out = np.where(np.asarray(frame.depth_mm) == 0, CLASS_NO_READING, 0).astype(np.uint8)
    out[areas.pixels] = CLASS_CLIFF_UNTRUSTED if untrusted(result) else CLASS_CLIFF
    if mask is not None:
        out[mask] = CLASS_OBSTACLE
    return out


def _log_cliff_blocks(rr: Any, rec: Any, result: Result, state: LayoutState) -> None:
    """Thin outlines around the (filled, in the segmentation image) drop-off blocks."""
    cliff = result.cliff
    blocks = np.empty((0, 2)) if cliff is None else np.asarray(cliff.blocks).reshape(-1, 2)
    # the cliff stage reports its own block size; the context's is the configured fallback
    size = float(getattr(cliff, "block_size", None) or state.block_size)
    # blocks are (row, col) of the top-left pixel; Boxes2D wants (x, y) = (col, row) pixel edges
    centers = blocks[:, ::-1].astype(np.float32) - 0.5 + size / 2
    rec.log(
        f"{DEPTH}/cliffs",
        rr.Boxes2D(
            centers=centers,
            half_sizes=np.full((len(blocks), 2), size / 2, np.float32),
            radii=BLOCK_EDGE_PX,
            colors=[BLOCK_EDGE_RGB],
        ),
    )
