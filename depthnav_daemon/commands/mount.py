"""``depthnav mount``: dead zones and the highest visible obstacle per distance, as text and a
PNG."""

from __future__ import annotations

import argparse
import math
from pathlib import Path

import numpy as np

from depthnav_daemon.commands.common import EXIT_OK
from depthnav_daemon.errors import ConfigError
from depthnav_daemon.pipeline.geometry import Mount, check_range
from depthnav_daemon.pipeline.mount_planner import lower_dead_zone_m, max_visible_height_m

# vertical field of view of the depth image, degrees (vendor data sheets)
MAX_DISTANCE_M = 100.0
SENSOR_VFOV_DEG = {
    "kinect": 43.0,
    "xtion": 45.0,
    "kinect2": 60.0,
    "realsense-d435": 58.0,
    "astra": 49.5,
}


def _distances(text: str) -> list[float]:
    try:
        values = [float(t) for t in text.split(",") if t.strip()]
    except ValueError:
        raise ConfigError(
            f"--distances-m={text!r} is not a comma-separated list of numbers"
        ) from None
    if not values or any(not (0 < v <= MAX_DISTANCE_M) for v in values):
        raise ConfigError(f"--distances-m={text!r} is out of range (accepted: numbers in 0..100 m)")
    return values


def mount_report(
    height_m: float,
    tilt_deg: float,
    sensor: str,
    vfov_deg: float | None,
    distances: str,
    plot: Path | None,
) -> str:
    """The text table (and optionally a PNG side view) for one mount."""
    Mount(height_m, tilt_deg, 0.0)  # validates height and tilt with the usual messages
    if vfov_deg is None:
        if sensor not in SENSOR_VFOV_DEG:
            raise ConfigError(
                f"--sensor={sensor!r} is not known (accepted: {', '.join(SENSOR_VFOV_DEG)})",
                hint="or give --vfov-deg",
            )
        vfov_deg = SENSOR_VFOV_DEG[sensor]
    vfov_deg = check_range("--vfov-deg", vfov_deg, 1.0, 170.0, " deg")
    ds = _distances(distances)
    dead = float(lower_dead_zone_m(height_m, tilt_deg, vfov_deg))
    lines = [
        f"sensor height {height_m:.2f} m, tilt {tilt_deg:.1f} deg down, "
        f"vertical FOV {vfov_deg:.1f} deg",
        f"lower dead zone (floor not seen): {_fmt(dead)}  (eq. 15)",
        "",
        f"{'distance m':>10}  {'highest obstacle seen m':>24}  (eq. 16)",
    ]
    tops = np.atleast_1d(max_visible_height_m(height_m, tilt_deg, vfov_deg, np.array(ds)))
    for d, top in zip(ds, tops, strict=True):
        lines.append(f"{d:>10.2f}  {top:>24.2f}")
    if plot is not None:
        draw_side_view(plot, height_m, tilt_deg, vfov_deg, max(ds))
        lines.append(f"\nside view written to {plot}")
    return "\n".join(lines)


def _fmt(value: float) -> str:
    return f"{value:.2f} m" if math.isfinite(value) else "none (the floor is never seen)"


def draw_side_view(
    path: Path, height_m: float, tilt_deg: float, vfov_deg: float, max_dist_m: float
) -> None:
    """A side view: floor, sensor, the field of view wedge, the dead zone, to a PNG."""
    from PIL import Image, ImageDraw

    w, h, margin = 800, 400, 40
    top_m = max(2.0 * height_m, 2.0)
    sx = (w - 2 * margin) / max_dist_m
    sy = (h - 2 * margin) / top_m

    def px(x: float, z: float) -> tuple[float, float]:
        return margin + x * sx, h - margin - z * sy

    img = Image.new("RGB", (w, h), "white")
    g = ImageDraw.Draw(img)
    lo = math.radians(tilt_deg + vfov_deg / 2)  # lower edge, below the horizon
    hi = math.radians(tilt_deg - vfov_deg / 2)  # upper edge
    far = max_dist_m * 2

    def edge(angle: float) -> tuple[float, float]:
        if angle > 0:  # meets the floor
            x = height_m / math.tan(angle)
            if x < far:
                return x, 0.0
        return far, height_m - far * math.tan(angle)

    wedge = [px(0, height_m), px(*edge(lo)), px(*edge(hi))]
    if edge(lo)[1] == 0.0 and edge(hi)[1] > 0.0:
        wedge.insert(2, px(far, 0.0))
    g.polygon(wedge, fill=(200, 225, 255))
    g.line([px(0, 0), px(max_dist_m, 0)], fill="black", width=2)
    dead = float(lower_dead_zone_m(height_m, tilt_deg, vfov_deg))
    if math.isfinite(dead):
        g.line([px(0, 0), px(min(dead, max_dist_m), 0)], fill="red", width=5)
        g.text(px(0, 0.05 * top_m), f"dead zone {dead:.2f} m", fill="red")
    g.ellipse(
        [
            px(0, height_m)[0] - 5,
            px(0, height_m)[1] - 5,
            px(0, height_m)[0] + 5,
            px(0, height_m)[1] + 5,
        ],
        fill="black",
    )
    g.text(
        (margin, 10),
        f"h {height_m:.2f} m, tilt {tilt_deg:.1f} deg, vfov {vfov_deg:.1f} deg",
        fill="black",
    )
    for d in np.arange(0, max_dist_m + 1e-9, 0.5):
        g.text((px(float(d), 0)[0] - 8, h - margin + 8), f"{d:g}", fill="black")
    img.save(path)


def cmd_mount(args: argparse.Namespace) -> int:
    text = mount_report(
        args.height_m, args.tilt_deg, args.sensor, args.vfov_deg, args.distances_m, args.plot
    )
    print(text)  # noqa: T201
    return EXIT_OK
