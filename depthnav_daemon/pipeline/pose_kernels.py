"""Compiled kernels of the pose stage (floor candidates, RANSAC scoring, refinement sums).

Everything random is drawn by the caller from its numpy Generator; these kernels are
deterministic functions of their inputs.
"""

from __future__ import annotations

import math

import numpy as np

from depthnav_daemon.pipeline._jit import kernel

DEGENERATE_NORM = 1e-9  # a plane normal shorter than this: the three points are collinear


@kernel
def count_candidates_kernel(depth, row0, row_step, col0, col_step, zlo, zhi):
    """Eq. 9-11: how many grid pixels have a depth inside their floor envelope.

    Args:
        depth: (H, W) uint16 mm.
        row0, row_step, col0, col_step: grid pixel (i, j) is depth[row0 + i * row_step, col0 + j *
            col_step].
        zlo, zhi: (Hs, Ws) uint16: a candidate iff zlo <= d <= zhi.

    Returns:
        The number of candidates.
    """
    hs, ws = zlo.shape
    n = 0
    for i in range(hs):
        drow = depth[row0 + i * row_step]
        lo = zlo[i]
        hi = zhi[i]
        for j in range(ws):
            d = drow[col0 + j * col_step]
            n += (lo[j] <= d) & (d <= hi[j])
    return n


@kernel
def candidates_kernel(depth, row0, row_step, col0, col_step, zlo, zhi, rays, keep, colbuf, out):
    """Eq. 12: back-project the candidates whose rank (row-major grid order) is listed in ``keep``.

    Args:
        depth, row0, row_step, col0, col_step, zlo, zhi: as ``count_candidates_kernel``.
        rays: (Hs, Ws, 3) float32 camera ray per metre of depth.
        keep: (M + 1,) intp increasing candidate ranks to emit, then a sentinel -1.
        colbuf: (Ws + 1,) intp work space.
        out: (M, 3) float32 points, metres.

    Returns:
        The number of points written (M).
    """
    hs, ws = zlo.shape
    n_keep = keep.shape[0] - 1
    mm_to_m = np.float32(0.001)
    base = 0  # rank of the row's first candidate
    m = 0
    for i in range(hs):
        if m >= n_keep:
            break
        drow = depth[row0 + i * row_step]
        lo = zlo[i]
        hi = zhi[i]
        # branch-free compaction of the row's candidate columns (floor / not floor is too random
        # for the branch predictor): always store, advance only on a candidate
        c = 0
        for j in range(ws):
            d = drow[col0 + j * col_step]
            colbuf[c] = j
            c += (lo[j] <= d) & (d <= hi[j])
        while m < n_keep and keep[m] < base + c:
            j = colbuf[keep[m] - base]
            z = np.float32(drow[col0 + j * col_step]) * mm_to_m
            out[m, 0] = rays[i, j, 0] * z
            out[m, 1] = rays[i, j, 1] * z
            out[m, 2] = rays[i, j, 2] * z
            m += 1
        base += c
    return m


@kernel
def hypotheses_kernel(pts, idx, accept, use_accept, normals, offsets, good):
    """Planes through point triples, oriented with the origin above them, checked against a prior.

    Args:
        pts: (K, 3) float32 points, metres.
        idx: (I, 3) int64 indices of each hypothesis' three points (drawn by the caller).
        accept: (3, 2) float64 [[tilt_lo, tilt_hi], [|roll| hi, unused], [h_lo, h_hi]] (radians,
            metres).
        use_accept: check the prior at all.
        normals: (I, 3) float64 unit normals, overwritten; offsets: (I,) float64: n.p + d = 0.
        good: (I,) bool, overwritten: a proper plane (non-degenerate triple) inside the prior.
    """
    for h in range(idx.shape[0]):
        i0 = idx[h, 0]
        i1 = idx[h, 1]
        i2 = idx[h, 2]
        x0 = np.float64(pts[i0, 0])
        y0 = np.float64(pts[i0, 1])
        z0 = np.float64(pts[i0, 2])
        ax = np.float64(pts[i1, 0]) - x0
        ay = np.float64(pts[i1, 1]) - y0
        az = np.float64(pts[i1, 2]) - z0
        bx = np.float64(pts[i2, 0]) - x0
        by = np.float64(pts[i2, 1]) - y0
        bz = np.float64(pts[i2, 2]) - z0
        nx = ay * bz - az * by
        ny = az * bx - ax * bz
        nz = ax * by - ay * bx
        norm = math.sqrt(nx * nx + ny * ny + nz * nz)
        ok = norm > DEGENERATE_NORM
        if ok:
            nx /= norm
            ny /= norm
            nz /= norm
        d = -(nx * x0 + ny * y0 + nz * z0)
        if d < 0:  # orient: the origin above the plane
            nx, ny, nz, d = -nx, -ny, -nz, -d
        if use_accept:
            tilt = math.atan2(-nz, math.hypot(nx, ny))
            roll = math.atan2(-nx, -ny)
            ok &= (tilt >= accept[0, 0]) & (tilt <= accept[0, 1]) & (abs(roll) <= accept[1, 0])
            ok &= (d >= accept[2, 0]) & (d <= accept[2, 1])
        normals[h, 0] = nx
        normals[h, 1] = ny
        normals[h, 2] = nz
        offsets[h] = d
        good[h] = ok


