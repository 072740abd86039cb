"""One frame as the paper's figs. 9 and 13 show it: the depth image with the scan band, obstacle
pixels and the drop-offs' lower floor drawn on it, beside a top-down view of what a costmap
receives: the scan, the cliff scan (the drop-offs' edges) with each drop-off's floor area filled,
the obstacle memory's cells and 360 deg scan, the robot and the sensor to scale.

Untrusted results (the mount contradicted by the floor, or not confirmed) are amber everywhere,
and the title says so."""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from depthnav_daemon.plots import COLORS, DEPTH_CMAP, new_figure
from depthnav_daemon.plots.overlays import (
    DEFAULT_FOOTPRINT_M,
    area_polygon,
    dropoff_areas,
    footprint_xy,
    fov_xy,
    memory_cells_xy,
    obstacle_pixels_of,
    range_rings,
    scan_strips,
    too_close_xy,
    trust_line,
    untrusted,
)

if TYPE_CHECKING:
    from matplotlib.axes import Axes
    from matplotlib.figure import Figure

    from depthnav_daemon.pipeline import Result
    from depthnav_daemon.pipeline.params import ScanParams
    from drivers.base import Frame

MAX_REACH_M = 6.0  # the top-down view stops here
TOO_CLOSE_R_M = 0.25  # where a "too close" (-inf) bearing is marked, ahead of the sensor


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
    scan_params: ScanParams | None = None,
    body_m: tuple[tuple[float, float], ...] = (),
) -> Figure:
    """The frame's depth image with overlays (left) and the top-down view (right).

    ``scan_params`` (the scan's, as configured) lets the paper method's obstacle and source
    pixels be drawn (its Result carries no obstacle mask). ``body_m``: the ``[robot]``
    footprint's outline (base frame, metres), drawn instead of the ``footprint_m`` box."""
    fig = new_figure(8.0, 4.6)
    left, right = fig.subplots(1, 2, width_ratios=[1.25, 1.0])
    areas = dropoff_areas(frame.depth_mm, result, min(range_max_m, MAX_REACH_M))
    mask, src = obstacle_pixels_of(frame.depth_mm, result, scan_params)
    _draw_depth(left, frame, result, range_max_m, areas.pixels, mask, src)
    _draw_top_down(right, result, range_max_m, footprint_m, areas.areas, body_m)
    m = result.mount
    head = (f"{title}: " if title else "") + (
        f"frame {result.seq}, sensor {m.height_m:.2f} m high, {_tilt_words(m.tilt_deg)}, "
        f"roll {round(m.roll_deg, 1) + 0.0:.1f}°"  # + 0.0: no "-0.0"
    )
    fig.suptitle(
        f"{head}\n{trust_line(result)}",
        fontsize=9,
        color=COLORS["untrusted"] if untrusted(result) else "black",
    )
    _legend(fig, result, mask is not None, body_m)
    return fig


def _tilt_words(tilt_deg: float) -> str:
    """ "tilt 15.0° down" / "tilt 5.0° up" (positive tilt is pitched down)."""
    return f"tilt {abs(tilt_deg):.1f}° {'up' if tilt_deg < 0 else 'down'}"


def _draw_depth(
    ax: Axes,
    frame: Frame,
    result: Result,
    range_max_m: float,
    dropoff_pixels: np.ndarray,
    mask: np.ndarray | None,
    src: np.ndarray,
) -> None:
    """The depth palette (near = light, far = dark, no reading blue-grey) with a colour bar in
    metres, strong colours on top."""
    import matplotlib as mpl

    depth = np.asarray(frame.depth_mm, dtype=np.float64) / 1000.0
    h, w = depth.shape
    cmap = mpl.colormaps[DEPTH_CMAP].reversed().with_extremes(bad=COLORS["no_reading"])
    image = ax.imshow(
        np.ma.masked_equal(depth, 0.0),
        cmap=cmap,
        vmin=0.0,
        vmax=range_max_m,
        interpolation="nearest",
    )
    bar = ax.figure.colorbar(image, ax=ax, fraction=0.05, pad=0.02, extend="max")
    bar.set_label("depth [m] (blue-grey: no reading)", fontsize=7)
    bar.ax.tick_params(labelsize=7)
    over = np.zeros((h, w, 4))
    first, stop = result.scan_band
    if (first, stop) != (0, h):  # a band that is the whole image says nothing: not drawn
        over[first:stop] = _rgba(COLORS["band"], 0.25)
    if mask is not None:
        over[mask] = _rgba(COLORS["obstacle"], 0.75)
    amber = untrusted(result)
    over[dropoff_pixels] = _rgba(COLORS["untrusted" if amber else "cliff"], 0.7)
    ax.imshow(over, interpolation="nearest")
    if len(src):
        color = COLORS["untrusted" if amber else "scan"]
        ax.plot(src[:, 1], src[:, 0], ".", color=color, ms=2.5, label="_src")
    ax.set_xlabel("image column [px]", fontsize=8)
    ax.set_ylabel("image row [px]", fontsize=8)
    ax.tick_params(labelsize=7)
    ax.set_title("depth image", fontsize=9)


