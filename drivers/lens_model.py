"""The lens models depthnav expresses, as ROS CameraInfo names them, and their maps.

Normalised coordinates are x = X/Z, y = Y/Z in the camera frame (RDF). A lens maps the ideal
(x, y) of a ray to the distorted (xd, yd) its pixel shows, (u, v) = (fx xd + cx, fy yd + cy):

- ``plumb_bob`` (OpenCV's default, Brown-Conrady), D = (k1, k2, p1, p2, k3):
  xd = x R + 2 p1 x y + p2 (r2 + 2 x2), yd = y R + p1 (r2 + 2 y2) + 2 p2 x y,
  R = 1 + k1 r2 + k2 r4 + k3 r6, r2 = x2 + y2.
- ``rational_polynomial`` (OpenCV's CALIB_RATIONAL_MODEL; the Azure Kinect's), D = (k1, k2, p1,
  p2, k3, k4, k5, k6): the same with R = (1 + k1 r2 + k2 r4 + k3 r6) / (1 + k4 r2 + k5 r4 + k6 r6).
- ``equidistant`` (OpenCV's fisheye module, Kannala-Brandt), D = (k1, k2, k3, k4):
  theta = atan(r), theta_d = theta (1 + k1 theta2 + k2 theta4 + k3 theta6 + k4 theta8),
  (xd, yd) = (theta_d / r) (x, y); all zero is the ideal equidistant fisheye, not a pinhole.

Pure numpy, no depthnav imports: ``drivers.base.Intrinsics`` checks with it that a model is
invertible over its image, ``depthnav_daemon.pipeline.lens`` inverts it.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Mapping
from typing import Any

import numpy as np
import numpy.typing as npt

from drivers.values import NumberError, short_repr, to_number

F64 = npt.NDArray[np.float64]

PLUMB_BOB, RATIONAL, EQUIDISTANT = "plumb_bob", "rational_polynomial", "equidistant"
# each model's coefficients in its ROS CameraInfo D order (OpenCV's order too)
MODEL_KEYS: dict[str, tuple[str, ...]] = {
    PLUMB_BOB: ("k1", "k2", "p1", "p2", "k3"),
    RATIONAL: ("k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6"),
    EQUIDISTANT: ("k1", "k2", "k3", "k4"),
}
MODELS = tuple(MODEL_KEYS)
COEFF_KEYS = MODEL_KEYS[RATIONAL]  # every coefficient field of Intrinsics, in this order
MODELS_TEXT = (
    "plumb_bob (k1, k2, p1, p2, k3), rational_polynomial (k1-k6, p1, p2), equidistant (k1-k4)"
)

PIXEL_HALF = 0.5  # pixel centres at integers: the image spans -0.5 .. size - 0.5
# the lens model must stay invertible this far beyond the image's edges (pixels, share of the side)
LENS_MARGIN_PX = 16.0
LENS_MARGIN_SHARE = 0.05
_FOLD_LIMIT_R = 20.0  # ideal normalised radius (87 deg off axis) the invertibility walk stops at
_SERIES_R = 1e-4  # below this radius the fisheye's scale uses its series (0/0 otherwise)
_MIN_DENOMINATOR = 1e-6  # a rational model's denominator must stay above this over the image


def lens_fields(table: Mapping[str, Any]) -> dict[str, float | str]:
    """The lens fields of an ``[intrinsics]`` table (camera.toml, recording.toml) as Intrinsics
    keywords: ``distortion_model`` (a name of ``MODELS``, default plumb_bob) and whichever of
    k1-k6, p1, p2 it gives (absent = 0). Which coefficients belong to which model is checked by
    Intrinsics (a k4 under plumb_bob is refused there, never dropped).

    Raises:
        ValueError: one line: a model that is not text, a coefficient that is not a number.
    """
    out: dict[str, float | str] = {}
    if "distortion_model" in table:
        model = table["distortion_model"]
        if not isinstance(model, str):
            raise ValueError(
                f"distortion_model = {short_repr(model)} is not text (one of {', '.join(MODELS)})"
            )
        out["distortion_model"] = model.strip()
    for key in COEFF_KEYS:
        if key not in table:
            continue
        if isinstance(table[key], str):
            raise ValueError(f"{key} is text, not a number")
        try:
            out[key] = float(to_number(table[key]))
        except NumberError as exc:
            raise ValueError(f"{key} = {short_repr(table[key])} {exc}") from None
    return out


def lens_table(model: str, coeffs: tuple[float, ...]) -> dict[str, float | str]:
    """The ``[intrinsics]`` lens entries ``lens_fields`` reads back: none for an ideal pinhole,
    the coefficients alone for plumb_bob (as before the other models), else the model's name and
    its coefficients."""
    if model == PLUMB_BOB and not any(coeffs):
        return {}
    named: dict[str, float | str] = {} if model == PLUMB_BOB else {"distortion_model": model}
    return named | {k: float(v) for k, v in zip(MODEL_KEYS[model], coeffs, strict=True)}


def plumb_bob(x: F64, y: F64, coeffs: tuple[float, ...]) -> tuple[F64, ...]:
    """The plumb-bob map and its Jacobian: ``lens_map`` for D = (k1, k2, p1, p2, k3)."""
    return lens_map(x, y, PLUMB_BOB, coeffs)


def rational_coeffs(model: str, coeffs: tuple[float, ...]) -> tuple[float, ...]:
    """(k1, k2, p1, p2, k3, k4, k5, k6) of a plumb_bob or rational_polynomial D (plumb_bob is
    the rational model with no denominator terms)."""
    return (tuple(coeffs) + (0.0,) * 8)[:8] if model != EQUIDISTANT else ()


def lens_map(x: F64, y: F64, model: str, coeffs: tuple[float, ...]) -> tuple[F64, ...]:
    """A lens model's map of ideal normalised (x, y) (equal shapes) and its Jacobian.

    Args:
        model: one of ``MODELS``.
        coeffs: its D, in ``MODEL_KEYS[model]`` order.

    Returns:
        (xd, yd, dxd/dx, dxd/dy, dyd/dx, dyd/dy), each shaped like ``x``.
    """
    if model == EQUIDISTANT:
        return _equidistant(x, y, coeffs)
    k1, k2, p1, p2, k3, k4, k5, k6 = rational_coeffs(model, coeffs)
    xx, yy, xy = x * x, y * y, x * y
    r2 = xx + yy
    num = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
    den = 1.0 + r2 * (k4 + r2 * (k5 + r2 * k6))
    radial = num / den
    # dR/d(r2), the quotient rule
    slope = (
        (k1 + r2 * (2.0 * k2 + 3.0 * k3 * r2)) * den - num * (k4 + r2 * (2.0 * k5 + 3.0 * k6 * r2))
    ) / (den * den)
    xd = x * radial + 2.0 * p1 * xy + p2 * (r2 + 2.0 * xx)
    yd = y * radial + p1 * (r2 + 2.0 * yy) + 2.0 * p2 * xy
    cross = 2.0 * xy * slope + 2.0 * p1 * x + 2.0 * p2 * y
    dxx = radial + 2.0 * xx * slope + 2.0 * p1 * y + 6.0 * p2 * x
    dyy = radial + 2.0 * yy * slope + 6.0 * p1 * y + 2.0 * p2 * x
    return xd, yd, dxx, cross, cross, dyy


def theta_d(theta: F64, coeffs: tuple[float, ...]) -> tuple[F64, F64]:
    """The fisheye's distorted angle theta_d(theta) and d theta_d / d theta (radians)."""
    k1, k2, k3, k4 = coeffs
    t2 = theta * theta
    poly = 1.0 + t2 * (k1 + t2 * (k2 + t2 * (k3 + t2 * k4)))
    slope = 1.0 + t2 * (3.0 * k1 + t2 * (5.0 * k2 + t2 * (7.0 * k3 + t2 * 9.0 * k4)))
    return theta * poly, slope


