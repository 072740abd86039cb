"""Compiled parts of ``placement_rays``: the walk of every base ray through the sensor's wedges
(table building, once per mount) and the per-frame kernel that decides each base bin's clear or
unknown and its arc crossings."""

from __future__ import annotations

import numpy as np

from depthnav_daemon.pipeline._jit import helper, kernel


@kernel
def run_starts(k, s, near, ray, own, check, span):
    """_merge_runs' walk: (C,) bool, True where a crossing starts an entry."""
    c = k.shape[0]
    out = np.ones(c, np.bool_)
    first = 0
    for i in range(1, c):
        same = own[i] == own[i - 1] and ray[i] == ray[i - 1] and check[i] == check[i - 1]
        same = same and abs(k[i] - k[i - 1]) == 1 and near[i] == near[i - 1]
        if same and not near[i]:
            same = s[i, 1] - s[first, 0] <= span
        if same:
            out[i] = False
        else:
            first = i
    return out


@kernel
def walk_crossings(
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
def _prefix_counts(ranges, rmin, full):
    """(m + 1,) int64 each: how many of wedges 0..i-1 read -inf, or something that may hide an
    obstacle nearer than ``rmin`` (a finite reading below it, which REP 117 says is -inf, is
    counted with them to be safe), NaN, and NaN where ``full`` (the wedge's view reaches
    range_max: its NaN is this frame's, not the view's; None: never)."""
    m = ranges.shape[0]
    n_close = np.zeros(m + 1, np.int64)
    n_nan = np.zeros(m + 1, np.int64)
    n_nan_full = np.zeros(m + 1, np.int64)
    for i in range(m):
        v = ranges[i]
        n_close[i + 1] = n_close[i] + (1 if v < rmin else 0)
        n_nan[i + 1] = n_nan[i] + (1 if np.isnan(v) else 0)
        n_nan_full[i + 1] = n_nan_full[i] + (
            1 if full is not None and np.isnan(v) and full[i] else 0
        )
    return n_close, n_nan, n_nan_full


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


@helper
def _range_min_table(ranges):
    """(L, m) float32 sparse table of the readings for range minima (NaN read as +inf: the NaN
    counts are separate): row q holds min(ranges[i:i + 2^q])."""
    m = ranges.shape[0]
    levels = 1
    while (1 << levels) <= m:
        levels += 1
    t = np.empty((levels, m), np.float32)
    for i in range(m):
        v = ranges[i]
        t[0, i] = np.float32(np.inf) if np.isnan(v) else v
    for q in range(1, levels):
        h = 1 << (q - 1)
        for i in range(m - (1 << q) + 1):
            t[q, i] = min(t[q - 1, i], t[q - 1, i + h])
    return t


@helper
def _range_min(t, lo, hi):
    """min of the readings lo..hi (inclusive) from ``_range_min_table``."""
    q = 0
    while (2 << q) <= hi - lo + 1:
        q += 1
    return min(t[q, lo], t[q, hi - (1 << q) + 1])


@kernel
def rays_to_base_kernel(
    ranges, start, k, k_hi, run, s, rho, a, centre, check, never, full, d2, rmin, wedges, foot,
    base, out,
):  # fmt: skip
    """Finish the base scan ``out`` (float32, arcs already mapped in with REP 117 values, +inf
    where no arc fed a bin): arc crossings and too-close wedges on the centre ray by min; then a
    bin with nothing finite is +inf where the contract's check passes, else NaN. A ``run`` entry
    (wedges k..k_hi crossed nearer than range_min) asks only whether one of them reads -inf or
    (checked) NaN, through prefix counts; another entry of several wedges asks their least
    reading (a sparse table) against its farthest point, and only where that is not beyond it
    looks at each wedge (its arc crossing, if it lies in the wedge). ``full``: (m,) bool, the
    wedges whose view reaches range_max, whose NaN makes a crossing in the dead zone unknown too
    (None: a cliff scan, whose NaN says nothing there). ``wedges``: (first bearing, width) of the
    sensor's wedges in the base frame; ``foot``: (x, y) of the sensor; ``base``: (first bearing,
    width) of the base bins."""
    inf = np.float32(np.inf)
    n_close, n_nan, n_nan_full = _prefix_counts(ranges, rmin, full)
    rmq = _range_min_table(ranges)
    a0s, incs = wedges
    tx, ty = foot
    b0, inc = base
    m = ranges.shape[0]
    mid = a0s + 0.5 * (m - 1) * incs
    for j in range(out.shape[0]):
        seen = not never[j]
        best = out[j]
        for e in range(start[j], start[j + 1]):
            if run[e]:  # a finite reading (>= range_min) lies past every one of these crossings
                close = n_close[k_hi[e] + 1] - n_close[k[e]] > 0
                nan = n_nan if check[e] else n_nan_full
                if close or nan[k_hi[e] + 1] - nan[k[e]] > 0:
                    seen = False
                if close and centre[e] and s[e, 0] <= rmin:
                    best = -inf
                continue
            if k_hi[e] > k[e]:
                mv = _range_min(rmq, k[e], k_hi[e])
                nan = n_nan if check[e] else n_nan_full
                if nan[k_hi[e] + 1] - nan[k[e]] > 0:
                    seen = False
                if mv > s[e, 1]:
                    continue  # every wedge seen free past the entry (or unknown, above)
                seen = False
                if centre[e]:
                    beta = b0 + j * inc
                    for kk in range(k[e], k_hi[e] + 1):
                        best = _crossing(
                            ranges[kk], kk, s[e, 0], rmin, a[e], d2, rho[e, 0], rho[e, 1], beta,
                            tx, ty, a0s, incs, mid, best,
                        )  # fmt: skip
                continue
            v = ranges[k[e]]
            # checked: seen free past the crossing; in the dead zone: no obstacle seen at or
            # before the crossing's far end (else the ray meets it or runs in its shadow: a
            # wall's end 1.3 m off read +inf on the base bin beside it)
            free = v == inf or (v > s[e, 1] and v < inf)
            unread = full is not None and np.isnan(v) and full[k[e]]  # in the dead zone too
            if not free and (check[e] or v <= s[e, 1] or unread):
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


@helper
def _crossing(v, kk, s_min, rmin, a, d2, rho0, rho1, beta, tx, ty, a0s, incs, mid, best):
    """One wedge kk of a merged entry on the centre ray (bearing beta): -inf if it reads too close
    and the entry starts within range_min; else where the ray meets its arc, if that point lies
    in the wedge; ``best`` otherwise."""
    if v == -np.inf:
        return np.float32(-np.inf) if s_min <= rmin else best
    if not v < np.inf:
        return best
    root = _arc_root(np.float64(v), a, d2, rho0, rho1)
    if not root < np.inf:
        return best
    px = root * np.cos(beta) - tx
    py = root * np.sin(beta) - ty
    psi = np.arctan2(py, px)
    psi = mid + ((psi - mid + np.pi) % (2.0 * np.pi)) - np.pi
    if abs(psi - (a0s + kk * incs)) <= 0.5 * incs + 1e-9:
        return min(best, root)
    return best
