"""The rerun sink's depth image and what is drawn on it: a grey depth palette under strong colours
(red obstacle pixels and filled magenta drop-off blocks in one segmentation image, the pixel each
scan reading came from in green) and the scan's row band when it is not the whole image."""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

import numpy as np

from depthnav_daemon.plots.overlays import scan_source_pixels
from depthnav_daemon.sinks.rerun.topdown import CLIFF_RGB, SCAN_RGB

if TYPE_CHECKING:
    from depthnav_daemon.pipeline import Result
    from depthnav_daemon.sinks.rerun.layout import LayoutState
    from drivers.base import Frame

DEPTH = "/world/sensor/depth"
CLASS_OBSTACLE = 1
BAND_RGB = (255, 212, 0)
CLASS_CLIFF = 2
CLIFF_RGBA = (*CLIFF_RGB, 230)
BLOCK_EDGE_RGB = (110, 0, 110)  # darker than the fill: the blocks stay countable
BLOCK_EDGE_PX = 0.5


def log_depth(rr: Any, rec: Any, frame: Frame, result: Result, state: LayoutState) -> None:
    """The depth image (grey, near = dark) and its overlays."""
    intr = frame.intrinsics
    far_mm = max(1000.0, state.reach_m * 1000.0)
    rec.log(
        DEPTH,
        rr.DepthImage(
            frame.depth_mm, meter=1000.0, colormap="grayscale", depth_range=[0.0, far_mm]
        ),
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
    classes = _classes(result, intr.height, intr.width)
    if classes is not None:
        rec.log(f"{DEPTH}/obstacles", rr.SegmentationImage(classes, opacity=0.75))
    src = scan_source_pixels(np.asarray(frame.depth_mm), result)
    rec.log(
        f"{DEPTH}/scan_pixels",
        rr.Points2D(src[:, ::-1].astype(np.float32), radii=1.5, colors=[SCAN_RGB]),
    )
    _log_cliff_blocks(rr, rec, result, state)


def _classes(result: Result, height: int, width: int) -> np.ndarray | None:
    """(H, W) uint8: CLASS_CLIFF inside drop-off blocks, CLASS_OBSTACLE on obstacle pixels (they
    win where both are), 0 elsewhere; None when there is neither a mask nor a cliff stage."""
    cliff, mask = result.cliff, result.obstacle_mask
    if cliff is None and mask is None:
        return None
    out = np.zeros((height, width), dtype=np.uint8)
    if cliff is not None:
        bs = cliff.block_size
        for r, c in np.asarray(cliff.blocks).reshape(-1, 2):
            out[r : r + bs, c : c + bs] = CLASS_CLIFF
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
