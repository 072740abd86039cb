"""What an off-centre sensor saw along each base-frame ray: the base scan's clear (+inf) claims and
the ranges between its arcs (``placement``).

A base bin's ray starts at the base origin, not at the sensor, so it crosses the sensor's bins
(wedges about the sensor's foot) one after another. The bin may say "clear to range_max" only if
every part of that ray is either in the sensor's lower dead zone (nearer than where its image first
meets the floor: the contract's stated exception) or inside a wedge that saw free floor past the
crossing (a +inf bin, or a hit farther than the crossing, within the wedge's view ``far``); a part
outside the view (beside or behind the sensor, or past a wedge's far) makes it unknown (NaN).
The rays at the bin's centre and at both its edges are checked, so a clear bin is clear across its
width. The centre ray also takes the exact range where it crosses a hit's arc (``|rho u - t| = r``
inside the wedge), so a near obstacle seen from the side leaves no hole between the arcs that
``placement`` maps, and a too-close (-inf) wedge it crosses within range_min makes it -inf.

The crossings depend only on the layouts, the placement and the view (a table built once per
mount); per frame the kernel looks each crossing's wedge up.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from depthnav_daemon.pipeline._jit import helper, kernel
from depthnav_daemon.pipeline.coverage import floor_extent
from depthnav_daemon.pipeline.geometry import F64, Mount, frozen_table
from drivers.base import Intrinsics

RAYS = (-0.45, 0.0, 0.45)  # checked rays per base bin, in base bin widths from its centre
CENTRE = 1  # the index of the centre ray in RAYS (the one that takes arc crossings)


@dataclass(frozen=True, slots=True)
class RayTable:
    """Per base bin j: crossings start[j]:start[j + 1] (wedge k, s_min, s_max, rho of the wedge's
    near and far end along the ray, the ray's t.u, which ray, whether the contract needs it seen),
    and ``never[j]``: some part of the bin's rays is outside the view (never +inf)."""

    start: npt.NDArray[np.int64]
    k: npt.NDArray[np.int64]  # (R,) the entry's wedge (its first, for a run)
    k_hi: npt.NDArray[np.int64]  # (R,) its last wedge (k for one crossing)
    s: F64  # (C, 2) s_min, s_max: the sensor range of the crossing's points, metres
    rho: F64  # (C, 2) the crossing's base range interval, metres
    a: F64  # (C,) t . u of the crossing's ray (arc crossings solve |rho u - t| = r)
    centre: npt.NDArray[np.bool_]  # (C,) on the bin's centre ray
    check: npt.NDArray[np.bool_]  # (C,) outside the dead zone: must be seen free for +inf
    run: npt.NDArray[np.bool_]  # (R,) nearer than range_min: only -inf and NaN readings matter
    never: npt.NDArray[np.bool_]  # (N,)
    range_max_m: float  # base range out to which +inf claims free (sensor's range_max - |t|)


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
    c = _crossings(*args, False, e, np.empty((0, 2)), np.empty((0, 2)), np.empty(0), e, e, never)
    k = np.empty(c, np.int64)
    s = np.empty((c, 2))
    rho = np.empty((c, 2))
    a = np.empty(c)
    ray = np.empty(c, np.int64)
    own = np.empty(c, np.int64)
    _crossings(*args, True, k, s, rho, a, ray, own, never)
    inside = (k >= 0) & (k < m)
    kk = np.clip(k, 0, m - 1)
    check = inside & (s[:, 1] >= nr[kk])
    keep = inside
    k, s, rho, a, ray, own, check = (x[keep] for x in (k, s, rho, a, ray, own, check))
    # a ray passing the sensor close by crosses hundreds of its wedges nearer than range_min
    # (736,805 crossings at 640x480 for a sensor 0.22 m off the origin: 4 ms a frame); there a
    # wedge's finite reading (>= range_min) is always past the crossing, so only -inf and NaN
    # matter: a run of such wedges is one entry, asked through prefix counts per frame
    lo, k_lo, k_hi = _merge_near_runs(k, s[:, 1] < range_min_m, ray, own, check)
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
            rho=rho[lo].copy(),
            a=a[lo].copy(),
            centre=(ray[lo] == CENTRE).copy(),
            check=check[lo].copy(),
            run=s[: lo.size, 1] < range_min_m,
            never=never,
            range_max_m=rmax,
        )
    )


