"""One mount seen from the side (the paper's figs. 6-7 for a single pose): what the sensor sees.

:func:`plan_mount` computes the numbers ``depthnav mount`` prints, from the mount planner's eq. 15
and eq. 16; :func:`draw_side_view` draws the same numbers to scale. Both come from one
:class:`MountPlan`, so the text and the figure cannot disagree.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from depthnav_daemon.pipeline.mount_planner import lower_dead_zone_m, max_visible_height_m
from depthnav_daemon.plots import COLORS, new_figure

if TYPE_CHECKING:
    from matplotlib.axes import Axes
    from matplotlib.figure import Figure

# the robot's body behind the sensor: its length is only a sketch, its height is to scale
ROBOT_DRAWN_LENGTH_M = 0.4
LEVEL_SLOPE = 1e-12  # an upper edge flatter than this is level


@dataclass(frozen=True, slots=True)
class MountPlan:
    """What a sensor at one mount sees (eq. 15, 16), in metres.

    Attributes:
        height_m, tilt_deg, vfov_deg: the mount (tilt positive = down) and vertical field of view.
        robot_height_m: the robot's height, or None when not given.
        distances_m: the distances of the table.
        highest_m: eq. 16 at each distance: the highest point seen there.
        dead_zone_m: eq. 15 with h_1 = 0: floor not seen in front of the sensor (+inf: never).
        robot_top_seen_m: (from, until) distances at which points as high as the robot are in
            view (until may be +inf), or None when they never are; None without a robot height.
    """

    height_m: float
    tilt_deg: float
    vfov_deg: float
    robot_height_m: float | None
    distances_m: tuple[float, ...]
    highest_m: tuple[float, ...]
    dead_zone_m: float
    robot_top_seen_m: tuple[float, float] | None

    @property
    def upper_slope(self) -> float:
        """Rise of the view's upper edge per metre ahead (eq. 16's tan(theta/2 - alpha))."""
        h = self.height_m
        return float(max_visible_height_m(h, self.tilt_deg, self.vfov_deg, 1.0)) - h

    @property
    def view_ends_m(self) -> float:
        """Where the upper edge of the view reaches the floor (+inf when it never does)."""
        slope = self.upper_slope
        return -self.height_m / slope if slope < 0 else math.inf


def plan_mount(
    height_m: float,
    tilt_deg: float,
    vfov_deg: float,
    distances_m: tuple[float, ...],
    robot_height_m: float | None = None,
) -> MountPlan:
    """The numbers of one mount, from eq. 15 and eq. 16 of the mount planner.

    Raises:
        ConfigError: a value outside its accepted range.
    """
    tops = np.atleast_1d(max_visible_height_m(height_m, tilt_deg, vfov_deg, np.array(distances_m)))
    dead = float(lower_dead_zone_m(height_m, tilt_deg, vfov_deg))
    seen = None
    if robot_height_m is not None:
        slope = float(max_visible_height_m(height_m, tilt_deg, vfov_deg, 1.0)) - height_m
        seen = _interval_below_edge(height_m, slope, robot_height_m)
    return MountPlan(
        height_m,
        tilt_deg,
        vfov_deg,
        robot_height_m,
        tuple(float(d) for d in distances_m),
        tuple(float(t) for t in tops),
        dead,
        seen,
    )


def _interval_below_edge(h: float, slope: float, top: float) -> tuple[float, float] | None:
    """Distances at which height ``top`` is under the upper edge h + slope * d (d >= 0)."""
    if abs(slope) < LEVEL_SLOPE:
        return (0.0, math.inf) if top <= h else None
    cross = (top - h) / slope  # where the edge passes through ``top``
    if slope > 0:
        return (max(cross, 0.0), math.inf)
    return (0.0, cross) if cross > 0 else None


def describe_robot_top(plan: MountPlan) -> str:
    """One line: from where obstacles as high as the robot are seen."""
    r, seen = plan.robot_height_m, plan.robot_top_seen_m
    if r is None:
        return ""
    head = f"obstacles as high as the robot ({r:.2f} m) are seen"
    if seen is None:
        return f"{head} at no distance: tilt up or mount higher  (eq. 16)"
    lo, hi = seen
    if math.isinf(hi):
        return f"{head} from {lo:.2f} m on  (eq. 16)"
    return f"{head} up to {hi:.2f} m  (eq. 16)"


def draw_side_view(plan: MountPlan) -> Figure:
    """The mount to scale: floor, robot, field of view, lower dead zone (eq. 15 over h_1), the
    highest obstacle seen per distance (eq. 16) and where it meets the robot's height."""
    max_d = max(*plan.distances_m, 1.0)
    seen = plan.robot_top_seen_m
    if seen is not None and 0.0 < seen[0] < 3 * max_d:  # show where the robot's height is reached
        max_d = max(max_d, 1.1 * seen[0])
    h, r = plan.height_m, plan.robot_height_m or 0.0
    top = max(1.6 * h, 1.25 * r, 1.0)
    # the table's highest points in view: a level sensor's rise above its height
    shown = [t for d, t in zip(plan.distances_m, plan.highest_m, strict=True) if d <= max_d]
    top = max(top, 1.1 * max((t for t in shown if math.isfinite(t)), default=0.0))
    # equal scales: the axes are as tall as the scene is for its width, plus room for the text
    axes_h_in = 7.1 * top / (max_d + ROBOT_DRAWN_LENGTH_M + 0.15)
    fig = new_figure(8.0, min(max(axes_h_in + 1.45, 3.0), 7.0))
    ax = fig.add_subplot()
    _draw_view(ax, plan, max_d, top)
    if plan.robot_height_m is not None:
        _draw_robot(ax, plan, max_d)
    ax.plot([0.0], [h], "o", color="black", ms=7, zorder=5, label="sensor")
    ax.plot(
        plan.distances_m,
        plan.highest_m,
        "o",
        color=COLORS["fov"],
        ms=4,
        gid="eq16_table",
        label="highest seen at the table's distances",
    )
    ax.axhline(0.0, color="black", lw=1.5)
    ax.set_xlim(-ROBOT_DRAWN_LENGTH_M - 0.15, max_d)
    ax.set_ylim(0.0, top)
    ax.set_aspect("equal")
    ax.set_xlabel("distance ahead of the sensor [m]")
    ax.set_ylabel("height above the floor [m]")
    ax.set_title(
        f"sensor {h:.2f} m high, tilted {abs(plan.tilt_deg):g}° "
        f"{'up' if plan.tilt_deg < 0 else 'down'}, vertical field of view "
        f"{plan.vfov_deg:g}°",
        fontsize=10,
    )
    ax.grid(True, color="#dddddd", lw=0.6)
    ax.set_axisbelow(True)
    fig.legend(loc="outside lower center", ncols=3, fontsize=8, frameon=False)
    return fig


