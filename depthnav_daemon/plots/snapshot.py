"""One frame as the paper's figs. 9 and 13 show it: the depth image with the scan band, obstacle
pixels and cliff blocks drawn on it, beside a top-down view of the scan and the cliff points with
the robot and the sensor to scale."""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from depthnav_daemon.plots import COLORS, new_figure
from depthnav_daemon.plots.overlays import (
    DEFAULT_FOOTPRINT_M,
    cliff_cell_sizes_m,
    footprint_xy,
    fov_xy,
    range_rings,
    scan_source_pixels,
    scan_strips,
)

if TYPE_CHECKING:
    from matplotlib.axes import Axes
    from matplotlib.figure import Figure

    from depthnav_daemon.pipeline import Result
    from drivers.base import Frame


def _rgba(hex_color: str, alpha: float) -> np.ndarray:
    from matplotlib.colors import to_rgba

    r, g, b, _ = to_rgba(hex_color)
    return np.array([r, g, b, alpha])


def draw_snapshot(
    frame: Frame,
    result: Result,
    range_max_m: float,
    title: str = "",
    footprint_m: tuple[float, float] = DEFAULT_FOOTPRINT_M,
) -> Figure:
    """The frame's depth image with overlays (left) and the top-down view (right)."""
    fig = new_figure(8.0, 4.3)
    left, right = fig.subplots(1, 2, width_ratios=[1.25, 1.0])
    _draw_depth(left, frame, result, range_max_m)
    _draw_top_down(right, result, range_max_m, footprint_m)
    m = result.mount
    fig.suptitle(
        (f"{title}: " if title else "")
        + f"frame {result.seq}, sensor {m.height_m:.2f} m high, tilt {m.tilt_deg:.1f}° down, "
        f"roll {m.roll_deg:.1f}° ({result.mount_source})",
        fontsize=10,
    )
    _legend(fig, result)
    return fig


def _draw_depth(ax: Axes, frame: Frame, result: Result, range_max_m: float) -> None:
    """Muted grey depth (near = light), no reading = white, strong colours on top."""
    depth = np.asarray(frame.depth_mm, dtype=np.float64)
    h, w = depth.shape
    shown = np.ma.masked_equal(depth, 0.0)
    ax.imshow(
        shown,
        cmap="gray_r",
        vmin=-0.25 * range_max_m * 1000,
        vmax=range_max_m * 1000,
        interpolation="nearest",
    )
    over = np.zeros((h, w, 4))
    first, stop = result.scan_band
    if (first, stop) != (0, h):  # a band that is the whole image says nothing: not drawn
        over[first:stop] = _rgba(COLORS["band"], 0.25)
    if result.obstacle_mask is not None:
        over[result.obstacle_mask] = _rgba(COLORS["obstacle"], 0.75)
    if result.cliff is not None:
        bs = result.cliff.block_size
        for r, c in np.asarray(result.cliff.blocks).reshape(-1, 2):
            over[r : r + bs, c : c + bs] = _rgba(COLORS["cliff"], 0.7)
    ax.imshow(over, interpolation="nearest")
    src = scan_source_pixels(np.asarray(frame.depth_mm), result)
    if len(src):
        ax.plot(src[:, 1], src[:, 0], ".", color=COLORS["scan"], ms=2.5, label="_src")
    ax.set_xlabel("image column [px]")
    ax.set_ylabel("image row [px]")
    ax.set_title("depth image (near = light)", fontsize=9)


def _draw_top_down(
    ax: Axes, result: Result, range_max_m: float, footprint_m: tuple[float, float]
) -> None:
    """Forward is up and left is left: plotted as (-y, x)."""
    from matplotlib.patches import Polygon, Rectangle

    scan = result.scan
    reach = min(range_max_m, 6.0)
    fov = fov_xy(scan, reach)
    ax.add_patch(Polygon(np.c_[-fov[:, 1], fov[:, 0]], color=COLORS["fov"], alpha=0.1, lw=0))
    half = reach * float(np.sin(min(max(abs(scan.angle_min), abs(scan.angle_max)), 1.4))) + 0.3
    half = max(half, footprint_m[1])
    for d, ring in range_rings(reach):
        ax.plot(-ring[:, 1], ring[:, 0], color="#cccccc", lw=0.6)
        # labelled on the right, outside the field of view where it fits inside the axes
        a = min(0.75, float(np.arcsin(min(1.0, (half - 0.35) / d))))
        ax.annotate(
            f"{d:g} m",
            (d * np.sin(a), d * np.cos(a)),
            fontsize=7,
            color="#999999",
            ha="left",
            va="bottom",
        )
    foot = footprint_xy(*footprint_m)
    ax.fill(-foot[:, 1], foot[:, 0], facecolor="#dddddd", edgecolor=COLORS["robot"], lw=1.2)
    ax.plot([0.0], [0.0], "^", color="black", ms=7)
    if result.cliff is not None and len(result.cliff.points_m):
        pts = np.asarray(result.cliff.points_m, dtype=np.float64)
        for (x, y), side in zip(pts, cliff_cell_sizes_m(result), strict=True):
            ax.add_patch(
                Rectangle(
                    (-y - side / 2, x - side / 2),
                    side,
                    side,
                    facecolor=COLORS["cliff"],
                    edgecolor="none",
                    alpha=0.8,
                )
            )
    for strip in scan_strips(scan):
        ax.plot(-strip[:, 1], strip[:, 0], "-o", color=COLORS["scan"], lw=1.8, ms=1.5)
    ax.set_xlim(-half, half)
    ax.set_ylim(-footprint_m[0] - 0.2, reach + 0.2)
    ax.set_aspect("equal")
    ax.set_xlabel("to the left [m]")
    ax.set_ylabel("forward [m]")
    ax.set_title("top down (level frame)", fontsize=9)
    ax.xaxis.set_major_formatter(lambda v, _pos: f"{0.0 - v:g}")
    ax.grid(False)


def _legend(fig: Figure, result: Result) -> None:
    from matplotlib.lines import Line2D
    from matplotlib.patches import Patch

    handles = [
        Line2D([], [], color=COLORS["scan"], marker="o", ms=3, label="laser scan (its pixels)"),
        Patch(color=COLORS["cliff"], label="drop-off (cliff) blocks"),
        Patch(facecolor="#dddddd", edgecolor=COLORS["robot"], label="robot, sensor ▲"),
        Patch(color=COLORS["fov"], alpha=0.3, label="field of view"),
    ]
    if result.obstacle_mask is not None:
        handles.insert(1, Patch(color=COLORS["obstacle"], label="obstacle pixels"))
    first, stop = result.scan_band
    if (first, stop) != (0, result.intrinsics.height):
        handles.insert(1, Patch(color=COLORS["band"], alpha=0.5, label="rows the scan reads"))
    fig.legend(handles=handles, loc="outside lower center", ncols=3, fontsize=8, frameon=False)
