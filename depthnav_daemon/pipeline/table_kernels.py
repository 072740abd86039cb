"""Compiled table builders (once per mount): the exact scan's per-pixel thresholds, bearings and
bin map, and the pose stage's prior envelope.

numpy took 50-70 ms for these at 640x480 (arctan2 and a dozen full-size temporaries); a mount
change rebuilt them on the frame path. The arithmetic is written out operation by operation, in
the order the numpy definitions in scan_table.py and pose_fit.py use, so the tables are bit-for-bit
those of the definitions (tests/pipeline/test_tables.py). The rays come in as (Hs, Ws) arrays of
normalised coordinates from ``geometry.normalized_coords`` (no separability is assumed: a lens
model makes x depend on both u and v).
"""

from __future__ import annotations

import math

import numpy as np

from depthnav_daemon.pipeline._jit import helper, kernel
from depthnav_daemon.pipeline.scan_kernels import flush_codes_kernel

U16_MAX = 65535.0


@helper
def _fmax(a: float, b: float) -> float:
    """np.maximum on scalars (NaN wins)."""
    return a if (a >= b or math.isnan(a)) else b


@helper
def _fmin(a: float, b: float) -> float:
    """np.minimum on scalars (NaN wins)."""
    return a if (a <= b or math.isnan(a)) else b


@helper
def _clip(a: float, lo: float, hi: float) -> float:
    """np.clip on a scalar: minimum(maximum(a, lo), hi)."""
    return _fmin(_fmax(a, lo), hi)


@helper
def _bounds_mm(k: float, lo: float, hi: float) -> tuple[float, float]:
    """Depth interval (mm) where lo <= k * z_m <= hi (scan_table._depth_bounds_mm, one pixel)."""
    a = lo / k * 1000.0
    b = hi / k * 1000.0
    inside = lo <= 0.0 <= hi
    if k > 0:
        return a, b
    if k < 0:
        return b, a
    return (0.0, math.inf) if inside else (math.inf, -math.inf)