@kernel
def ransac_count_kernel(
    px, py, pz, normals, offsets, order, inlier_dist, confidence, chunk, counts
):
    """Inlier counts of plane hypotheses, with PCL's adaptive stop.

    Hypotheses are scored in ``order``, ``chunk`` at a time; after each chunk, with w the best
    inlier share so far, scoring stops once log(1 - confidence) / log(1 - w^3) hypotheses have been
    scored (an all-inlier sample was then drawn with probability ``confidence``). confidence >= 1
    scores them all.

    Args:
        px, py, pz: (K,) float32 point coordinates, metres.
        normals: (I, 3) float32 unit normals; offsets: (I,) float32; plane n.p + d = 0.
        order: (C,) intp hypotheses to score, in order.
        inlier_dist: float32 inlier distance, metres.
        confidence: float64 stop probability.
        chunk: hypotheses per stop check.
        counts: (I,) int64, written for the scored hypotheses.

    Returns:
        How many of ``order`` were scored.
    """
    k_pts = px.shape[0]
    n_cand = order.shape[0]
    need = n_cand
    log_fail = math.log(1.0 - confidence) if confidence < 1.0 else -math.inf
    best = 0
    s = 0
    while s < min(n_cand, need):
        e = min(s + chunk, n_cand)
        for q in range(s, e):
            h = order[q]
            a = normals[h, 0]
            b = normals[h, 1]
            c = normals[h, 2]
            dd = offsets[h]
            cnt = np.int32(0)
            for j in range(
                k_pts
            ):  # the same float32 operations, in the same order, as numpy would do
                dist = abs(px[j] * a + py[j] * b + pz[j] * c + dd)
                cnt += np.int32(dist <= inlier_dist)
            counts[h] = cnt
            best = max(best, cnt)
        s = e
        if confidence >= 1.0:
            continue
        w = best / k_pts
        if 0.0 < w < 1.0:
            need = min(need, math.ceil(log_fail / math.log(1.0 - math.pow(w, 3.0))))
        elif w >= 1.0:
            need = 0
    return s


@kernel
def plane_moments_kernel(pts, normal, offset, inlier_dist, mean, scatter):
    """Mean and scatter matrix of the points within ``inlier_dist`` of a plane (float64 sums).

    Args:
        pts: (K, 3) float32 points, metres.
        normal: (3,) float64, offset: float64: plane n.p + d = 0.
        inlier_dist: float64 metres.
        mean: (3,) float64, overwritten with the inliers' centroid.
        scatter: (3, 3) float64, overwritten with sum (p - mean)(p - mean)^T over the inliers.

    Returns:
        (inliers, sum of the inliers' squared distances to the plane in metres^2).
    """
    k_pts = pts.shape[0]
    for r in range(3):
        mean[r] = 0.0
        for c in range(3):
            scatter[r, c] = 0.0
    if k_pts == 0:
        return 0, 0.0
    # one branch-free pass of sums about a reference point (the first point): the moments about
    # the centroid follow without the cancellation of raw sums at metres from the origin
    rx = np.float64(pts[0, 0])
    ry = np.float64(pts[0, 1])
    rz = np.float64(pts[0, 2])
    n = 0.0
    sx = sy = sz = xx = xy = xz = yy = yz = zz = ssd = 0.0
    for j in range(k_pts):
        x = np.float64(pts[j, 0])
        y = np.float64(pts[j, 1])
        z = np.float64(pts[j, 2])
        dist = x * normal[0] + y * normal[1] + z * normal[2] + offset
        w = 1.0 if abs(dist) <= inlier_dist else 0.0
        qx = x - rx
        qy = y - ry
        qz = z - rz
        n += w
        ssd += w * dist * dist
        sx += w * qx
        sy += w * qy
        sz += w * qz
        xx += w * qx * qx
        xy += w * qx * qy
        xz += w * qx * qz
        yy += w * qy * qy
        yz += w * qy * qz
        zz += w * qz * qz
    if n == 0.0:
        return 0, 0.0
    mx = sx / n
    my = sy / n
    mz = sz / n
    mean[0] = rx + mx
    mean[1] = ry + my
    mean[2] = rz + mz
    scatter[0, 0] = xx - n * mx * mx
    scatter[0, 1] = scatter[1, 0] = xy - n * mx * my
    scatter[0, 2] = scatter[2, 0] = xz - n * mx * mz
    scatter[1, 1] = yy - n * my * my
    scatter[1, 2] = scatter[2, 1] = yz - n * my * mz
    scatter[2, 2] = zz - n * mz * mz
    return int(n), ssd
