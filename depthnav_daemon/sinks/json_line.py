"""The frame's JSON line as bytes, made once a frame and shared by the ``stdout`` and ``udp`` sinks.

The line is ``orjson.dumps(jsonmsg.frame_message(...))``, byte for byte. In the frame loop (its
stages have just streamed megabytes of tables through the caches) building that message's dozen
small objects cost about as much as writing its 1500 numbers, so the line is put together from
text instead wherever the message allows:

- the numbers: the three lists written by one kernel call into a buffer kept from frame to frame
  (json_numbers.lists_text), copied once, into the scan and cliff objects' text;
- a scan's head (angles and limits: the same frame after frame), the pose when the frame has no
  floor estimate, and the mount's trust: made once, reused while they stay the same object.

Anything else (several sensors, points the kernel cannot write, a frame's floor estimate inside
the pose) takes the message's own dicts; tests/sinks/test_json_line.py compares both.
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

import numpy as np
import orjson

from depthnav_daemon.sinks.json_numbers import lists_text
from depthnav_daemon.sinks.jsonmsg import (
    SCHEMA_VERSION,
    SEC,
    _mount_json,
    _num,
    _pose_to_json,
    _scan_geometry,
    _trust_json,
    dropoffs_trusted,
    frame_message,
    memory_to_json,
)

if TYPE_CHECKING:
    from depthnav_daemon.pipeline import Result
    from depthnav_daemon.pipeline.scan import LaserScan
    from drivers.base import Frame

Fragment = orjson.Fragment

# The last frame's line: (result, version, UTF-8 JSON). Every sink that sends the whole object
# (stdout, udp with content=all) gets these bytes: made once a frame, not once a sink.
_last_line: list[tuple[Any, str, bytes]] = []
# One-entry caches, each a tuple replaced whole (threads read them): the pose's text for a mount
# object and source, and the trust's text for a verdict object (the daemon hands every frame the
# same objects until they change)
_last_pose: tuple[Any, str, Fragment] | None = None
_last_trust: tuple[Any, Fragment] | None = None


def frame_json(frame: Frame, result: Result, version: str, wall_time_s: float) -> bytes:
    """:func:`jsonmsg.frame_message` of the frame as compact UTF-8 JSON, made once per Result.

    The sinks of one frame share it, so they also share its ``wall_s`` (the time the first one
    asked). A new Result (the next frame) or another version makes a new line.
    """
    for last_result, last_version, last_data in _last_line[-1:]:
        if last_result is result and last_version == version:
            return last_data
    data = _line(result, version, wall_time_s)
    if data is None:
        data = orjson.dumps(frame_message(frame, result, version, wall_time_s))
    _last_line[:] = [(result, version, data)]  # one entry, replaced whole (threads read it)
    return data


def _line(result: Result, version: str, wall_time_s: float) -> bytes | None:
    """The line from text (see the module docstring); None where the message's dicts are
    needed."""
    if result.sensors:
        return None
    scan, cliff = result.scan, result.cliff
    if np.ndim(scan.ranges) != 1:
        return None
    if cliff is None:
        got = lists_text(scan.ranges)
    elif np.ndim(cliff.scan.ranges) != 1:
        return None
    else:
        got = lists_text(scan.ranges, cliff.points_m, cliff.scan.ranges)
    if got is None:
        return None
    text, a, b, n = got
    scan_json = Fragment(b"".join((_scan_head(scan), text[:a], b"}")))
    cliff_json = None
    if cliff is not None:
        total = np.size(cliff.points_m) // 2
        cliff_json = Fragment(
            b"".join(
                (
                    b'{"points_m":',
                    text[a:b],
                    b',"points_total":%d,"points_dropped":0,"scan":' % total,
                    _scan_head(cliff.scan),
                    text[b:n],
                    b'},"trusted":true}' if dropoffs_trusted(result) else b'},"trusted":false}',
                )
            )
        )
    return orjson.dumps(
        {
            "v": SCHEMA_VERSION,
            "version": version,
            "seq": int(result.seq),
            "t_s": _num(result.timestamp_s, SEC),
            "wall_s": _num(wall_time_s, SEC),
            "scan": scan_json,
            "cliff": cliff_json,
            "pose": _pose(result),
            "mount": _trust(result),
            "memory": memory_to_json(result.memory),
            "sensors": None,
            "timings_s": {k: _num(v, SEC) for k, v in sorted(result.timings_s.items())},
            "warning": result.warning,
            "message": None,
        }
    )


def _scan_head(scan: LaserScan) -> bytes:
    """``{"angle_min":...,"range_max":...,"ranges":`` of a scan (its ranges and ``}`` follow)."""
    return _head(
        scan.angle_min, scan.angle_max, scan.angle_increment, scan.range_min, scan.range_max
    )


@functools.lru_cache(maxsize=64)
def _head(
    angle_min: float, angle_max: float, angle_increment: float, range_min: float, range_max: float
) -> bytes:
    a_min, a_max, a_inc, r_min, r_max = _scan_geometry(
        angle_min, angle_max, angle_increment, range_min, range_max
    )
    whole = orjson.dumps(
        {
            "angle_min": a_min,
            "angle_max": a_max,
            "angle_increment": a_inc,
            "range_min": r_min,
            "range_max": r_max,
            "ranges": None,
        }
    )
    return whole[: -len(b"null}")]


def _pose(result: Result) -> Any:
    """The pose object: its text, made once per mount, when the frame has no floor estimate."""
    global _last_pose  # noqa: PLW0603 - a one-entry cache
    if result.pose is not None:
        return _pose_to_json(result)
    m, source = result.mount, result.mount_source
    last = _last_pose
    if last is not None and last[0] is m and last[1] == source:
        return last[2]
    text = Fragment(orjson.dumps(dict(_mount_json(m, source))))
    _last_pose = (m, source, text)
    return text


def _trust(result: Result) -> Fragment | None:
    """The mount object (its trust): its text, made once per verdict."""
    global _last_trust  # noqa: PLW0603 - a one-entry cache
    t = result.mount_trust
    if t is None:
        return None
    last = _last_trust
    if last is not None and last[0] is t:
        return last[1]
    text = Fragment(orjson.dumps(_trust_json(t)))
    _last_trust = (t, text)
    return text


def fit_message(
    frame: Frame,
    result: Result,
    version: str,
    wall_time_s: float,
    max_bytes: int,
    shape: Callable[[dict[str, Any]], dict[str, Any]] | None = None,
) -> bytes | None:
    """The frame's JSON as UTF-8, cliff points dropped (nearest kept) until it fits ``max_bytes``.

    Args:
        shape: applied to each message before it is encoded (a sink's choice of content); None:
            the whole object (then the line :func:`frame_json` shares when it fits).

    Returns:
        The encoded message, or None when even the message without any cliff points is too big.
    """
    if shape is None:
        data = frame_json(frame, result, version, wall_time_s)
        shape = _whole
    else:
        data = orjson.dumps(shape(frame_message(frame, result, version, wall_time_s)))
    if len(data) <= max_bytes:
        return data
    if result.cliff is None:
        return None
    total = int(np.asarray(result.cliff.points_m).reshape(-1, 2).shape[0])
    cap = total
    while cap > 0:
        # scale by the overshoot, then shave 10 % more: a couple of rounds at most in practice
        cap = min(cap - 1, int(cap * max_bytes / len(data) * 0.9))
        cap = max(cap, 0)
        note = (
            f"cliff points capped to the nearest {cap} of {total} "
            f"to fit one {max_bytes}-byte datagram"
        )
        data = orjson.dumps(
            shape(
                frame_message(
                    frame, result, version, wall_time_s, max_cliff_points=cap, message=note
                )
            )
        )
        if len(data) <= max_bytes:
            return data
    return None


def _whole(msg: dict[str, Any]) -> dict[str, Any]:
    return msg