@kernel
def exact_table_kernel(
    x,
    y,
    xe,
    ye,
    rot,
    height_m,
    min_h_m,
    max_h_m,
    range_min_m,
    range_max_m,
    zlo_mm,
    zhi_mm,
    near_lo_mm,
    near_hi_mm,
    k_lo,
    k_mid,
    k_hi,
    kr32,
    centre,
    lo_b,
    hi_b,
    sane,
):
    """The exact scan's per-pixel tables (scan_table.exact_table, the numpy definition).

    Args:
        x, y: (Hs, Ws) float64 normalised coordinates of the used pixels' centres.
        xe, ye: (Hs, Ws + 1) float64 normalised coordinates of their footprint edges (pixel j
            spans edges j and j + 1).
        rot: (3, 3) camera to level frame.
        height_m, min_h_m, max_h_m, range_min_m, range_max_m: the mount and the scan's limits.
        zlo_mm .. k_hi: (Hs, Ws) uint16, overwritten (ExactTable's fields of the same names).
        kr32: (Hs, Ws) float32, overwritten: horizontal range per mm of depth.
        centre, lo_b, hi_b: (Hs, Ws) float64, overwritten: bearings of the centre and of the
            footprint's lower and upper edge, radians.
        sane: (Hs, Ws) bool, overwritten: the footprint does not straddle the +-pi seam.

    Returns:
        (edge_min, edge_max, used): lowest and highest edge bearing of the sane pixels, and
        their number (0: the two bounds are meaningless).
    """
    hs, ws = x.shape
    r00, r01, r02 = rot[0, 0], rot[0, 1], rot[0, 2]
    r10, r11, r12 = rot[1, 0], rot[1, 1], rot[1, 2]
    r20, r21, r22 = rot[2, 0], rot[2, 1], rot[2, 2]
    lo_h = min_h_m - height_m
    hi_h = max_h_m - height_m
    edge = np.empty(ws + 1, np.float64)
    edge_min = math.inf
    edge_max = -math.inf
    used = 0
    for i in range(hs):
        for j in range(ws + 1):
            fx = r00 * xe[i, j] + r01 * ye[i, j] + r02
            fy = r10 * xe[i, j] + r11 * ye[i, j] + r12
            edge[j] = math.atan2(fy, fx)
        for j in range(ws):
            xi = x[i, j]
            yi = y[i, j]
            fwd = r00 * xi + r01 * yi + r02
            left = r10 * xi + r11 * yi + r12
            kh = r20 * xi + r21 * yi + r22
            kr = math.hypot(fwd, left)
            hlo, hhi = _bounds_mm(kh, lo_h, hi_h)
            rlo, rhi = _bounds_mm(kr, range_min_m, range_max_m)
            zlo = _fmax(_fmax(hlo, rlo), 1.0)
            zhi = _fmin(hhi, rhi)
            a = np.uint16(_clip(np.ceil(zlo), 1.0, U16_MAX))
            b = np.uint16(_clip(np.floor(zhi), 0.0, U16_MAX))
            nl = np.uint16(_clip(np.ceil(_fmax(hlo, 1.0)), 1.0, U16_MAX))
            nh = np.uint16(_clip(np.ceil(_fmin(hhi, rlo)) - 1.0, 0.0, U16_MAX))
            zlo_mm[i, j] = a
            zhi_mm[i, j] = b
            near_lo_mm[i, j] = nl
            near_hi_mm[i, j] = nh
            # see exact_table: close iff k_lo <= d <= k_mid, obstacle iff k_mid < d <= k_hi
            near = nl <= nh
            k_lo[i, j] = nl if near else a
            k_mid[i, j] = nh if near else np.uint16(a - np.uint16(1))
            k_hi[i, j] = b if a <= b else np.uint16(0)
            kr32[i, j] = np.float32(kr / 1000.0)
            centre[i, j] = math.atan2(left, fwd)
            el = edge[j]
            er = edge[j + 1]
            lo = _fmin(el, er)
            hi = _fmax(el, er)
            lo_b[i, j] = lo
            hi_b[i, j] = hi
            ok = (hi - lo) < math.pi
            sane[i, j] = ok
            if ok:
                used += 1
                edge_min = min(edge_min, lo)
                edge_max = max(edge_max, hi)
    return edge_min, edge_max, used


@kernel
def pose_envelope_kernel(rx, ry, rz, rows_kz, lo_kz, hi_kz):
    """Lowest and highest metres down per metre of depth of every ray over a grid of rotations.

    Args:
        rx, ry, rz: (Hs, Ws) float32-valued camera ray components (float64 arrays: the pose
            table's rays before its float32 copy).
        rows_kz: (K, 3) float64: the level frame's z row of every rotation of the prior grid.
        lo_kz, hi_kz: (Hs, Ws) float64, overwritten: min and max over the grid of
            -(rays . rows_kz[k]).
    """
    hs, ws = rx.shape
    for i in range(hs):
        for j in range(ws):
            lo_kz[i, j] = math.inf
            hi_kz[i, j] = -math.inf
    for k in range(rows_kz.shape[0]):
        a = rows_kz[k, 0]
        b = rows_kz[k, 1]
        c = rows_kz[k, 2]
        for i in range(hs):
            for j in range(ws):
                down = -(rx[i, j] * a + ry[i, j] * b + rz[i, j] * c)
                lo_kz[i, j] = _fmin(lo_kz[i, j], down)
                hi_kz[i, j] = _fmax(hi_kz[i, j], down)


CHUNK_PX = 1 << 14  # pixels of scratch (bearings, bin map) of one chunk of rows: ~0.7 MB


