"""The memory's former per-mount table (``near_limits``: the lower dead zone per bin), kept until
``pipeline.prepare`` and its test move to ``coverage.floor_extent``, which the memory now uses (its
``near`` is this table's, with every column read and the view's edge bins handled).

numpy took 30-45 ms at 1280x720 for it (a full-image ray rotation, arctan2, a scatter-min) on the
worker that builds a new mount's tables, holding the interpreter lock for parts of it: the frame
loop waited for the lock. This kernel visits only the sampled pixels and releases the lock.
"""

from __future__ import annotations

import functools
import math

import numpy as np

from depthnav_daemon.pipeline._jit import kernel
from depthnav_daemon.pipeline.geometry import F32, Mount, cam_to_level, pixel_rays
from drivers.base import Intrinsics

NEAR_STRIDE = 2  # pixels between the samples of the near-limit table


@kernel
def near_limits_kernel(
    rays, rot, height_m, row0, row_stop, row_step, col_step, angle_min, inc, out
):
    """Per scan bin, the nearest floor range any sampled pixel sees (``near_limits``).

    Args:
        rays: (H, W, 3) float64 camera rays per metre of depth (``geometry.pixel_rays``).
        rot: (3, 3) float64 camera to level frame.
        height_m: the sensor's height above the floor, metres.
        row0, row_stop, row_step, col_step: the sampled pixels, rows row0:row_stop:row_step and
            columns 0::col_step.
        angle_min, inc: bin b is centred on angle_min + b * inc, radians.
        out: (n,) float64, overwritten: the nearest floor range per bin, metres; +inf where no
            sampled pixel sees the floor, then each bin the minimum of itself and its two
            neighbours (the sampling stride leaves gaps; the ends wrap, as numpy.roll).
    """
    n = out.shape[0]
    for b in range(n):
        out[b] = math.inf
    r00, r01, r02 = rot[0, 0], rot[0, 1], rot[0, 2]
    r10, r11, r12 = rot[1, 0], rot[1, 1], rot[1, 2]
    r20, r21, r22 = rot[2, 0], rot[2, 1], rot[2, 2]
    for v in range(row0, row_stop, row_step):
        for u in range(0, rays.shape[1], col_step):
            x = rays[v, u, 0]
            y = rays[v, u, 1]
            z = rays[v, u, 2]
            dz = r20 * x + r21 * y + r22 * z
            if not dz < 0.0:
                continue
            dx = r00 * x + r01 * y + r02 * z
            dy = r10 * x + r11 * y + r12 * z
            t = height_m / -dz
            r = t * math.hypot(dx, dy)
            b = math.floor((math.atan2(dy, dx) - angle_min) / inc + 0.5)
            if 0 <= b < n and r < out[b]:
                out[b] = r
    if n > 1:
        # min over (b - 1, b, b + 1), wrapping: from a copy of the first and the original last
        first = out[0]
        prev = out[n - 1]
        for b in range(n):
            here = out[b]
            nxt = first if b == n - 1 else out[b + 1]
            out[b] = min(prev, here, nxt)
            prev = here


@functools.lru_cache(maxsize=32)
def near_limits(
    intr: Intrinsics,
    mount: Mount,
    angle_min: float,
    inc: float,
    n: int,
    rows: tuple[int, int, int],
) -> F32:
    """(n,) float32: per scan bin, the nearest floor range the sensor sees (its lower dead zone,
    eq. 15 generalised to every bearing, tilt and roll), +inf where no pixel sees the floor."""
    start, stop, step = rows
    stop = intr.height if stop < 0 else min(stop, intr.height)
    out = np.empty(n)
    near_limits_kernel(
        pixel_rays(intr),
        cam_to_level(mount.tilt_rad, mount.roll_rad),
        float(mount.height_m),
        int(start),
        int(stop),
        max(1, int(step)),
        max(1, NEAR_STRIDE),
        float(angle_min),
        float(inc),
        out,
    )
    res = out.astype(np.float32)
    res.setflags(write=False)
    return res
