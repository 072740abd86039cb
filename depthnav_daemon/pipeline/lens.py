"""Undoing a lens model: the ideal ray of each distorted pixel coordinate.

Normalised coordinates are x = X/Z, y = Y/Z in the camera frame (RDF). A real lens maps the ideal
(x, y) of a ray to the distorted (xd, yd) its pixel shows, (u, v) = (fx xd + cx, fy yd + cy), by
one of the ROS CameraInfo models of ``drivers.lens_model``: ``plumb_bob`` (radial k1, k2, k3,
tangential p1, p2; k1 < 0 barrel, k1 > 0 pincushion), ``rational_polynomial`` (the same with a
radial denominator k4, k5, k6) or ``equidistant`` (Kannala-Brandt fisheye, k1-k4).

``undistort`` inverts plumb_bob and rational_polynomial by Newton's method per point (a compiled
kernel: a 640x480 grid in a few milliseconds), the fisheye by a bracketed Newton's method on its
one radial equation theta_d(theta) = r_d (vectorised numpy). ``geometry.normalized_coords`` calls
it, and the table builders call that once per camera and mount, so the per-frame cost does not
change. ``Intrinsics`` refuses coefficients that fold back inside the image, so every pixel has
exactly one ray.
"""

from __future__ import annotations

import math

import numpy as np
import numpy.typing as npt

from depthnav_daemon.pipeline._jit import kernel
from drivers.base import EQUIDISTANT, Intrinsics, lens_map, rational_coeffs, theta_d

F64 = npt.NDArray[np.float64]

TOLERANCE = 1e-12  # |distort(x) - xd| at which Newton stops (normalised units; 6e-10 pixels)
MIN_GUESS_FACTOR = 0.25  # a radial factor below this is outside the model's useful range
MAX_ITERATIONS = 50  # Newton needs about 5 within the image; the rest are halved steps
# a fisheye ray must point in front of the camera for a depth along the optical axis to exist
MAX_THETA = math.pi / 2.0 - 1e-9


def distort(x: npt.ArrayLike, y: npt.ArrayLike, intr: Intrinsics) -> tuple[F64, F64]:
    """Distorted normalised coordinates (xd, yd) of ideal ones (x, y) (broadcastable arrays),
    each shaped like ``x + y``; the identity for a pinhole."""
    xa, ya = np.broadcast_arrays(np.asarray(x, np.float64), np.asarray(y, np.float64))
    xd, yd = lens_map(xa, ya, intr.distortion_model, intr.distortion)[:2]
    return np.asarray(xd, np.float64), np.asarray(yd, np.float64)


def undistort(xd: npt.ArrayLike, yd: npt.ArrayLike, intr: Intrinsics) -> tuple[F64, F64]:
    """Ideal normalised coordinates (x, y) whose distortion is (xd, yd) (broadcastable arrays),
    each shaped like ``xd + yd``; converged to 1e-12, NaN where the model cannot be inverted
    (points far outside the image; a fisheye's rays 90 deg or more off axis)."""
    xa, ya = np.broadcast_arrays(np.asarray(xd, np.float64), np.asarray(yd, np.float64))
    shape = xa.shape
    if not intr.has_distortion:
        return xa.astype(np.float64, copy=True), ya.astype(np.float64, copy=True)
    if intr.distortion_model == EQUIDISTANT:
        return _undistort_equidistant(xa, ya, intr.distortion)
    # fresh writable C arrays: the one argument type the kernel is compiled (and warmed) for
    xs = np.array(xa, dtype=np.float64, order="C").reshape(-1)
    ys = np.array(ya, dtype=np.float64, order="C").reshape(-1)
    coeffs = np.array(rational_coeffs(intr.distortion_model, intr.distortion), dtype=np.float64)
    out_x, out_y = _undistort_kernel(xs, ys, coeffs, TOLERANCE, MAX_ITERATIONS)
    return out_x.reshape(shape), out_y.reshape(shape)


def _undistort_equidistant(xd: F64, yd: F64, coeffs: tuple[float, ...]) -> tuple[F64, F64]:
    """The fisheye's inverse: theta with theta_d(theta) = r_d by Newton's method kept inside a
    bracket [lo, hi] that holds the root (a step leaving it is a bisection instead), then
    (x, y) = (xd, yd) tan(theta) / r_d. NaN where no theta below 90 deg reaches r_d."""
    rd = np.hypot(xd, yd)
    lo = np.zeros_like(rd)
    hi = np.full_like(rd, MAX_THETA)
    reachable = theta_d(hi, coeffs)[0] >= rd  # theta_d rises over the image (Intrinsics checks)
    theta = np.minimum(rd, MAX_THETA)  # the ideal equidistant lens's answer
    converged = np.zeros(rd.shape, dtype=bool)
    for _ in range(MAX_ITERATIONS + 30):
        value, slope = theta_d(theta, coeffs)
        err = value - rd
        converged = np.abs(err) <= TOLERANCE
        if converged.all():
            break
        lo = np.where(err < 0, theta, lo)
        hi = np.where(err > 0, theta, hi)
        with np.errstate(divide="ignore", invalid="ignore"):
            step = theta - err / slope
        inside = (step > lo) & (step < hi) & np.isfinite(step)
        theta = np.where(converged, theta, np.where(inside, step, 0.5 * (lo + hi)))
    ok = converged & reachable
    with np.errstate(divide="ignore", invalid="ignore"):
        scale = np.where(rd > 0, np.tan(theta) / np.where(rd > 0, rd, 1.0), 1.0)
    return np.where(ok, xd * scale, np.nan), np.where(ok, yd * scale, np.nan)


