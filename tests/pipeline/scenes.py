"""Scene builders shared by the pipeline tests: random boxes placed where the camera sees them."""

from __future__ import annotations

import math

import numpy as np

from depthnav_daemon.pipeline.geometry import Mount, level_rays
from depthnav_daemon.sim.synthetic import Box, Scene
from drivers.base import Intrinsics

# Asymmetric on purpose (fx != fy, cx != W/2, cy != H/2, H != W) so swapped axes fail loudly.
ASYM_640 = Intrinsics(640, 480, 575.0, 555.0, 331.0, 228.0)


def floor_point(intr: Intrinsics, mount: Mount, u: float, v: float) -> tuple[float, float] | None:
    """Where the ray through pixel (u, v) meets the floor, (x, y) metres in the world, or None."""
    d = level_rays(intr, mount.tilt_rad, mount.roll_rad)[int(v), int(u)]
    if d[2] >= -1e-6:
        return None
    t = mount.height_m / -d[2]
    return float(t * d[0]), float(t * d[1])


def random_boxes_in_view(
    rng: np.random.Generator,
    intr: Intrinsics,
    mount: Mount,
    count: int,
    min_range_m: float = 0.3,
    max_range_m: float = 3.5,
    height_range_m: tuple[float, float] = (0.12, 0.6),
) -> Scene:
    """Boxes standing on floor the camera sees, between min and max horizontal range, not
    overlapping."""
    boxes: list[Box] = []
    for _ in range(400):
        if len(boxes) == count:
            break
        u = rng.uniform(0.2, 0.8) * intr.width
        v = rng.uniform(0.45, 0.95) * intr.height
        p = floor_point(intr, mount, u, v)
        if p is None:
            continue
        r = math.hypot(*p)
        if not min_range_m + 0.05 < r < max_range_m:
            continue
        small = r < 0.8  # close to a low, steep camera only a small box fits in view
        size = rng.uniform(0.08, 0.15) if small else rng.uniform(0.15, 0.4)
        box = Box(
            p[0] + size / 2,
            p[1],
            size,
            size if small else rng.uniform(0.15, 0.4),
            rng.uniform(*height_range_m),
            yaw_deg=rng.uniform(-30, 30),
        )
        if any(math.hypot(box.x_m - b.x_m, box.y_m - b.y_m) < 2 * size + 0.1 for b in boxes):
            continue
        boxes.append(box)
    return Scene(boxes=tuple(boxes))
