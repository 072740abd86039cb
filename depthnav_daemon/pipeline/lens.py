"""The plumb-bob (Brown-Conrady) lens model: distorting ideal rays and undoing it.

Normalised coordinates are x = X/Z, y = Y/Z in the camera frame (RDF). A real lens maps the ideal
(x, y) of a ray to the distorted (xd, yd) its pixel shows, (u, v) = (fx xd + cx, fy yd + cy), by
OpenCV's and ROS CameraInfo's ``plumb_bob`` formula (``drivers.base.plumb_bob``): radial k1, k2, k3
(k1 < 0 barrel: the image edges are pulled in; k1 > 0 pincushion), tangential p1, p2.

``undistort`` inverts it by Newton's method per point (a compiled kernel: a 640x480 grid in a few
milliseconds). ``geometry.normalized_coords`` calls it, and the table builders call that once per
camera and mount, so the per-frame cost does not change. ``Intrinsics`` refuses coefficients that
fold back inside the image, so every pixel has exactly one ray.
"""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

from depthnav_daemon.pipeline._jit import kernel
from drivers.base import Intrinsics, plumb_bob

F64 = npt.NDArray[np.float64]

TOLERANCE = 1e-12  # |distort(x) - xd| at which Newton stops (normalised units; 6e-10 pixels)
MIN_GUESS_FACTOR = 0.25  # a radial factor below this is outside the model's useful range
MAX_ITERATIONS = 50  # Newton needs about 5 within the image; the rest are halved steps


def distort(x: npt.ArrayLike, y: npt.ArrayLike, intr: Intrinsics) -> tuple[F64, F64]:
    """Distorted normalised coordinates (xd, yd) of ideal ones (x, y) (broadcastable arrays),
    each shaped like ``x + y``; the identity for a pinhole."""
    xa, ya = np.broadcast_arrays(np.asarray(x, np.float64), np.asarray(y, np.float64))
    xd, yd = plumb_bob(xa, ya, intr.distortion)[:2]
    return np.asarray(xd, np.float64), np.asarray(yd, np.float64)


def undistort(xd: npt.ArrayLike, yd: npt.ArrayLike, intr: Intrinsics) -> tuple[F64, F64]:
    """Ideal normalised coordinates (x, y) whose distortion is (xd, yd) (broadcastable arrays),
    each shaped like ``xd + yd``; converged to 1e-12, NaN where Newton's method does not converge
    (points far outside the image, beyond where the model is invertible)."""
    xa, ya = np.broadcast_arrays(np.asarray(xd, np.float64), np.asarray(yd, np.float64))
    shape = xa.shape
    if not intr.has_distortion:
        return xa.astype(np.float64, copy=True), ya.astype(np.float64, copy=True)
    # fresh writable C arrays: the one argument type the kernel is compiled (and warmed) for
    xs = np.array(xa, dtype=np.float64, order="C").reshape(-1)
    ys = np.array(ya, dtype=np.float64, order="C").reshape(-1)
    coeffs = np.array(intr.distortion, dtype=np.float64)
    out_x, out_y = _undistort_kernel(xs, ys, coeffs, TOLERANCE, MAX_ITERATIONS)
    return out_x.reshape(shape), out_y.reshape(shape)


@kernel
def _residual(
    x: float, y: float, tx: float, ty: float, k1: float, k2: float, p1: float, p2: float, k3: float
) -> tuple[float, float]:  # pragma: no cover - compiled
    """plumb_bob(x, y) - (tx, ty)."""
    xx, yy, xy = x * x, y * y, x * y
    r2 = xx + yy
    radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
    return (
        x * radial + 2.0 * p1 * xy + p2 * (r2 + 2.0 * xx) - tx,
        y * radial + p1 * (r2 + 2.0 * yy) + 2.0 * p2 * xy - ty,
    )


@kernel
def _undistort_kernel(
    xd: F64, yd: F64, coeffs: F64, tol: float, max_iter: int
) -> tuple[F64, F64]:  # pragma: no cover - compiled
    """Newton's method on plumb_bob(x, y) = (xd, yd) per point, from the radial fixed-point
    guess (xd, yd) / R(rd); a step that does not reduce the residual is halved (at most 30
    times)."""
    k1, k2, p1, p2, k3 = coeffs[0], coeffs[1], coeffs[2], coeffs[3], coeffs[4]
    n = xd.shape[0]
    out_x = np.empty(n)
    out_y = np.empty(n)
    for i in range(n):
        tx, ty = xd[i], yd[i]
        r2 = tx * tx + ty * ty
        guess = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
        if not guess > MIN_GUESS_FACTOR:  # start from the distorted point instead
            guess = 1.0
        x, y = tx / guess, ty / guess
        ex, ey = _residual(x, y, tx, ty, k1, k2, p1, p2, k3)
        err = ex * ex + ey * ey
        converged = False
        for _ in range(max_iter):
            if err <= tol * tol:
                converged = True
                break
            xx, yy, xy = x * x, y * y, x * y
            r2 = xx + yy
            radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
            slope = k1 + r2 * (2.0 * k2 + 3.0 * k3 * r2)  # dR/d(r2)
            cross = 2.0 * xy * slope + 2.0 * p1 * x + 2.0 * p2 * y
            dxx = radial + 2.0 * xx * slope + 2.0 * p1 * y + 6.0 * p2 * x
            dyy = radial + 2.0 * yy * slope + 6.0 * p1 * y + 2.0 * p2 * x
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
                nex, ney = _residual(nx, ny, tx, ty, k1, k2, p1, p2, k3)
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
