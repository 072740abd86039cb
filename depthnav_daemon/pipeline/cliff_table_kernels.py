"""Compiled table builder of the exact cliff stage's edge search: per pixel of the used rows, its
drop-off and obstacle bounds, floor point and bins (called by cliff_table.py once per camera,
mount, parameters and layout; the search itself is cliff_kernels.edges)."""

from __future__ import annotations

import math

import numpy as np

from depthnav_daemon.pipeline._jit import inlined, kernel

_TAN_PI_8 = 0.41421356237309503
# atan(z) = z - z^3 / 3 + z^5 / 5 - ...: through z^21, |z| <= tan(pi / 8): error < 5e-10 rad
_ATAN_TERMS = tuple((-1.0) ** k / (2 * k + 1) for k in range(11))


@inlined
def band_mm(h, m, nk, per_m, never):
    """The drop-off and standing bounds (mm, as floats) of a ray meeting the floor ``per_m``
    metres of depth per metre of height below the camera (h m high): a reading beyond the first
    lies below the floor by more than the margin m and nk t^2 (nk: sigmas x the noise's k), one
    short of the second above it; clipped to [0, never]."""
    t = h * per_m
    lo = max((h + m) * per_m, t + nk * t * t)
    up = max(min((h - m) * per_m, t - nk * t * t), 0.0)
    # integer readings: d > lo <=> d > floor(lo); d < up <=> d < ceil(up)
    return (
        min(max(math.floor(lo * 1000.0), 0.0), never),
        min(max(math.ceil(up * 1000.0), 0.0), never),
    )


@kernel
def band_mm_kernel(per_m, h, m, nk, never, lo, up):
    """``band_mm`` of every ray (N,) float64 into lo, up (N,) uint16 (the cliff table's reach
    samples past range_max, which the pixel tables leave at ``never``)."""
    for i in range(per_m.shape[0]):
        a, b = band_mm(h, m, nk, per_m[i], never)
        lo[i] = np.uint16(a)
        up[i] = np.uint16(b)


@inlined
def _bearing(y, x):
    """atan2(y, x) within 5e-10 rad, radians: octant reduction, then atan's series on
    |z| <= tan(pi / 8) (~3x faster than libm's atan2, which took half the table's time)."""
    ax = abs(x)
    ay = abs(y)
    if ax == 0.0 and ay == 0.0:
        return 0.0
    swap = ay > ax
    t = ax / ay if swap else ay / ax  # [0, 1]
    base = 0.0
    if t > _TAN_PI_8:  # atan(t) = pi / 4 + atan((t - 1) / (t + 1))
        t = (t - 1.0) / (t + 1.0)
        base = math.pi / 4
    z2 = t * t
    p = _ATAN_TERMS[10]
    for k in range(9, -1, -1):
        p = p * z2 + _ATAN_TERMS[k]
    a = base + t * p
    if swap:
        a = math.pi / 2 - a
    if x < 0.0:
        a = math.pi - a
    return -a if y < 0.0 else a


@kernel
def edge_table_kernel(x, y, xe, ye, rot, limits, max_span, band, xyt, bins):
    """The edge search's per-pixel tables (cliff_table.CliffTable) in one pass, for rows row0..H-1.

    Args:
        x, y: (Hu, W) float64 normalised coordinates of the pixel centres.
        xe, ye: (Hu, W + 1) float64 of the pixel edges (pixel u spans edges u and u + 1).
        rot: (3, 3) float64 camera to level frame.
        limits: (9,) float64: height, ground margin, noise sigmas times k, range_min, range_max
            (metres), angle_min, angle increment (radians), bins, NEVER (the "never" bound).
        max_span: most bins one pixel covers.
        band, xyt, bins: overwritten, as CliffTable.px_band_mm, px_xyt_m, px_bins: a reading
            beyond band[0] (mm) lies below the floor by more than the margin and the noise, one
            short of band[1] above it; both NEVER where the pixel's floor point is out of the
            range limits or it has none. Bins: those its footprint's bearings overlap (cliff_table's
            ``_sample_bins`` rule), first > last for none.
    """
    h, m, nk, rmin, rmax, a0, inc, nb, never = limits
    n = np.int64(nb)
    hu, w = x.shape
    nan = np.float32(np.nan)
    bear = np.empty(w + 1)  # the row's edge bearings
    for v in range(hu):
        for u in range(w + 1):
            ex = rot[0, 0] * xe[v, u] + rot[0, 1] * ye[v, u] + rot[0, 2]
            ey = rot[1, 0] * xe[v, u] + rot[1, 1] * ye[v, u] + rot[1, 2]
            bear[u] = _bearing(ey, ex)
        for u in range(w):
            kx = rot[0, 0] * x[v, u] + rot[0, 1] * y[v, u] + rot[0, 2]
            ky = rot[1, 0] * x[v, u] + rot[1, 1] * y[v, u] + rot[1, 2]
            kz = rot[2, 0] * x[v, u] + rot[2, 1] * y[v, u] + rot[2, 2]
            lo_mm = never
            up_mm = never
            if kz < 0:
                per_m = -1.0 / kz  # floor depth per metre of height
                t = h * per_m  # the floor's depth along the ray
                fx = t * kx
                fy = t * ky
                xyt[v, u, 0] = np.float32(fx)
                xyt[v, u, 1] = np.float32(fy)
                xyt[v, u, 2] = np.float32(t)
                r = math.sqrt(fx * fx + fy * fy)  # a grazing ray's overflows to +inf: out of range
                if rmin <= r <= rmax:
                    lo_mm, up_mm = band_mm(h, m, nk, per_m, never)
            else:
                xyt[v, u, 0] = nan
                xyt[v, u, 1] = nan
                xyt[v, u, 2] = nan
            band[0, v, u] = np.uint16(lo_mm)
            band[1, v, u] = np.uint16(up_mm)
            b0 = min(bear[u], bear[u + 1])
            b1 = max(bear[u], bear[u + 1])
            first = 1
            last = 0
            if b1 - b0 < math.pi:  # a footprint across the +-pi seam feeds no bin
                f = math.floor((b0 - a0) / inc + 0.5)
                g = math.floor((b1 - a0) / inc + 0.5)
                if g >= 0 and f <= n - 1:
                    fc = min(max(f, 0.0), n - 1.0)
                    first = np.int64(fc)
                    last = np.int64(min(max(min(g, fc + max_span - 1.0), 0.0), n - 1.0))
            bins[0, v, u] = first
            bins[1, v, u] = last
