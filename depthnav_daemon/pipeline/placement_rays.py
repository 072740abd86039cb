"""What an off-centre sensor saw along each base-frame ray: the base scan's clear (+inf) claims and
the ranges between its arcs (``placement``).

A base bin's ray starts at the base origin, not at the sensor, so it crosses the sensor's bins
(wedges about the sensor's foot) one after another. The bin may say "clear to range_max" only if
every part of that ray is either in the sensor's lower dead zone (nearer than where its image first
meets the floor: the contract's stated exception) or inside a wedge that saw free floor past the
crossing (a +inf bin, or a hit farther than the crossing, within the wedge's view ``far``); a part
outside the view (beside or behind the sensor, or past a wedge's far) makes it unknown (NaN).
In the dead zone the image still sees tall things: a crossing there of a wedge whose view reaches
range_max but that read NaN this frame (a box too close to read: all 0) makes an obstacle scan's
bin unknown too (seed 1801: a box 0.33 m before the lens, 0.67 m from the base origin, read +inf
on 6 base bins); a cliff scan's NaN says nothing there (no camera sees the floor's dead zone).
The rays at the bin's centre and at both its edges are checked, so a clear bin is clear across its
width. The centre ray also takes the exact range where it crosses a hit's arc (``|rho u - t| = r``
inside the wedge), so a near obstacle seen from the side leaves no hole between the arcs that
``placement`` maps, and a too-close (-inf) wedge it crosses within range_min makes it -inf.

The crossings depend only on the layouts, the placement and the view (a table built once per
mount); per frame the kernel (``placement_ray_kernels``) looks each crossing's wedge up.
Consecutive crossings of a ray through neighbouring wedges within MERGE_SPAN_M of sensor range are
one entry, asked through a range minimum of their readings (a sparse table built per frame):
326,463 entries become 119,236 for a 640x480 sensor 0.22 m off the origin, 0.91 -> 0.50 ms a
frame for the scan (0.79 -> 0.48 ms for the cliff scan); over the 200 generated drives the
same unsafe counts and 0.1 % more NaN bins.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from depthnav_daemon.pipeline.coverage import floor_extent
from depthnav_daemon.pipeline.geometry import F64, Mount, frozen_table
from depthnav_daemon.pipeline.placement_ray_kernels import (
    run_starts,
    walk_crossings,
)
from drivers.base import Intrinsics

RAYS = (-0.45, 0.0, 0.45)  # checked rays per base bin, in base bin widths from its centre
CENTRE = 1  # the index of the centre ray in RAYS (the one that takes arc crossings)
# consecutive crossings of one ray through neighbouring wedges whose sensor ranges lie within this
# span (m) are one entry, asked as a whole: clear only if every wedge's reading lies beyond the
# entry's farthest point (a reading up to this much beyond one crossing's own far end makes the
# bin unknown rather than clear: safe); near the sensor a ray crosses a wedge every few mm
MERGE_SPAN_M = 0.05


@dataclass(frozen=True, slots=True)
class RayTable:
    """Per base bin j: crossings start[j]:start[j + 1] (wedge k, s_min, s_max, rho of the wedge's
    near and far end along the ray, the ray's t.u, which ray, whether the contract needs it seen),
    and ``never[j]``: some part of the bin's rays is outside the view (never +inf)."""

    start: npt.NDArray[np.int64]
    k: npt.NDArray[np.int64]  # (R,) the entry's lowest wedge
    k_hi: npt.NDArray[np.int64]  # (R,) its highest wedge (k for one crossing)
    s: F64  # (C, 2) s_min, s_max: the sensor range of the crossing's points, metres
    rho: F64  # (C, 2) the crossing's base range interval, metres
    a: F64  # (C,) t . u of the crossing's ray (arc crossings solve |rho u - t| = r)
    centre: npt.NDArray[np.bool_]  # (C,) on the bin's centre ray
    check: npt.NDArray[np.bool_]  # (C,) outside the dead zone: must be seen free for +inf
    run: npt.NDArray[np.bool_]  # (R,) nearer than range_min: only -inf and NaN readings matter
    never: npt.NDArray[np.bool_]  # (N,)
    full: npt.NDArray[np.bool_]  # (M,) the sensor wedge's view reaches range_max
    range_max_m: float  # base range out to which +inf claims free (sensor's range_max - |t|)
    # the sensor's wedges (first centre bearing in the base frame, width) and its foot: where a
    # merged entry's arc crossing lies (which wedge it is in)
    wedges: tuple[float, float] = (0.0, 0.0)
    foot: tuple[float, float] = (0.0, 0.0)
    base: tuple[float, float] = (0.0, 0.0)  # the base bins' first centre bearing and width


@functools.lru_cache(maxsize=32)
def ray_table(
    sensor: tuple[float, float, int],
    base: tuple[float, float, int],
    x_m: float,
    y_m: float,
    yaw_rad: float,
    range_max_m: float,
    intr: Intrinsics,
    level: Mount,
    rows: tuple[int, int, int],
    range_min_m: float = 0.0,
) -> RayTable:
    """The crossings of every base ray with the sensor's wedges (module docstring).

    Args:
        sensor: (angle_min, increment, bins) of the sensor's level scan (its own frame).
        base: (angle_min, increment, bins) of the base scan.
        x_m, y_m, yaw_rad: the sensor's placement.
        range_max_m: the sensor scan's range_max.
        intr, level, rows: the sensor's camera, its mount without placement and the image rows
            the scan read (start, stop, step): what its view sees (coverage.floor_extent).
        range_min_m: the sensor scan's range_min: crossings nearer than it are merged into runs
            (a finite reading is never that near).
    """
    a0s, incs, m = sensor
    b0, inc, n = base
    d = math.hypot(x_m, y_m)
    rmax = max(range_max_m - d, 0.0)
    near, far = floor_extent(intr, level, a0s, incs, m, rows)
    nr = near.astype(np.float64)
    fr = far.astype(np.float64)
    args = (a0s + yaw_rad, incs, m, b0, inc, n, x_m, y_m, rmax, np.array(RAYS), nr, fr)
    never = np.zeros(n, np.bool_)
    # two passes: count, then fill (a ray near the sensor crosses many wedges)
    e = np.empty(0, np.int64)
    c = walk_crossings(
        *args, False, e, np.empty((0, 2)), np.empty((0, 2)), np.empty(0), e, e, never
    )
    k = np.empty(c, np.int64)
    s = np.empty((c, 2))
    rho = np.empty((c, 2))
    a = np.empty(c)
    ray = np.empty(c, np.int64)
    own = np.empty(c, np.int64)
    walk_crossings(*args, True, k, s, rho, a, ray, own, never)
    inside = (k >= 0) & (k < m)
    kk = np.clip(k, 0, m - 1)
    check = inside & (s[:, 1] >= nr[kk])
    keep = inside
    k, s, rho, a, ray, own, check = (x[keep] for x in (k, s, rho, a, ray, own, check))
    # a ray passing the sensor close by crosses hundreds of its wedges nearer than range_min
    # (736,805 crossings at 640x480 for a sensor 0.22 m off the origin: 4 ms a frame); there a
    # wedge's finite reading (>= range_min) is always past the crossing, so only -inf and NaN
    # matter: a run of such wedges is one entry, asked through prefix counts per frame; farther
    # out, runs within MERGE_SPAN_M of sensor range are one entry (module docstring)
    near_rm = s[:, 1] < range_min_m
    lo, k_lo, k_hi = _merge_runs(k, s, near_rm, ray, own, check)
    last = np.r_[lo[1:] - 1, k.size - 1].astype(np.int64) if lo.size else lo
    rho = np.c_[rho[lo, 0], rho[last, 1]] if lo.size else rho
    if lo.size:
        s = np.c_[np.minimum.reduceat(s[:, 0], lo), np.maximum.reduceat(s[:, 1], lo)]
    start = np.zeros(n + 1, np.int64)
    np.add.at(start, own[lo] + 1, 1)
    start = np.cumsum(start)
    return frozen_table(
        RayTable(
            start=start,
            k=k_lo,
            k_hi=k_hi,
            s=s[: lo.size].copy(),
            rho=rho,
            a=a[lo].copy(),
            centre=(ray[lo] == CENTRE).copy(),
            check=check[lo].copy(),
            run=near_rm[lo] & near_rm[last],
            never=never,
            full=fr >= range_max_m,
            range_max_m=rmax,
            wedges=(a0s + yaw_rad, incs),
            foot=(x_m, y_m),
            base=(b0, inc),
        )
    )


def _merge_runs(
    k: npt.NDArray[np.int64],
    s: F64,
    near: npt.NDArray[np.bool_],
    ray: npt.NDArray[np.int64],
    own: npt.NDArray[np.int64],
    check: npt.NDArray[np.bool_],
) -> tuple[npt.NDArray[np.int64], npt.NDArray[np.int64], npt.NDArray[np.int64]]:
    """(C,) crossings in walk order -> the first crossing of each entry (R,), and each entry's
    lowest and highest wedge (R,) each: consecutive crossings of one ray of one bin through
    neighbouring wedges with the same ``check`` make one entry if all are nearer than range_min
    (``near``: only -inf and NaN readings matter there), or none is and their sensor ranges
    span at most MERGE_SPAN_M; the others stay one each."""
    if k.size == 0:
        return (np.zeros(0, np.int64),) * 3
    starts = run_starts(k, s, near, ray, own, check, MERGE_SPAN_M)
    lo = np.flatnonzero(starts)
    return lo, np.minimum.reduceat(k, lo), np.maximum.reduceat(k, lo)