def _draw_view(ax: Axes, plan: MountPlan, max_d: float, top: float) -> None:
    """Field of view, its lower edge over h_1 (eq. 15) and its upper edge (eq. 16)."""
    h, t, v = plan.height_m, plan.tilt_deg, plan.vfov_deg
    # lower edge: a point h_1 above the floor enters the view at eq. 15's d_m(h_1)
    h1 = np.linspace(0.0, h, 50)
    low_x = lower_dead_zone_m(h, t, v, h1)
    finite = np.isfinite(low_x) & (low_x <= 4 * max_d)
    low_x, low_y = low_x[finite], h1[finite]
    far = np.linspace(0.0, 2 * max_d, 50)
    up_y = max_visible_height_m(h, t, v, far)
    if low_x.size:  # the view meets the floor: wedge sensor -> floor -> far -> upper edge
        wedge_x = np.r_[low_x[::-1], low_x[0], 2 * max_d, far[::-1]]
        wedge_y = np.r_[low_y[::-1], 0.0, 0.0, up_y[::-1]]
    else:  # looking at or above the horizon: the lower edge is eq. 16's twin below the axis
        low_edge = h - far * math.tan(math.radians(t + v / 2))
        wedge_x, wedge_y = np.r_[far, far[::-1]], np.r_[low_edge, up_y[::-1]]
    ax.fill(
        wedge_x,
        np.clip(wedge_y, 0.0, 4 * top),
        color=COLORS["fov"],
        alpha=0.15,
        lw=0,
        label=f"field of view ({v:g}°)",
    )
    ax.plot(
        far, up_y, color=COLORS["fov"], lw=2, gid="eq16", label="highest obstacle seen (eq. 16)"
    )
    ends = plan.view_ends_m
    if ends < max_d:  # the view's upper edge reaches the floor: nothing beyond is seen
        ax.axvspan(
            ends,
            max_d,
            facecolor="none",
            edgecolor="#999999",
            hatch="//",
            lw=0,
            label=f"not seen: the view ends on the floor at {ends:.2f} m",
        )
    if low_x.size:
        ax.plot(
            low_x, low_y, color=COLORS["dead"], lw=2, gid="eq15", label="view's lower edge (eq. 15)"
        )
        ax.fill(
            np.r_[0.0, low_x],
            np.r_[0.0, low_y],
            color=COLORS["dead"],
            alpha=0.35,
            lw=0,
            label=f"lower dead zone: {plan.dead_zone_m:.2f} m of floor",
        )
        ax.annotate(
            f"{plan.dead_zone_m:.2f} m",
            (plan.dead_zone_m, 0.0),
            xytext=(4, 4),
            textcoords="offset points",
            ha="left",
            fontsize=8,
            color="#a05a00",
        )


def _draw_robot(ax: Axes, plan: MountPlan, max_d: float) -> None:
    """The robot's body (height to scale), its height line and the upper dead zone under it."""
    from matplotlib.patches import Rectangle

    r = float(plan.robot_height_m or 0.0)
    ax.add_patch(
        Rectangle(
            (-ROBOT_DRAWN_LENGTH_M, 0.0),
            ROBOT_DRAWN_LENGTH_M,
            r,
            facecolor="#cccccc",
            edgecolor=COLORS["robot"],
            label=f"robot, {r:.2f} m high",
        )
    )
    ax.axhline(r, color=COLORS["robot"], lw=1, ls="--")
    d = np.linspace(0.0, max_d, 100)
    edge = plan.height_m + plan.upper_slope * d
    ax.fill_between(
        d,
        edge,
        r,
        where=edge < r,
        color=COLORS["obstacle"],
        alpha=0.18,
        lw=0,
        label="not seen, below the robot's height",
    )
    seen = plan.robot_top_seen_m
    if seen is None:
        return
    for x in seen:
        if 0.0 < x < max_d:
            ax.plot([x], [r], "D", color=COLORS["obstacle"], ms=6, zorder=6, gid="robot_top")
            ax.annotate(
                f"{x:.2f} m",
                (x, r),
                xytext=(0, 7),
                textcoords="offset points",
                ha="center",
                fontsize=8,
                color=COLORS["obstacle"],
            )
