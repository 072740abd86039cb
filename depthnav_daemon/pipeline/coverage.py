"""What a sensor's image covers on the floor, per scan bin: the seen region the safety contract
speaks of (README, Conventions).

A pitched camera sees the floor along a bearing only between two ranges: ``near`` (where its lowest
read image row meets the floor: the lower dead zone ends) and ``far`` (where the bearing leaves the
image through a side or top edge; +inf where pixels of the bin look at or above the horizon). A
tilted image's bottom corners reach wide bearings only close to the robot, so the bins at the edge
of the view have a ``far`` of a metre or two. A scan bin may say "clear out to range_max" (+inf)
only where ``far >= range_max``; the obstacle memory clears only cells between ``near`` and
``far``.

Both are per-mount tables (built once per camera, mount and layout, cached); the kernel releases
the interpreter lock (built on the worker of a mount change while the frame loop runs).
"""

from __future__ import annotations

import functools
import math

import numpy as np

from depthnav_daemon.pipeline._jit import kernel
from depthnav_daemon.pipeline.geometry import F32, Mount, cam_to_level, pixel_rays
from drivers.base import Intrinsics


@kernel
def floor_extent_kernel(rays, rot, height_m, row0, row_stop, row_step, angle_min, inc, near, far):
    """Per bin, the nearest and farthest floor range the read pixels see.

    Args:
        rays: (H, W, 3) float64 camera rays per metre of depth (``geometry.pixel_rays``).
        rot: (3, 3) float64 camera to level frame.
        height_m: the sensor's height above the floor, metres.
        row0, row_stop, row_step: the read rows (every column is read).
        angle_min, inc: bin b is centred on angle_min + b * inc, radians.
        near, far: (n,) float64, overwritten. A bin no pixel centre falls in takes the worse of
            its neighbours (near: the larger, far: the smaller); then near is the smallest and far
            the smallest over the bin and its two neighbours (a bin's edge bearings are seen no
            farther than its neighbours' centres). No pixel sees floor: near +inf, far 0.
    """
    n = near.shape[0]
    hits = np.zeros(n, np.int64)
    for b in range(n):
        near[b] = math.inf
        far[b] = 0.0
    r00, r01, r02 = rot[0, 0], rot[0, 1], rot[0, 2]
    r10, r11, r12 = rot[1, 0], rot[1, 1], rot[1, 2]
    r20, r21, r22 = rot[2, 0], rot[2, 1], rot[2, 2]
    for v in range(row0, row_stop, row_step):
        for u in range(rays.shape[1]):
            x = rays[v, u, 0]
            y = rays[v, u, 1]
            z = rays[v, u, 2]
            dx = r00 * x + r01 * y + r02 * z
            dy = r10 * x + r11 * y + r12 * z
            dz = r20 * x + r21 * y + r22 * z
            b = math.floor((math.atan2(dy, dx) - angle_min) / inc + 0.5)
            if b < 0 or b >= n:
                continue
            hits[b] += 1
            if dz < 0.0:
                r = height_m / -dz * math.hypot(dx, dy)
                near[b] = min(near[b], r)
                far[b] = max(far[b], r)
            else:
                far[b] = math.inf  # at or above the horizon: the floor on it is seen to the end
    _spread(hits, near, far)


@kernel
def _spread(hits, near, far):
    """Bins without a pixel take the worse neighbour; then each bin the smaller near and far of
    itself and its neighbours (floor_extent_kernel)."""
    n = near.shape[0]
    # empty bins (finer than the pixels there): the worse neighbour
    for b in range(n):
        if hits[b] == 0:
            lo = b - 1
            while lo >= 0 and hits[lo] == 0:
                lo -= 1
            hi = b + 1
            while hi < n and hits[hi] == 0:
                hi += 1
            if lo >= 0 and hi < n:
                near[b] = max(near[lo], near[hi])
                far[b] = min(far[lo], far[hi])
    if n > 1:
        pn = near[0]
        pf = far[0]
        for b in range(n):
            hn = near[b]
            hf = far[b]
            nn = near[b + 1] if b + 1 < n else hn
            nf = far[b + 1] if b + 1 < n else 0.0
            pf_b = pf if b > 0 else 0.0
            near[b] = min(pn, hn, nn)
            far[b] = min(pf_b, hf, nf)
            pn = hn
            pf = hf


@functools.lru_cache(maxsize=32)
def floor_extent(
    intr: Intrinsics,
    mount: Mount,
    angle_min: float,
    inc: float,
    n: int,
    rows: tuple[int, int, int],
) -> tuple[F32, F32]:
    """(near, far): (n,) float32 each, read-only; per bin of the layout (angle_min, inc, n) of the
    level frame at the sensor's foot, the floor ranges the read ``rows`` (start, stop, step; stop
    -1 = the image height) see, metres (module docstring). The end bins are seen no farther than
    0 (the view's edge runs through them)."""
    start, stop, step = rows
    stop = intr.height if stop < 0 else min(stop, intr.height)
    near = np.empty(n)
    far = np.empty(n)
    floor_extent_kernel(
        pixel_rays(intr),
        cam_to_level(mount.tilt_rad, mount.roll_rad),
        float(mount.height_m),
        int(start),
        int(stop),
        max(1, int(step)),
        float(angle_min),
        float(inc),
        near,
        far,
    )
    out = near.astype(np.float32), far.astype(np.float32)
    for a in out:
        a.setflags(write=False)
    return out


def seen_to(far: F32, range_max_m: float) -> np.ndarray:
    """(n,) bool: the bins whose floor is seen out to ``range_max_m``."""
    return far >= np.float32(range_max_m) * np.float32(1.0 - 1e-6)


__all__ = ["floor_extent", "floor_extent_kernel", "seen_to"]
