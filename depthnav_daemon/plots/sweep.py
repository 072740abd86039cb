"""The paper's fig. 6 for any sensor: the lower dead zone against tilt for several heights (eq. 15),
beside the highest obstacle seen at 1, 2 and 3 m against tilt (eq. 16), so a tilt can be chosen
from a picture. The mount being planned is marked on both."""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from depthnav_daemon.pipeline.geometry import MAX_TILT_DEG
from depthnav_daemon.pipeline.mount_planner import lower_dead_zone_m, max_visible_height_m
from depthnav_daemon.plots import COLORS, new_figure

if TYPE_CHECKING:
    from matplotlib.axes import Axes
    from matplotlib.figure import Figure

    from depthnav_daemon.plots.mount_side import MountPlan

HEIGHTS_M = (0.3, 0.5, 0.8, 1.2)  # the paper's fig. 6 shows a few typical mounts
SWEEP_DISTANCES_M = (1.0, 2.0, 3.0)
DEAD_ZONE_TOP_M = 3.0  # dead zones longer than this run off the top of the plot
SAME_HEIGHT_M = 1e-3  # the mount's own height is one of the curves
HEIGHT_COLORS = ("#9ecae1", "#6baed6", "#3182bd", "#08519c")
DISTANCE_COLORS = ("#a1d99b", "#41ab5d", "#006d2c")


def tilts_deg(vfov_deg: float, tilt_deg: float = 0.0) -> np.ndarray:
    """Tilts swept: level (or ``tilt_deg`` - 5 deg for a mount tilted up) to where the lower edge
    of the view points straight down."""
    lo = float(np.floor(tilt_deg / 5.0) * 5.0 - 5.0) if tilt_deg < 0 else 0.0
    return np.linspace(lo, min(MAX_TILT_DEG, 90.0 - vfov_deg / 2 + 5.0), 200)


def dead_zone_curves(
    vfov_deg: float, heights_m: tuple[float, ...], tilt_deg: float = 0.0
) -> dict[float, np.ndarray]:
    """Eq. 15 (h_1 = 0) over :func:`tilts_deg` for each height, metres."""
    return {
        h: np.array(
            [float(lower_dead_zone_m(h, t, vfov_deg)) for t in tilts_deg(vfov_deg, tilt_deg)]
        )
        for h in heights_m
    }


def draw_sweep(plan: MountPlan, sensor: str = "") -> Figure:
    """Fig. 6 for ``plan``'s sensor, with ``plan``'s height among the curves and its tilt marked."""
    fig = new_figure(8.0, 3.9)
    left, right = fig.subplots(1, 2)
    _draw_dead_zone(left, plan)
    _draw_highest(right, plan)
    name = f"{sensor}, " if sensor else ""
    fig.suptitle(f"choosing the tilt: {name}{plan.vfov_deg:g}° vertical field of view", fontsize=11)
    return fig


def _mark_tilt(ax: Axes, plan: MountPlan) -> None:
    ax.axvline(plan.tilt_deg, color="black", lw=1, ls=":")
    ax.annotate(
        f"{plan.tilt_deg:g}°",
        (plan.tilt_deg, 1.0),
        xycoords=("data", "axes fraction"),
        xytext=(3, -12),
        textcoords="offset points",
        fontsize=8,
    )


def _draw_dead_zone(ax: Axes, plan: MountPlan) -> None:
    heights = tuple(sorted(set(HEIGHTS_M) | {round(plan.height_m, 3)}))
    tilts = tilts_deg(plan.vfov_deg, plan.tilt_deg)
    others = iter(HEIGHT_COLORS * 2)
    for h, dead in dead_zone_curves(plan.vfov_deg, heights, plan.tilt_deg).items():
        mine = abs(h - plan.height_m) < SAME_HEIGHT_M
        ax.plot(
            tilts,
            np.where(np.isfinite(dead), dead, np.nan),
            color=COLORS["dead"] if mine else next(others),
            lw=2.5 if mine else 1.5,
            gid=f"dead_zone_{h:g}",
            label=f"h = {h:g} m" + (" (this mount)" if mine else ""),
        )
    if np.isfinite(plan.dead_zone_m):
        ax.plot([plan.tilt_deg], [plan.dead_zone_m], "o", color="black", ms=5, zorder=5)
    _mark_tilt(ax, plan)
    ax.set_ylim(0.0, DEAD_ZONE_TOP_M)
    ax.set_xlim(tilts[0], tilts[-1])
    ax.set_xlabel("tilt, down [deg] (negative: up)")
    ax.set_ylabel("lower dead zone on the floor [m]")
    ax.set_title("floor not seen in front (eq. 15)", fontsize=10)
    ax.grid(True, color="#dddddd", lw=0.6)
    ax.legend(fontsize=8, loc="upper right")


def _draw_highest(ax: Axes, plan: MountPlan) -> None:
    tilts = tilts_deg(plan.vfov_deg, plan.tilt_deg)
    tops = []
    for d, color in zip(SWEEP_DISTANCES_M, DISTANCE_COLORS, strict=True):
        top = np.array(
            [float(max_visible_height_m(plan.height_m, t, plan.vfov_deg, d)) for t in tilts]
        )
        tops.append(top)
        ax.plot(tilts, top, color=color, lw=2, gid=f"highest_{d:g}", label=f"at {d:g} m")
    ax.axhline(plan.height_m, color="black", lw=0.8, ls="--")
    ax.annotate(
        f"sensor {plan.height_m:.2f} m",
        (tilts[-1], plan.height_m),
        xytext=(-3, 3),
        textcoords="offset points",
        ha="right",
        fontsize=8,
    )
    if plan.robot_height_m is not None:
        ax.axhline(plan.robot_height_m, color=COLORS["obstacle"], lw=1.2, ls="--")
        ax.annotate(
            f"robot {plan.robot_height_m:.2f} m",
            (tilts[-1], plan.robot_height_m),
            xytext=(-3, 3),
            textcoords="offset points",
            ha="right",
            fontsize=8,
            color=COLORS["obstacle"],
        )
    _mark_tilt(ax, plan)
    hi = max(2.0 * plan.height_m, 1.3 * (plan.robot_height_m or 0.0), 1.0)
    ax.set_ylim(0.0, hi)
    ax.set_xlim(tilts[0], tilts[-1])
    ax.set_xlabel("tilt, down [deg] (negative: up)")
    ax.set_ylabel("highest obstacle seen [m]")
    ax.set_title(f"top of the view at h = {plan.height_m:.2f} m (eq. 16)", fontsize=10)
    ax.grid(True, color="#dddddd", lw=0.6)
    ax.legend(fontsize=8, loc="lower left")