def _equidistant(x: F64, y: F64, coeffs: tuple[float, ...]) -> tuple[F64, ...]:
    """The fisheye as a radial map (xd, yd) = s(r2) (x, y), s = theta_d / r, with its Jacobian."""
    xx, yy, xy = x * x, y * y, x * y
    r2 = xx + yy
    r = np.sqrt(r2)
    small = r < _SERIES_R
    safe_r = np.where(small, 1.0, r)
    theta = np.arctan(safe_r)
    td, dtd = theta_d(theta, coeffs)
    # s = theta_d / r; ds/d(r2) = (ds/dr) / (2 r), ds/dr = (theta_d' r / (1 + r2) - theta_d) / r2
    s = np.where(small, 1.0 + (coeffs[0] - 1.0 / 3.0) * r2, td / safe_r)
    ds_dr = (dtd * safe_r / (1.0 + safe_r * safe_r) - td) / (safe_r * safe_r)
    slope = np.where(small, coeffs[0] - 1.0 / 3.0, ds_dr / (2.0 * safe_r))
    cross = 2.0 * xy * slope
    return x * s, y * s, s + 2.0 * xx * slope, cross, cross, s + 2.0 * yy * slope


@functools.lru_cache(maxsize=64)
def distortion_problem(
    width: int,
    height: int,
    fx: float,
    fy: float,
    cx: float,
    cy: float,
    model: str,
    coeffs: tuple[float, ...],
) -> str | None:
    """Why this lens model cannot be inverted over the image, or None when it can.

    Walks outwards from the principal point along 94 directions in ideal normalised coordinates
    until the distorted point leaves the image (a margin beyond its edges): on the way the
    map must keep a positive Jacobian (and a rational model a positive denominator) and move
    outwards, so every pixel has exactly one ray. A model that folds back (a polynomial's turning
    point inside the image) fails.
    """
    # 90 directions and the corners' (radial distortion keeps a point's direction)
    edges_u, edges_v = (-PIXEL_HALF, width - PIXEL_HALF), (-PIXEL_HALF, height - PIXEL_HALF)
    corners = [math.atan2(b - cy, a - cx) for a in edges_u for b in edges_v]
    theta = np.concatenate((np.linspace(0.0, 2.0 * math.pi, 90, endpoint=False), corners))
    theta = theta[:, None]
    # steps of 0.004 (2.3 pixels at fx 580) near the axis, coarser out where only a fold can be
    r = np.concatenate((np.linspace(0.0, 4.0, 1001)[1:], np.linspace(4.0, _FOLD_LIMIT_R, 81)[1:]))
    r = r[None, :]
    x, y = r * np.cos(theta), r * np.sin(theta)
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        xd, yd, dxx, dxy, dyx, dyy = lens_map(x, y, model, coeffs)
        good = (dxx * dyy - dxy * dyx > 0) & (
            np.diff(xd * np.cos(theta) + yd * np.sin(theta), axis=1, prepend=0.0) > 0
        )
        if model != EQUIDISTANT:
            k4, k5, k6 = rational_coeffs(model, coeffs)[5:]
            r2 = r * r
            good &= 1.0 + r2 * (k4 + r2 * (k5 + r2 * k6)) > _MIN_DENOMINATOR
        u, v = fx * xd + cx, fy * yd + cy
    # the table builders also look half a sample step past the edge pixels
    margin_u = min(LENS_MARGIN_PX, LENS_MARGIN_SHARE * width) + PIXEL_HALF
    margin_v = min(LENS_MARGIN_PX, LENS_MARGIN_SHARE * height) + PIXEL_HALF
    inside = (np.abs(u - (width - 1) / 2) <= (width - 1) / 2 + margin_u) & (
        np.abs(v - (height - 1) / 2) <= (height - 1) / 2 + margin_v
    )
    # each direction is fine up to where it first leaves the image
    first_out = np.where(inside.all(axis=1), r.shape[1], np.argmin(inside, axis=1))
    before = np.arange(r.shape[1])[None, :] < first_out[:, None]
    if np.any(before & ~good):
        return "folds back inside the image"
    if np.any(first_out == r.shape[1]):
        if model == EQUIDISTANT:  # theta is below 87 deg here: the image sees further out
            return "sees rays 87 deg or more off axis (a depth along the optical axis needs < 90)"
        return "never reaches the image edge"
    return None
