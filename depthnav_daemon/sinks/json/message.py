"""The JSON object of one frame, shared by the ``stdout`` and ``udp`` sinks (docs/json_schema.md).

Strict JSON (no NaN/Infinity literals). Scan ranges keep the three REP 117 special values apart:
a finite range is a number in metres rounded to 1 mm, NaN (no valid reading) is ``null``, +inf (no
obstacle within range_max) is the string ``"Infinity"`` and -inf (an obstacle closer than
range_min) is ``"-Infinity"``. Python's ``float()`` and JavaScript's ``Number()`` both read those
strings; :func:`decode_ranges` is the reference decoder.

Arrays go through numpy (rounded to 1 mm, ``tolist``) and the object through orjson, one call per
message. A frame's line is made once and shared by the sinks that send the same object (line.py).

Mount trust: ``mount.trusted`` and ``scan.trusted`` are false while the mount is unconfirmed
(nobody configured it, the floor has not given it yet): every range is then null (unknown), and
``mount.note`` says why. ``cliff.trusted`` (and ``mount.dropoffs_trusted``) flag drop-offs.
"""

from __future__ import annotations

import functools
import logging
import math
from collections.abc import Sequence
from typing import TYPE_CHECKING, Any

import numpy as np
import orjson

if TYPE_CHECKING:
    from depthnav_daemon.pipeline import Result
    from depthnav_daemon.pipeline.geometry import Mount
    from depthnav_daemon.pipeline.scan import LaserScan
    from drivers.base import Frame

log = logging.getLogger(__name__)

SCHEMA_VERSION = 1
POS_INF = "Infinity"
NEG_INF = "-Infinity"
MM = 3  # decimals for metres (1 mm)
RAD = 6  # decimals for radians (1 microradian)
DEG = 3  # decimals for degrees
SEC = 6  # decimals for seconds (1 microsecond)


def _num(value: float | None, decimals: int) -> float | None:
    """A finite number rounded to ``decimals``; None for None/NaN/inf (scalars have no inf code)."""
    if value is None:
        return None
    v = float(value)
    return round(v, decimals) if math.isfinite(v) else None


def encode_ranges(ranges: np.ndarray) -> list[float | str | None]:
    """REP 117 ranges (N,) metres -> JSON list: numbers (1 mm), null, "Infinity", "-Infinity"."""
    r = np.asarray(ranges, dtype=np.float64)
    finite = np.isfinite(r)
    if finite.all():  # nearly every bin of a frame with obstacles all around
        out: list[float | str | None] = np.round(r, MM).tolist()
        return out
    # an object array takes the special values by mask: most bins of a corridor are +inf, and a
    # Python loop over them cost twice as much per frame
    obj = np.round(r, MM).astype(object)
    obj[np.isposinf(r)] = POS_INF
    obj[np.isneginf(r)] = NEG_INF
    obj[np.isnan(r)] = None
    out = obj.tolist()
    return out


def decode_ranges(values: Sequence[float | str | None]) -> np.ndarray:
    """The inverse of :func:`encode_ranges`: a JSON ranges list -> (N,) float64 with NaN/+inf/-inf.

    Raises:
        ValueError: an element that is none of number, null, "Infinity", "-Infinity".
    """
    out = np.empty(len(values), dtype=np.float64)
    for i, v in enumerate(values):
        if v is None:
            out[i] = math.nan
        elif v == POS_INF:
            out[i] = math.inf
        elif v == NEG_INF:
            out[i] = -math.inf
        elif isinstance(v, (int, float)) and not isinstance(v, bool):
            out[i] = float(v)
        else:
            raise ValueError(f"ranges[{i}]={v!r} is not a number, null, {POS_INF!r} or {NEG_INF!r}")
    return out


def scan_to_json(scan: LaserScan) -> dict[str, Any]:
    """A LaserScan as a dict with sensor_msgs/LaserScan field names (radians, metres)."""
    a_min, a_max, a_inc, r_min, r_max = _scan_geometry(
        scan.angle_min, scan.angle_max, scan.angle_increment, scan.range_min, scan.range_max
    )
    return {
        "angle_min": a_min,
        "angle_max": a_max,
        "angle_increment": a_inc,
        "range_min": r_min,
        "range_max": r_max,
        "ranges": encode_ranges(scan.ranges),
    }


