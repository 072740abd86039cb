"""The paper's box experiment (figs. 11-12) as one figure: both scan methods side by side.

One panel per method; a row per sensor pose and ground margin e_g, a column per box (40, 15, 3,
1 cm). A filled cell is a box the scan reports within 5 cm of its true range; a dot marks a box
taller than e_g (one that should be reported); the last column counts the bins that report an
obstacle away from every box (the floor, or a box at the wrong bearing).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from depthnav_daemon.plots import COLORS, new_figure

if TYPE_CHECKING:
    from matplotlib.axes import Axes
    from matplotlib.figure import Figure

    from depthnav_daemon.sim.paper_experiment import Row

METHODS = (("paper", "paper (eq. 1-5, as published)"), ("exact", "exact (depthnav's default)"))


def detection_grid(
    rows: list[Row], method: str, poses: tuple, margins: tuple
) -> tuple[np.ndarray, np.ndarray]:
    """(len(poses) * len(margins), boxes) bool detections and the false bins per row, in pose then
    margin order."""
    by_key = {(r.method, r.height_m, r.tilt_deg, r.margin_m): r for r in rows}
    found, false_bins = [], []
    for h, t in poses:
        for e in margins:
            r = by_key[(method, h, t, e)]
            found.append(r.detected)
            false_bins.append(r.false_bins)
    return np.array(found, dtype=bool), np.array(false_bins)


def draw_experiment(
    rows: list[Row],
    poses: tuple,
    margins: tuple,
    box_heights_m: tuple[float, ...],
) -> Figure:
    """Both methods' detections over every pose and margin (see the module docstring)."""
    fig = new_figure(8.0, 7.4)
    axes = fig.subplots(1, 2, sharey=True)
    for ax, (method, title) in zip(axes, METHODS, strict=True):
        found, false_bins = detection_grid(rows, method, poses, margins)
        _draw_panel(ax, found, false_bins, margins, box_heights_m)
        ax.set_title(title, fontsize=10)
    labels = [f"{e * 100:g} cm" for _ in poses for e in margins]
    axes[0].set_yticks(range(len(labels)), labels, fontsize=7)
    axes[0].set_ylabel("ground margin e_g, per sensor pose (height, tilt down)", labelpad=62)
    for i, (h, t) in enumerate(poses):
        axes[0].annotate(
            f"{h:.2f} m\n{t:g}°",
            (0.0, (i + 0.5) * len(margins) - 0.5),
            xycoords=("axes fraction", "data"),
            xytext=(-46, 0),
            textcoords="offset points",
            ha="right",
            va="center",
            fontsize=8,
            fontweight="bold",
        )
    fig.suptitle(
        "box experiment (figs. 11-12) on synthetic Kinect frames: which boxes each method reports",
        fontsize=10,
    )
    _legend(fig)
    return fig


def _draw_panel(
    ax: Axes,
    found: np.ndarray,
    false_bins: np.ndarray,
    margins: tuple,
    box_heights_m: tuple[float, ...],
) -> None:
    from matplotlib.colors import ListedColormap

    n_rows, n_boxes = found.shape
    ax.imshow(
        found.astype(float),
        cmap=ListedColormap(["#eeeeee", COLORS["scan"]]),
        vmin=0,
        vmax=1,
        aspect="auto",
        interpolation="nearest",
        extent=(-0.5, n_boxes - 0.5, n_rows - 0.5, -0.5),
    )
    e = np.array([margins[i % len(margins)] for i in range(n_rows)])
    should_y, should_x = np.nonzero(
        (np.array(box_heights_m)[None, :] > e[:, None] + 0.005) & (e[:, None] > 0)
    )
    ax.plot(should_x, should_y, ".", color="black", ms=3)
    for y, n in enumerate(false_bins):
        ax.text(
            n_boxes - 0.1,
            y,
            str(n),
            va="center",
            ha="left",
            fontsize=7,
            color=COLORS["obstacle"] if n else "#888888",
        )
    for x in np.arange(0.5, n_boxes - 1):  # white gaps between the cells
        ax.axvline(x, color="white", lw=1.5)
    for y in np.arange(0.5, n_rows - 1):
        ax.axhline(y, color="white", lw=1.0)
    for k in range(len(margins), n_rows, len(margins)):
        ax.axhline(k - 0.5, color="black", lw=1.2)
    ax.set_xticks(range(n_boxes), [f"{h * 100:g}" for h in box_heights_m])
    ax.set_xlim(-0.5, n_boxes + 0.6)
    ax.set_xlabel("box height [cm]     false bins", fontsize=9, loc="right")
    ax.tick_params(length=0)
    for side in ("top", "right"):
        ax.spines[side].set_visible(False)


def _legend(fig: Figure) -> None:
    from matplotlib.lines import Line2D
    from matplotlib.patches import Patch

    fig.legend(
        handles=[
            Patch(color=COLORS["scan"], label="reported within 5 cm"),
            Patch(color="#eeeeee", label="missed"),
            Line2D(
                [],
                [],
                ls="",
                marker=".",
                color="black",
                label="taller than e_g: should be reported",
            ),
            Line2D([], [], ls="", marker="$3$", color=COLORS["obstacle"], label="false bins"),
        ],
        loc="outside lower center",
        ncols=4,
        fontsize=8,
        frameon=False,
    )