def _merge_near_runs(
    k: npt.NDArray[np.int64],
    near: npt.NDArray[np.bool_],
    ray: npt.NDArray[np.int64],
    own: npt.NDArray[np.int64],
    check: npt.NDArray[np.bool_],
) -> tuple[npt.NDArray[np.int64], npt.NDArray[np.int64], npt.NDArray[np.int64]]:
    """(C,) crossings in walk order -> the first crossing of each entry (R,), and each entry's
    lowest and highest wedge (R,) each: consecutive crossings nearer than range_min (``near``)
    of one ray of one bin, through neighbouring wedges with the same ``check``, make one entry;
    the others stay one each."""
    if k.size == 0:
        return (np.zeros(0, np.int64),) * 3
    same = near[1:] & near[:-1] & (own[1:] == own[:-1]) & (ray[1:] == ray[:-1])
    same &= (check[1:] == check[:-1]) & (np.abs(k[1:] - k[:-1]) == 1)
    lo = np.flatnonzero(np.r_[True, ~same])
    return lo, np.minimum.reduceat(k, lo), np.maximum.reduceat(k, lo)


@kernel
def _crossings(
    a0s, incs, m, b0, inc, n, tx, ty, rmax, rays, near, far,
    fill, out_k, out_s, out_rho, out_a, out_ray, owner, never,
):  # fmt: skip
    """Walk every base ray from the origin to rmax through the sensor's wedges (ordered by base
    bin); with ``fill`` write the crossing arrays; set ``never``; returns how many crossings.
    Outside the view a ray's part up to the view's edge is one crossing (wedge index < 0 or
    >= m)."""
    c = 0
    d2 = tx * tx + ty * ty
    mid = a0s + 0.5 * (m - 1) * incs  # wedge bearings are unwrapped next to the view's middle
    near_out = np.inf
    for k in range(m):
        near_out = min(near_out, near[k])
    for j in range(n):
        for r in range(rays.shape[0]):
            beta = b0 + (j + rays[r]) * inc
            ux = np.cos(beta)
            uy = np.sin(beta)
            a = ux * tx + uy * ty
            rho = 0.0
            while rho < rmax:
                # the wedge at rho (a point just past it, so a boundary hit moves on)
                px = (rho + 1e-8) * ux - tx
                py = (rho + 1e-8) * uy - ty
                psi = np.arctan2(py, px)
                psi = mid + ((psi - mid + np.pi) % (2.0 * np.pi)) - np.pi
                k = np.int64(np.floor((psi - a0s) / incs + 0.5))
                outside = k < 0 or k >= m
                nxt = _leave(a0s, incs, m, k, outside, ux, uy, tx, ty, rho, rmax)
                s_min, s_max = _s_span(rho, nxt, a, d2)
                if outside or not near[k] < np.inf:
                    # beside or behind the view: unseen unless within its dead zone's reach
                    if s_max >= near_out:
                        never[j] = True
                elif s_max >= near[k] and far[k] < s_max:
                    never[j] = True  # past what this wedge's view reaches
                if fill:
                    out_k[c] = k
                    out_s[c, 0] = s_min
                    out_s[c, 1] = s_max
                    out_rho[c, 0] = rho
                    out_rho[c, 1] = nxt
                    out_a[c] = a
                    out_ray[c] = r
                    owner[c] = j
                c += 1
                rho = nxt
    return c


@kernel
def _leave(a0s, incs, m, k, outside, ux, uy, tx, ty, rho, rmax):
    """Where the ray (direction (ux, uy) from the origin) leaves wedge k (outside the view: the
    view's edges) beyond rho: the nearer boundary crossing, or rmax."""
    nxt = rmax
    for e in range(2):
        if outside:
            al = a0s - 0.5 * incs if e == 0 else a0s + (m - 0.5) * incs
        else:
            al = a0s + (k - 0.5 + e) * incs
        wx = np.cos(al)
        wy = np.sin(al)
        den = ux * wy - uy * wx
        if den == 0.0:
            continue
        t = (tx * wy - ty * wx) / den
        # on the boundary's forward half (s > 0) and ahead of rho
        if t > rho + 1e-7 and (t * ux - tx) * wx + (t * uy - ty) * wy > 0.0:
            nxt = min(nxt, t)
    return nxt