@functools.lru_cache(maxsize=64)
def _scan_geometry(
    angle_min: float, angle_max: float, angle_increment: float, range_min: float, range_max: float
) -> tuple[float | None, ...]:
    """A scan's angles and limits, rounded: the same frame after frame, so rounded once (Python's
    round() of five numbers was a tenth of the line's cost)."""
    return (
        _num(angle_min, RAD),
        _num(angle_max, RAD),
        _num(angle_increment, RAD + 3),
        _num(range_min, MM),
        _num(range_max, MM),
    )


def _cliff_to_json(
    cliff: Any,
    max_points: int | None,
    trusted: bool = True,
) -> dict[str, Any]:
    """The cliff object; keeps the ``max_points`` floor points nearest the sensor when capped.
    ``trusted`` False flags its drop-offs (the mount they rest on is not trusted)."""
    pts = np.asarray(cliff.points_m, dtype=np.float64).reshape(-1, 2)
    total = int(pts.shape[0])
    if max_points is not None and total > max_points:
        # the nearest drop-offs matter most to a robot that has to stop in time
        keep = np.argsort(np.hypot(pts[:, 0], pts[:, 1]), kind="stable")[:max_points]
        pts = pts[np.sort(keep)]
    if not np.isfinite(pts).all():  # the row-wise test costs more: only when one is needed
        pts = pts[np.isfinite(pts).all(axis=1)]
    return {
        "points_m": np.round(pts, MM).tolist(),
        "points_total": total,
        "points_dropped": total - int(pts.shape[0]),
        "scan": scan_to_json(cliff.scan),
        "trusted": trusted,
    }


def memory_to_json(memory: Any) -> dict[str, Any] | None:
    """The memory object (docs/json_schema.md): status, the 360 deg memory scan, cell counts, the
    odometry samples refused per kind."""
    if memory is None:
        return None
    pose = memory.pose
    return {
        "status": memory.status,
        "scan": None if memory.scan is None else scan_to_json(memory.scan),
        "cells": {"obstacle": int(memory.obstacle_cells), "cliff": int(memory.cliff_cells)},
        "odom": None
        if pose is None
        else {"x_m": _num(pose[0], MM), "y_m": _num(pose[1], MM), "yaw_rad": _num(pose[2], RAD)},
        "size_m": _num(memory.size_m, MM),
        "cell_m": _num(memory.cell_m, MM),
        "note": memory.note,
        "odometry_rejected": {k: int(v) for k, v in memory.odometry_rejected.items()},
    }


def sensors_to_json(sensors: Sequence[Any], max_cliff_points: int | None) -> list | None:
    """Several sensors: each one's name, status, age and own latest scan, cliff and pose (its base
    frame results); None with one sensor."""
    if not sensors:
        return None
    out = []
    for s in sensors:
        r = s.result
        out.append(
            {
                "name": s.name,
                "status": s.status,
                "age_s": _num(s.age_s, SEC),
                "seq": None if r is None else int(r.seq),
                "scan": None if r is None else _live_scan_json(r),
                "cliff": None
                if r is None or r.cliff is None
                else _cliff_to_json(r.cliff, max_cliff_points, dropoffs_trusted(r)),
                "pose": None if r is None else _pose_to_json(r),
                "mount": None if r is None else mount_trust_to_json(r),
            }
        )
    return out


def mount_trusted(result: Result) -> bool:
    """Whether the mount a result rests on is known (configured, or confirmed by the floor);
    True when nobody assessed it."""
    trust = result.mount_trust
    return trust is None or trust.trusted


def _live_scan_json(result: Result) -> dict[str, Any]:
    """The result's scan, with ``trusted``: false while its mount is unconfirmed (its ranges are
    then all unknown)."""
    out = scan_to_json(result.scan)
    out["trusted"] = mount_trusted(result)
    return out


def dropoffs_trusted(result: Result) -> bool:
    """Whether a result's drop-offs rest on a trusted mount (True when nobody assessed it)."""
    trust = result.mount_trust
    return trust is None or trust.dropoffs_trusted


def mount_trust_to_json(result: Result) -> dict[str, Any] | None:
    """The mount object: where the mount came from, whether the floor confirms it, and whether
    drop-offs are trusted (docs/json_schema.md); None when nobody assessed it."""
    t = result.mount_trust
    if t is None:
        return None
    # the daemon hands every frame the same frozen verdict until it changes: made once (a copy,
    # so that a caller changing its message changes no other frame's)
    global _last_trust  # noqa: PLW0603 - a one-entry cache
    last = _last_trust
    if last is not None and last[0] is t:
        return dict(last[1])
    out = _trust_json(t)
    _last_trust = (t, out)  # one tuple, replaced whole (threads read it)
    return dict(out)


