"""``depthnav mount``: dead zones and the highest obstacle seen per distance, as text and figures.

The numbers come from ``plots.mount_side.plan_mount`` (eq. 15 and 16 of the mount planner); the
side view (``--plot``) draws that same plan, the sweep (``--sweep``) the paper's fig. 6 for this
sensor. Figures need the ``depthnav[plot]`` extra (matplotlib).
"""

from __future__ import annotations

import argparse
import math
import os
from pathlib import Path

from depthnav_daemon.commands.common import EXIT_OK, figure_output, save_figure
from depthnav_daemon.errors import ConfigError
from depthnav_daemon.pipeline.geometry import MAX_MOUNT_HEIGHT_M, Mount, check_range
from depthnav_daemon.plots.mount_side import MountPlan, describe_robot_top, plan_mount
from drivers.values import short_repr

MAX_DISTANCE_M = 100.0
# vertical field of view of the depth image, degrees (vendor data sheets)
SENSOR_VFOV_DEG = {
    "kinect": 43.0,
    "xtion": 45.0,
    "kinect2": 60.0,
    "realsense-d435": 58.0,
    "astra": 49.5,
    # Intel RealSense depth (data sheet: 87 x 58 deg each)
    "d435": 58.0,
    "d455": 58.0,
    "d405": 58.0,
}
# depth range of a sensor, metres: (nearest reading, far end of the data sheet's ideal range)
SENSOR_RANGE_M = {
    "realsense-d435": (0.28, 3.0),
    "d435": (0.28, 3.0),
    "d455": (0.52, 6.0),
    "d405": (0.07, 0.5),
}


def _distances(text: str) -> tuple[float, ...]:
    try:
        values = [float(t) for t in text.split(",") if t.strip()]
    except ValueError:
        raise ConfigError(
            f"--distances-m={text!r} is not a comma-separated list of numbers"
        ) from None
    if not values or any(not (0 < v <= MAX_DISTANCE_M) for v in values):
        raise ConfigError(f"--distances-m={text!r} is out of range (accepted: numbers in 0..100 m)")
    return tuple(values)


def sensor_vfov_deg(sensor: str, vfov_deg: float | None) -> float:
    """The vertical field of view: given, or the named sensor's.

    Raises:
        ConfigError: an unknown sensor name or a field of view out of range.
    """
    if vfov_deg is None:
        if sensor not in SENSOR_VFOV_DEG:
            raise ConfigError(
                f"--sensor={sensor!r} is not known (accepted: {', '.join(SENSOR_VFOV_DEG)})",
                hint="or give --vfov-deg",
            )
        vfov_deg = SENSOR_VFOV_DEG[sensor]
    return check_range("--vfov-deg", vfov_deg, 1.0, 170.0, " deg")


def mount_plan(
    height_m: float,
    tilt_deg: float,
    sensor: str,
    vfov_deg: float | None,
    distances: str,
    robot_height_m: float | None = None,
) -> MountPlan:
    """The checked inputs' plan (what is printed and drawn).

    Raises:
        ConfigError: a value out of range.
    """
    Mount(height_m, tilt_deg, 0.0)  # validates height and tilt with the usual messages
    vfov = sensor_vfov_deg(sensor, vfov_deg)
    if robot_height_m is not None:
        check_range("--robot-height-m", robot_height_m, 0.01, MAX_MOUNT_HEIGHT_M, " m")
    return plan_mount(height_m, tilt_deg, vfov, _distances(distances), robot_height_m)


def format_plan(plan: MountPlan) -> str:
    """The text table of a plan."""
    lines = [
        f"sensor height {plan.height_m:.2f} m, tilt {plan.tilt_deg:.1f} deg down, "
        f"vertical FOV {plan.vfov_deg:.1f} deg",
        f"lower dead zone (floor not seen): {_fmt(plan.dead_zone_m)}  (eq. 15)",
    ]
    if plan.robot_height_m is not None:
        lines.append(describe_robot_top(plan))
    lines += ["", f"{'distance m':>10}  {'highest obstacle seen m':>24}  (eq. 16)"]
    for d, top in zip(plan.distances_m, plan.highest_m, strict=True):
        seen = f"{top:.2f}" if top >= 0 else f"nothing (the view ends at {plan.view_ends_m:.2f} m)"
        lines.append(f"{d:>10.2f}  {seen:>24}")
    return "\n".join(lines)


def _fmt(value: float) -> str:
    return f"{value:.2f} m" if math.isfinite(value) else "none (the floor is never seen)"


def cmd_mount(args: argparse.Namespace) -> int:
    # the figure files are checked before any work, so a bad name fails at once
    plot = figure_output(args.plot, "--plot")[0] if args.plot else None
    sweep = figure_output(args.sweep, "--sweep")[0] if args.sweep else None
    if plot is not None and sweep is not None and _same_file(plot, sweep):
        raise ConfigError(
            f"--plot and --sweep name the same file {short_repr(str(plot))}: the sweep would "
            "overwrite the side view",
            hint="give each figure its own file, e.g. --plot side.png --sweep sweep.png",
        )
    plan = mount_plan(
        args.height_m,
        args.tilt_deg,
        args.sensor,
        args.vfov_deg,
        args.distances_m,
        args.robot_height_m,
    )
    print(format_plan(plan))  # noqa: T201
    if args.vfov_deg is None and args.sensor in SENSOR_RANGE_M:
        near, far = SENSOR_RANGE_M[args.sensor]
        print(f"{args.sensor} depth range: from {near:.2f} m, ideal to {far:.1f} m")  # noqa: T201
    if plot is not None:
        _write_side_view(plan, plot)
    if sweep is not None:
        _write_sweep(plan, args.sensor if args.vfov_deg is None else "", sweep)
    return EXIT_OK


def _same_file(a: Path, b: Path) -> bool:
    """The two paths name one file (the same path, or an existing file through links)."""
    if os.path.abspath(a) == os.path.abspath(b):
        return True
    try:
        return os.path.samefile(a, b)
    except (OSError, ValueError):  # one does not exist yet: different files
        return False


def _write_side_view(plan: MountPlan, path: Path) -> None:
    from depthnav_daemon.plots.mount_side import draw_side_view

    save_figure(draw_side_view(plan), path, "--plot")
    print(f"side view written to {path}")  # noqa: T201


def _write_sweep(plan: MountPlan, sensor: str, path: Path) -> None:
    from depthnav_daemon.plots.sweep import draw_sweep

    save_figure(draw_sweep(plan, sensor), path, "--sweep")
    print(f"dead-zone sweep written to {path}")  # noqa: T201