@kernel
def exact_codes_kernel(x, y, xe, ye, rot, limits, u16, kr32, inc, max_bins):
    """exact_table_kernel, then the bin map and the run flush codes, in one call, chunk by chunk
    of rows: the per-pixel bearings and bin maps in between are made for CHUNK_PX pixels at a
    time (they were ~40 MB of float64 and int64 at 1280x720, 57 B a pixel: the tables' memory
    budget, scan_table.TABLE_BUDGET_B_PER_PX), and all scratch is freed in here, without the
    interpreter lock. Freed by numpy on the table worker, it held it 1-2 ms an array (the pages
    going back to the system): the frame loop waited as long. A first pass over the edges finds
    the bins (their extent needs every row); each row's tables are then those of
    exact_table_kernel and bin_map_kernel on the whole image, bit for bit (rows are independent).

    Args:
        x, y, xe, ye, rot: as exact_table_kernel (any layout: broadcast or strided views).
        limits: (5,) float64 height_m, min_h_m, max_h_m, range_min_m, range_max_m.
        u16: (7, Hs, Ws) uint16, overwritten: zlo_mm, zhi_mm, near_lo_mm, near_hi_mm, k_lo,
            k_mid, k_hi (exact_table_kernel's tables).
        kr32: (Hs, Ws) float32, overwritten: horizontal range per mm of depth.
        inc: bin width, radians.
        max_bins: the most bins accepted (at most 32767: the bin map is kept as int16).

    Returns:
        (used, n, angle_min, fl_start, fl_code): sane pixels (0: no bins, nothing else made),
        bins (> max_bins: refused, no tables or codes made), the first bin's centre, and the run
        flush codes (scan_kernels.run_flush_codes) of the bin map.
    """
    hs, ws = x.shape
    r00, r01, r02 = rot[0, 0], rot[0, 1], rot[0, 2]
    r10, r11, r12 = rot[1, 0], rot[1, 1], rot[1, 2]
    edge = np.empty(ws + 1, np.float64)
    edge_min = math.inf
    edge_max = -math.inf
    used = 0
    for i in range(hs):  # exact_table_kernel's edge bearings, sanity and extent
        for j in range(ws + 1):
            fx = r00 * xe[i, j] + r01 * ye[i, j] + r02
            fy = r10 * xe[i, j] + r11 * ye[i, j] + r12
            edge[j] = math.atan2(fy, fx)
        for j in range(ws):
            lo = _fmin(edge[j], edge[j + 1])
            hi = _fmax(edge[j], edge[j + 1])
            if (hi - lo) < math.pi:
                used += 1
                edge_min = min(edge_min, lo)
                edge_max = max(edge_max, hi)
    none = np.zeros(0, np.int32)
    if used == 0:
        return used, 0, 0.0, none, none
    n = max(1, math.ceil((edge_max - edge_min) / inc))
    if n > max_bins:
        return used, n, 0.0, none, none
    angle_min = edge_min + inc / 2.0
    step = max(1, CHUNK_PX // max(ws, n))
    centre = np.empty((step, ws))
    lo_b = np.empty((step, ws))
    hi_b = np.empty((step, ws))
    sane = np.empty((step, ws), np.bool_)
    g_lo = np.empty((step, n), np.int64)
    g_hi = np.empty((step, n), np.int64)
    cb_lo = np.empty((hs, ws), np.int16)  # bins and n fit: n <= max_bins
    cb_hi = np.empty((hs, ws), np.int16)
    for r0 in range(0, hs, step):
        r1 = min(hs, r0 + step)
        m = r1 - r0
        exact_table_kernel(
            x[r0:r1], y[r0:r1], xe[r0:r1], ye[r0:r1], rot,
            limits[0], limits[1], limits[2], limits[3], limits[4],
            u16[0, r0:r1], u16[1, r0:r1], u16[2, r0:r1], u16[3, r0:r1], u16[4, r0:r1],
            u16[5, r0:r1], u16[6, r0:r1], kr32[r0:r1], centre[:m], lo_b[:m], hi_b[:m], sane[:m],
        )  # fmt: skip
        bin_map_kernel(
            centre[:m], lo_b[:m], hi_b[:m], sane[:m], angle_min, inc, g_lo[:m], g_hi[:m],
            cb_lo[r0:r1], cb_hi[r0:r1],
        )  # fmt: skip
    fl_start, fl_code = flush_codes_kernel(cb_lo, cb_hi, n, 0)
    return used, n, angle_min, fl_start, fl_code


@kernel
def reach_limits_kernel(probe, x, y, rot, height_m, reach_m):
    """scan_table.reach_limits with each floor range made where it is asked (no (Hs, Ws) array
    of them): per run (column, first row, last row) its last row, from the first on, whose floor
    point lies at or beyond ``reach_m``; first - 1 where even the first row's lies nearer.

    The floor range is scan_table's numpy definition operation by operation (level ray
    v = rot (x, y, 1); t = height / -v_z where v_z < 0; range t * hypot(v_x, v_y), +inf at or
    above the horizon), so the answer is the definition's bit for bit.

    Args:
        probe: (3, P) int16 column, first and last row (kernel rows) of each run.
        x, y: (Hs, Ws) float64 normalised coordinates of the used pixels.
        rot: (3, 3) camera to level frame.

    Returns:
        (P,) int16.
    """
    p = probe.shape[1]
    out = np.empty(p, np.int16)
    for k in range(p):
        c = np.int64(probe[0, k])
        r0 = np.int64(probe[1, k])
        r1 = np.int64(probe[2, k])
        lim = r0 - 1
        for r in range(r0, r1 + 1):
            xi = x[r, c]
            yi = y[r, c]
            fwd = rot[0, 0] * xi + rot[0, 1] * yi + rot[0, 2]
            left = rot[1, 0] * xi + rot[1, 1] * yi + rot[1, 2]
            up = rot[2, 0] * xi + rot[2, 1] * yi + rot[2, 2]
            rng = math.inf
            if up < 0:
                t = height_m / -up
                if math.isfinite(t):
                    rng = t * math.hypot(fwd, left)
            if not rng >= reach_m:
                break
            lim = r
        out[k] = np.int16(lim)
    return out


@kernel
def bin_map_kernel(centre, lo_b, hi_b, sane, angle_min, inc, g_lo, g_hi, cb_lo, cb_hi):
    """The exact scan's bin map (once per mount; see scan_table._bin_map).

    Args:
        centre, lo_b, hi_b: (Hs, Ws) float64 bearing of each pixel's centre and footprint edges.
        sane: (Hs, Ws) bool pixels to use.
        angle_min, inc: bin b is centred on angle_min + b * inc.
        g_lo, g_hi: (Hs, n) int64, overwritten: first and last column feeding each bin (Ws, -1:
            none).
        cb_lo, cb_hi: (Hs, Ws) int64, overwritten: first and last bin a column feeds (n, -1: none).
    """
    hs, ws = centre.shape
    n = g_lo.shape[1]
    cols = np.empty(ws, np.int64)
    lo_r = np.empty(ws, np.float64)
    hi_r = np.empty(ws, np.float64)
    for i in range(hs):
        for b in range(n):
            g_lo[i, b] = ws
            g_hi[i, b] = -1
        for j in range(ws):
            cb_lo[i, j] = n
            cb_hi[i, j] = -1
        for j in range(ws):
            if sane[i, j]:
                b = min(max(np.int64(np.floor((centre[i, j] - angle_min) / inc + 0.5)), 0), n - 1)
                g_lo[i, b] = min(g_lo[i, b], j)
                g_hi[i, b] = max(g_hi[i, b], j)
                cb_lo[i, j] = b
                cb_hi[i, j] = b
        m = 0
        for j in range(ws - 1, -1, -1):  # bearings fall with the column: rising order
            if sane[i, j]:
                cols[m] = j
                lo_r[m] = lo_b[i, j]
                hi_r[m] = hi_b[i, j]
                m += 1
        if m == 0:
            continue
        # bins without a pixel centre in this row: the pixel whose footprint covers the bin centre
        for b in range(n):
            if g_hi[i, b] >= 0:
                continue
            c_b = angle_min + inc * b
            lo_k = 0  # searchsorted(lo_r[:m], c_b, side="right")
            hi_k = m
            while lo_k < hi_k:
                mid = (lo_k + hi_k) // 2
                if lo_r[mid] <= c_b:
                    lo_k = mid + 1
                else:
                    hi_k = mid
            k = lo_k - 1
            kk = min(max(k, 0), m - 1)
            if k >= 0 and c_b <= hi_r[kk]:
                c = cols[kk]
                g_lo[i, b] = c
                g_hi[i, b] = c
                cb_lo[i, c] = min(cb_lo[i, c], b)
                cb_hi[i, c] = max(cb_hi[i, c], b)