_last_trust: tuple[Any, dict[str, Any]] | None = None


def _trust_json(t: Any) -> dict[str, Any]:
    return {
        "source": t.source,
        "pinned": t.pinned,
        "floor": t.floor,
        "floor_height_m": _num(t.floor_height_m, MM),
        "floor_tilt_deg": _num(t.floor_tilt_deg, DEG),
        "floor_roll_deg": _num(t.floor_roll_deg, DEG),
        "trusted": t.trusted,
        "dropoffs_trusted": t.dropoffs_trusted,
        "note": t.note,
    }


_last_mount: tuple[Any, str, tuple[tuple[str, Any], ...]] | None = None


@functools.lru_cache(maxsize=16)
def _mount_json(m: Mount, source: str) -> tuple[tuple[str, Any], ...]:
    """The pose object's mount part: the same frame after frame (a mount changes seldom), so
    rounded once (six rounds were a tenth of the line's cost)."""
    return (
        ("height_m", _num(m.height_m, MM)),
        ("tilt_deg", _num(m.tilt_deg, DEG)),
        ("roll_deg", _num(m.roll_deg, DEG)),
        ("x_m", _num(m.x_m, MM)),
        ("y_m", _num(m.y_m, MM)),
        ("yaw_deg", _num(m.yaw_deg, DEG)),
        ("source", source),
        ("estimate", None),
    )


def _pose_to_json(result: Result) -> dict[str, Any]:
    """The mount used for this frame, where it came from, and this frame's floor estimate if any."""
    global _last_mount  # noqa: PLW0603 - a one-entry cache
    m, source = result.mount, result.mount_source
    last = _last_mount
    if last is not None and last[0] is m and last[1] == source:
        out = dict(last[2])  # the same mount object as the last frame's: no hashing it anew
    else:
        pairs = _mount_json(m, source)
        _last_mount = (m, source, pairs)
        out = dict(pairs)
    est = result.pose
    if est is not None:
        out["estimate"] = {
            "ok": bool(est.ok),
            "height_m": _num(est.height_m, MM),
            "tilt_deg": _num(est.tilt_deg, DEG),
            "roll_deg": _num(est.roll_deg, DEG),
            "inliers": int(est.inliers),
            "inlier_ratio": _num(est.inlier_ratio, 4),
            "residual_m": _num(est.residual_m, 5),
            "candidates": int(est.candidates),
            "reason": str(est.reason),
        }
    return out


def frame_message(
    frame: Frame,
    result: Result,
    version: str,
    wall_time_s: float,
    *,
    max_cliff_points: int | None = None,
    message: str | None = None,
) -> dict[str, Any]:
    """The JSON object for one processed frame (see docs/json_schema.md).

    Args:
        frame: the depth frame (only its seq and timestamp are used).
        result: what the pipeline computed for it.
        version: depthnav version string.
        wall_time_s: host UNIX time when the message is made, seconds.
        max_cliff_points: keep at most this many cliff floor points (the nearest); None = all.
        message: a note from the sink about this message (e.g. points dropped), or None.

    Returns:
        A dict ready for :func:`dumps`.
    """
    return {
        "v": SCHEMA_VERSION,
        "version": version,
        "seq": int(result.seq),
        "t_s": _num(result.timestamp_s, SEC),
        "wall_s": _num(wall_time_s, SEC),
        "scan": _live_scan_json(result),
        "cliff": None
        if result.cliff is None
        else _cliff_to_json(result.cliff, max_cliff_points, dropoffs_trusted(result)),
        "pose": _pose_to_json(result),
        "mount": mount_trust_to_json(result),
        "memory": memory_to_json(result.memory),
        "sensors": sensors_to_json(result.sensors, max_cliff_points),
        "timings_s": {k: _num(v, SEC) for k, v in sorted(result.timings_s.items())},
        "warning": result.warning,
        "message": message,
    }


def dumps(msg: dict[str, Any]) -> str:
    """Compact strict JSON, one line.

    orjson writes the same text as ``json.dumps(separators=(",", ":"), ensure_ascii=False)``
    about five times faster (a third of the daemon's CPU at 30 frames/s went here); it never writes
    NaN or Infinity literals: a stray non-finite float becomes null, the schema's "unknown".
    """
    return orjson.dumps(msg).decode()