def _draw_top_down(
    ax: Axes,
    result: Result,
    range_max_m: float,
    footprint_m: tuple[float, float],
    areas: list[tuple[np.ndarray, np.ndarray]],
    body_m: tuple[tuple[float, float], ...] = (),
) -> None:
    """Forward is up and left is left: plotted as (-y, x)."""
    from matplotlib.patches import Polygon, Rectangle

    scan = result.scan
    reach = min(range_max_m, MAX_REACH_M)
    fov = fov_xy(scan, reach)
    ax.add_patch(Polygon(np.c_[-fov[:, 1], fov[:, 0]], color=COLORS["fov"], alpha=0.1, lw=0))
    half = reach * float(np.sin(min(max(abs(scan.angle_min), abs(scan.angle_max)), 1.4))) + 0.3
    half = max(half, footprint_m[1])
    for d, ring in range_rings(reach):
        ax.plot(-ring[:, 1], ring[:, 0], color="#cccccc", lw=0.6, zorder=1)
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
    obstacles, cliffs, cell = memory_cells_xy(result)
    for xy, name in ((obstacles, "memory_obstacle"), (cliffs, "memory_cliff")):
        for x, y in xy:
            ax.add_patch(
                Rectangle(
                    (-y - cell / 2, x - cell / 2),
                    cell,
                    cell,
                    facecolor=COLORS[name],
                    edgecolor="none",
                    alpha=0.55,
                    zorder=2,
                )
            )
    if result.memory is not None and result.memory.scan is not None:
        for strip in scan_strips(result.memory.scan):
            ax.plot(-strip[:, 1], strip[:, 0], "-", color=COLORS["memory_scan"], lw=1.0, zorder=3)
    # the configured body (its readings are ignored), else a box of the drawing's size
    foot = np.asarray(body_m, dtype=float) if body_m else footprint_xy(*footprint_m)
    ax.fill(
        -foot[:, 1], foot[:, 0], facecolor="#dddddd", edgecolor=COLORS["robot"], lw=1.2, zorder=4,
        hatch="//" if body_m else None,
    )  # fmt: skip
    ax.plot([0.0], [0.0], "^", color="black", ms=7, zorder=8)
    amber = untrusted(result)
    drop = COLORS["untrusted" if amber else "cliff"]
    for near, far in areas:
        poly = area_polygon(near, far)
        ax.add_patch(Polygon(np.c_[-poly[:, 1], poly[:, 0]], facecolor=drop, alpha=0.35, lw=0))
    if result.cliff is not None:
        for strip in scan_strips(result.cliff.scan):
            ax.plot(-strip[:, 1], strip[:, 0], "-", color=drop, lw=2.4, zorder=6)
    for strip in scan_strips(scan):
        color = COLORS["untrusted" if amber else "scan"]
        ax.plot(-strip[:, 1], strip[:, 0], "-o", color=color, lw=1.8, ms=1.5, zorder=7)
    close = too_close_xy(scan, TOO_CLOSE_R_M)
    if len(close):
        ax.plot(-close[:, 1], close[:, 0], "x", color=COLORS["obstacle"], ms=4, zorder=8)
    ax.set_xlim(-half, half)
    ax.set_ylim(min(-footprint_m[0], float(foot[:, 0].min())) - 0.2, reach + 0.2)
    ax.set_aspect("equal")
    ax.set_xlabel("to the left [m]", fontsize=8)
    ax.set_ylabel("forward [m]", fontsize=8)
    ax.tick_params(labelsize=7)
    ax.set_title("top down (robot's base frame)", fontsize=9)
    ax.xaxis.set_major_formatter(lambda v, _pos: f"{0.0 - v:g}")
    ax.grid(False)


def _legend(
    fig: Figure, result: Result, has_mask: bool, body_m: tuple[tuple[float, float], ...] = ()
) -> None:
    from matplotlib.lines import Line2D
    from matplotlib.patches import Patch

    amber = untrusted(result)
    scan = COLORS["untrusted" if amber else "scan"]
    drop = COLORS["untrusted" if amber else "cliff"]
    handles = [
        Line2D([], [], color=scan, marker="o", ms=3, label="laser scan (its pixels)"),
        Line2D([], [], color=drop, lw=2.4, label="cliff scan (drop-off edge)"),
        Patch(color=drop, alpha=0.5, label="drop-off: lower floor seen"),
    ]
    if has_mask:
        handles.append(Patch(color=COLORS["obstacle"], label="obstacle pixels"))
    if np.isneginf(np.asarray(result.scan.ranges)).any():
        handles.append(
            Line2D([], [], color=COLORS["obstacle"], marker="x", ls="", label="too close (-inf)")
        )
    first, stop = result.scan_band
    if (first, stop) != (0, result.intrinsics.height):
        handles.append(Patch(color=COLORS["band"], alpha=0.5, label="rows the scan reads"))
    if result.memory is not None:
        handles += [
            Patch(color=COLORS["memory_obstacle"], alpha=0.7, label="remembered obstacle"),
            Patch(color=COLORS["memory_cliff"], alpha=0.7, label="remembered drop-off"),
            Line2D([], [], color=COLORS["memory_scan"], label="memory scan (360°)"),
        ]
    handles += [
        Patch(
            facecolor="#dddddd",
            edgecolor=COLORS["robot"],
            hatch="//" if body_m else None,
            label="robot body (ignored), sensor ▲" if body_m else "robot, sensor ▲",
        ),
        Patch(color=COLORS["fov"], alpha=0.3, label="field of view"),
    ]
    if amber:
        handles.append(Patch(color=COLORS["untrusted"], label="amber: mount not trusted"))
    fig.legend(handles=handles, loc="outside lower center", ncols=4, fontsize=7, frameon=False)
