"""Mount planner: the lower dead zone (eq. 15) and the band of heights seen at a distance (eq. 16).

Angles follow depthnav: tilt positive = pitched down; theta is the vertical field of view. The
lower edge of the view points theta/2 + tilt below the horizon, the upper edge theta/2 - tilt above.
"""

from __future__ import annotations

import math

import numpy as np
import numpy.typing as npt

from depthnav_daemon.errors import ConfigError
from depthnav_daemon.pipeline.geometry import MAX_MOUNT_HEIGHT_M, MAX_TILT_DEG, check_range

F64 = npt.NDArray[np.float64]


def _check(height_m: float, tilt_deg: float, vfov_deg: float) -> tuple[float, float, float]:
    h = check_range("height_m", height_m, 0.01, MAX_MOUNT_HEIGHT_M, " m")
    t = check_range("tilt_deg", tilt_deg, -MAX_TILT_DEG, MAX_TILT_DEG, " deg")
    v = check_range("vfov_deg", vfov_deg, 1.0, 179.0, " deg")
    return h, math.radians(t), math.radians(v)


def _distances(name: str, values: npt.ArrayLike, hi: float) -> F64:
    try:
        arr = np.asarray(values, dtype=np.float64)
    except (TypeError, ValueError):
        raise ConfigError(
            f"{name}={values!r} is not a number or array of numbers (accepted: 0..{hi:g} m)"
        ) from None
    bad = ~(np.isfinite(arr) & (arr >= 0) & (arr <= hi))
    if bad.any():
        raise ConfigError(
            f"{name}={float(arr[bad].flat[0])!r} is out of range (accepted: 0..{hi:g} m)"
        )
    return arr


def lower_dead_zone_m(
    height_m: float, tilt_deg: float, vfov_deg: float, h1_m: npt.ArrayLike = 0.0
) -> F64:
    """Eq. 15: d_m = (h - h1) tan(pi/2 - theta/2 - alpha), the blind length in front of the sensor.

    Args:
        height_m: optical centre above the floor, metres.
        tilt_deg: pitch, positive down, degrees.
        vfov_deg: vertical field of view theta, degrees.
        h1_m: height(s) above the floor at which the dead zone is measured, metres, 0 <= h1 <= h
            (0 = on the floor); scalar or array.

    Returns:
        Horizontal distance(s), metres, same shape as ``h1_m``: +inf when the lower edge of the view
        does not point below the horizon, 0 when it points past the vertical.

    Raises:
        ConfigError: a value outside its accepted range.
    """
    h, a, theta = _check(height_m, tilt_deg, vfov_deg)
    h1 = _distances("h1_m", h1_m, h)
    depression = theta / 2 + a
    if depression <= 0:
        return np.full(h1.shape, np.inf)
    return np.maximum((h - h1) * math.tan(math.pi / 2 - depression), 0.0)


def max_visible_height_m(
    height_m: float, tilt_deg: float, vfov_deg: float, distance_m: npt.ArrayLike
) -> F64:
    """Eq. 16: h_max = h + sgn(theta/2 - alpha) l1 tan|theta/2 - alpha|, highest point seen at l1.

    Args:
        height_m, tilt_deg, vfov_deg: as ``lower_dead_zone_m``.
        distance_m: horizontal distance(s) l1 from the sensor, metres; scalar or array.

    Returns:
        Height(s) above the floor, metres, same shape as ``distance_m``; +inf when the upper edge of
        the view points past the vertical.
    """
    h, a, theta = _check(height_m, tilt_deg, vfov_deg)
    l1 = _distances("distance_m", distance_m, 1e4)
    elevation = theta / 2 - a
    if elevation >= math.pi / 2:
        return np.full(l1.shape, np.inf)
    # sgn(x) tan|x| = tan(x) for |x| < pi/2
    return h + l1 * math.tan(elevation)


def min_visible_height_m(
    height_m: float, tilt_deg: float, vfov_deg: float, distance_m: npt.ArrayLike
) -> F64:
    """The lowest point seen at horizontal distance l1: h - l1 tan(theta/2 + alpha), metres (eq. 15
    solved for h1); negative means the floor itself is in view there (the value is where the lower
    edge of the view would meet a plane at that height)."""
    h, a, theta = _check(height_m, tilt_deg, vfov_deg)
    l1 = _distances("distance_m", distance_m, 1e4)
    depression = theta / 2 + a
    if depression >= math.pi / 2:
        return np.full(l1.shape, -np.inf)
    return h - l1 * math.tan(depression)


def plan_table(
    height_m: float, tilt_deg: float, vfov_deg: float, distances_m: npt.ArrayLike
) -> list[dict[str, float | bool]]:
    """Rows for a CLI table: what the sensor sees at each distance.

    Returns:
        One dict per distance: ``distance_m``; ``lowest_seen_m`` (height of the lowest point
        seen, 0 when the floor is seen); ``highest_seen_m`` (eq. 16); ``floor_seen`` (beyond the
        lower dead zone of eq. 15).
    """
    d = np.atleast_1d(_distances("distances_m", distances_m, 1e4))
    lo = min_visible_height_m(height_m, tilt_deg, vfov_deg, d)
    hi = max_visible_height_m(height_m, tilt_deg, vfov_deg, d)
    dead = float(lower_dead_zone_m(height_m, tilt_deg, vfov_deg))
    return [
        {
            "distance_m": float(di),
            "lowest_seen_m": float(max(li, 0.0)),
            "highest_seen_m": float(hv),
            "floor_seen": bool(di >= dead),
        }
        for di, li, hv in zip(d, lo, hi, strict=True)
    ]
