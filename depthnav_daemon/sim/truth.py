"""Ground truth of a synthetic scene in the horizontal plane: true ranges per bearing to boxes and
drop-offs, and which floor locations lie in a drop-off (the scene generator is synthetic.py)."""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import numpy as np
import numpy.typing as npt

if TYPE_CHECKING:
    from depthnav_daemon.sim.synthetic import Scene

F64 = npt.NDArray[np.float64]


def slab(o: F64, d: F64, lo: F64, hi: F64) -> tuple[F64, F64]:
    """Entry and exit ray parameters of an axis-aligned box, per ray (..., ); entry > exit =
    miss."""
    # over: a subnormal direction component gives inf, as a zero one does (handled below)
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        inv = 1.0 / d
        t1 = (lo - o) * inv
        t2 = (hi - o) * inv
    tmin = np.where(np.isnan(t1), -np.inf, np.minimum(t1, t2))
    tmax = np.where(np.isnan(t2), np.inf, np.maximum(t1, t2))
    # rays parallel to a slab: inside it -> unbounded, outside -> miss
    par = d == 0
    inside = (o >= lo) & (o <= hi)
    tmin = np.where(par, np.where(inside, -np.inf, np.inf), tmin)
    tmax = np.where(par, np.where(inside, np.inf, -np.inf), tmax)
    return tmin.max(axis=-1), tmax.min(axis=-1)


def _ray_rect_2d(
    bearings: F64, x0: F64, x1: F64, y0: F64, y1: F64, origin: F64, yaw_rad: float
) -> F64:
    """Horizontal distance from ``origin`` (2,) along each bearing (N,) to a rectangle; +inf =
    miss."""
    c, s = math.cos(yaw_rad), math.sin(yaw_rad)
    d = np.stack([np.cos(bearings), np.sin(bearings)], axis=-1)
    rot = np.array([[c, s], [-s, c]])
    d = d @ rot.T
    o = rot @ origin
    t_in, t_out = slab(o[None, :], d, np.array([x0, y0]), np.array([x1, y1]))
    return np.where((t_in <= t_out) & (t_out >= 0), np.maximum(t_in, 0.0), np.inf)


def truth_obstacle_ranges(
    scene: Scene, bearings_rad: F64, min_height_m: float, max_height_m: float
) -> F64:
    """True horizontal range to the nearest box side per bearing, (N,) metres, +inf where none.

    Only boxes whose vertical extent overlaps [min_height_m, max_height_m] count; bearings are
    counter-clockwise from forward, measured at the sensor's foot.
    """
    best = np.full(np.shape(bearings_rad), np.inf)
    for box in scene.boxes:
        if box.top_m < min_height_m or box.base_m > max_height_m:
            continue
        origin = -np.array([box.x_m, box.y_m])
        r = _ray_rect_2d(
            np.asarray(bearings_rad, dtype=np.float64),
            -box.length_m / 2,
            box.length_m / 2,
            -box.width_m / 2,
            box.width_m / 2,
            origin,
            math.radians(box.yaw_deg),
        )
        best = np.minimum(best, r)
    return best


def truth_drop_ranges(scene: Scene, bearings_rad: F64) -> F64:
    """True horizontal range to the nearest drop-off (hole or step edge) per bearing, (N,), +inf
    none."""
    best = np.full(np.shape(bearings_rad), np.inf)
    for hole in scene.holes:
        r = _ray_rect_2d(
            np.asarray(bearings_rad, dtype=np.float64),
            hole.x_min_m,
            hole.x_max_m,
            hole.y_min_m,
            hole.y_max_m,
            np.zeros(2),
            0.0,
        )
        best = np.minimum(best, r)
    return best


def in_drop_off(scene: Scene, x_m: F64, y_m: F64, margin_m: float = 0.0) -> npt.NDArray[np.bool_]:
    """True where the floor location (x, y) lies within ``margin_m`` of a hole's footprint."""
    x = np.asarray(x_m)
    y = np.asarray(y_m)
    out = np.zeros(np.broadcast(x, y).shape, dtype=bool)
    for h in scene.holes:
        out |= (
            (x >= h.x_min_m - margin_m)
            & (x <= h.x_max_m + margin_m)
            & (y >= h.y_min_m - margin_m)
            & (y <= h.y_max_m + margin_m)
        )
    return out


def truth_obstacle_interval(
    scene: Scene,
    bearings_rad: F64,
    half_width_rad: float,
    min_height_m: float,
    max_height_m: float,
    samples: int = 17,
) -> tuple[F64, F64]:
    """Lowest and highest true obstacle range over [b - half_width, b + half_width] per bearing b.

    A scan bin collects every pixel whose footprint overlaps it, so its honest truth is an interval:
    on a face seen at a grazing angle the range changes by centimetres within one bin.

    Returns:
        (lo, hi), each (N,) metres; lo is +inf where no obstacle lies in the interval, hi is +inf
        where the obstacle does not cover the whole interval.
    """
    b = np.asarray(bearings_rad, dtype=np.float64)
    offsets = np.linspace(-half_width_rad, half_width_rad, samples)
    r = truth_obstacle_ranges(
        scene, (b[:, None] + offsets[None, :]).ravel(), min_height_m, max_height_m
    )
    r = r.reshape(b.size, samples)
    return r.min(axis=1), r.max(axis=1)