@kernel
def _residual(
    x: float, y: float, tx: float, ty: float, c: F64
) -> tuple[float, float]:  # pragma: no cover - compiled
    """rational_polynomial(x, y) - (tx, ty), c = (k1, k2, p1, p2, k3, k4, k5, k6)."""
    k1, k2, p1, p2, k3, k4, k5, k6 = c[0], c[1], c[2], c[3], c[4], c[5], c[6], c[7]
    xx, yy, xy = x * x, y * y, x * y
    r2 = xx + yy
    radial = (1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))) / (1.0 + r2 * (k4 + r2 * (k5 + r2 * k6)))
    return (
        x * radial + 2.0 * p1 * xy + p2 * (r2 + 2.0 * xx) - tx,
        y * radial + p1 * (r2 + 2.0 * yy) + 2.0 * p2 * xy - ty,
    )


@kernel
def _jacobian(x: float, y: float, c: F64) -> tuple[float, float, float]:  # pragma: no cover
    """(dxd/dx, dxd/dy = dyd/dx, dyd/dy) of rational_polynomial at (x, y), c as ``_residual``."""
    k1, k2, p1, p2, k3, k4, k5, k6 = c[0], c[1], c[2], c[3], c[4], c[5], c[6], c[7]
    xx, yy, xy = x * x, y * y, x * y
    r2 = xx + yy
    num = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
    den = 1.0 + r2 * (k4 + r2 * (k5 + r2 * k6))
    radial = num / den
    # dR/d(r2), the quotient rule
    dnum = k1 + r2 * (2.0 * k2 + 3.0 * k3 * r2)
    dden = k4 + r2 * (2.0 * k5 + 3.0 * k6 * r2)
    slope = (dnum * den - num * dden) / (den * den)
    cross = 2.0 * xy * slope + 2.0 * p1 * x + 2.0 * p2 * y
    dxx = radial + 2.0 * xx * slope + 2.0 * p1 * y + 6.0 * p2 * x
    dyy = radial + 2.0 * yy * slope + 6.0 * p1 * y + 2.0 * p2 * x
    return dxx, cross, dyy


@kernel
def _undistort_kernel(
    xd: F64, yd: F64, coeffs: F64, tol: float, max_iter: int
) -> tuple[F64, F64]:  # pragma: no cover - compiled
    """Newton's method on rational_polynomial(x, y) = (xd, yd) per point (plumb_bob: k4..k6 = 0),
    from the radial fixed-point guess (xd, yd) / R(rd); a step that does not reduce the residual
    is halved (at most 30 times)."""
    k1, k2, k3 = coeffs[0], coeffs[1], coeffs[4]
    k4, k5, k6 = coeffs[5], coeffs[6], coeffs[7]
    n = xd.shape[0]
    out_x = np.empty(n)
    out_y = np.empty(n)
    for i in range(n):
        tx, ty = xd[i], yd[i]
        r2 = tx * tx + ty * ty
        guess = (1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))) / (1.0 + r2 * (k4 + r2 * (k5 + r2 * k6)))
        if not guess > MIN_GUESS_FACTOR:  # start from the distorted point instead
            guess = 1.0
        x, y = tx / guess, ty / guess
        ex, ey = _residual(x, y, tx, ty, coeffs)
        err = ex * ex + ey * ey
        converged = False
        for _ in range(max_iter):
            if err <= tol * tol:
                converged = True
                break
            dxx, cross, dyy = _jacobian(x, y, coeffs)
            det = dxx * dyy - cross * cross
            if not (det != 0.0 and np.isfinite(det)):
                break
            sx = (dyy * ex - cross * ey) / det
            sy = (dxx * ey - cross * ex) / det
            # backtrack: a full Newton step can overshoot on a strongly curved model
            t = 1.0
            nx, ny, nex, ney, nerr = x, y, ex, ey, err
            for _ in range(30):
                nx, ny = x - t * sx, y - t * sy
                nex, ney = _residual(nx, ny, tx, ty, coeffs)
                nerr = nex * nex + ney * ney
                if nerr < err:
                    break
                t *= 0.5
            if not nerr < err:
                break  # no step helps: stuck at rounding level or outside the invertible part
            x, y, ex, ey, err = nx, ny, nex, ney, nerr
        if converged or err <= tol * tol:
            out_x[i] = x
            out_y[i] = y
        else:
            out_x[i] = np.nan
            out_y[i] = np.nan
    return out_x, out_y