@kernel
def _s_span(rho0, rho1, a, d2):
    """Smallest and largest sensor range over the ray's part [rho0, rho1] (t.u = a, |t|^2 = d2)."""
    lo_s = np.sqrt(max(rho0 * rho0 - 2.0 * a * rho0 + d2, 0.0))
    hi_s = np.sqrt(max(rho1 * rho1 - 2.0 * a * rho1 + d2, 0.0))
    s_min = min(lo_s, hi_s)
    if rho0 < a < rho1:
        s_min = np.sqrt(max(d2 - a * a, 0.0))
    return s_min, max(lo_s, hi_s)


@helper
def _prefix_counts(ranges, rmin):
    """(m + 1,) int64 each: how many of wedges 0..i-1 read -inf, or something that may hide an
    obstacle nearer than ``rmin`` (a finite reading below it, which REP 117 says is -inf, is
    counted with them to be safe), and NaN."""
    m = ranges.shape[0]
    n_close = np.zeros(m + 1, np.int64)
    n_nan = np.zeros(m + 1, np.int64)
    for i in range(m):
        v = ranges[i]
        n_close[i + 1] = n_close[i] + (1 if v < rmin else 0)
        n_nan[i + 1] = n_nan[i] + (1 if np.isnan(v) else 0)
    return n_close, n_nan


@helper
def _arc_root(v, a, d2, rho0, rho1):
    """Where the ray meets the arc of radius ``v`` about the sensor inside the crossing
    [rho0, rho1]: |rho u - t| = v, rho = a +- sqrt(a^2 - d2 + v^2); +inf where it does not."""
    q = a * a - d2 + v * v
    if q >= 0.0:
        sq = np.sqrt(q)
        for root in (a - sq, a + sq):
            if rho0 - 1e-6 <= root <= rho1 + 1e-6 and root >= 0.0:
                return np.float32(root)
    return np.float32(np.inf)


@kernel
def rays_to_base_kernel(
    ranges, start, k, k_hi, run, s, rho, a, centre, check, never, d2, rmin, out
):  # fmt: skip
    """Finish the base scan ``out`` (float32, arcs already mapped in with REP 117 values, +inf
    where no arc fed a bin): arc crossings and too-close wedges on the centre ray by min; then a
    bin with nothing finite is +inf where the contract's check passes, else NaN. A ``run`` entry
    (wedges k..k_hi crossed nearer than range_min) asks only whether one of them reads -inf or
    (checked) NaN, through prefix counts."""
    inf = np.float32(np.inf)
    n_close, n_nan = _prefix_counts(ranges, rmin)
    for j in range(out.shape[0]):
        seen = not never[j]
        best = out[j]
        for e in range(start[j], start[j + 1]):
            if run[e]:  # a finite reading (>= range_min) lies past every one of these crossings
                close = n_close[k_hi[e] + 1] - n_close[k[e]] > 0
                if close or (check[e] and n_nan[k_hi[e] + 1] - n_nan[k[e]] > 0):
                    seen = False
                if close and centre[e] and s[e, 0] <= rmin:
                    best = -inf
                continue
            v = ranges[k[e]]
            # checked: seen free past the crossing; in the dead zone: no obstacle seen at or
            # before the crossing's far end (else the ray meets it or runs in its shadow: a
            # wall's end 1.3 m off read +inf on the base bin beside it)
            free = v == inf or (v > s[e, 1] and v < inf)
            if not free and (check[e] or v <= s[e, 1]):
                seen = False
            if not centre[e]:
                continue
            if v == -inf:
                if s[e, 0] <= rmin:
                    best = -inf
                continue
            if s[e, 0] <= v <= s[e, 1]:
                best = min(best, _arc_root(np.float64(v), a[e], d2, rho[e, 0], rho[e, 1]))
        if best < inf:
            out[j] = best
        else:
            out[j] = inf if seen else np.float32(np.nan)
