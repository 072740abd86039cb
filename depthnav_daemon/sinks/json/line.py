"""The frame's JSON line as bytes, made once a frame and shared by the ``stdout`` and ``udp`` sinks.

The line is ``orjson.dumps(jsonmsg.frame_message(...))`` and a newline, byte for byte. In the
frame loop (its stages have just streamed megabytes of tables through the caches) every small
Python step costs: the message's dicts, its four rounded times and the joins of the pieces cost as
much as writing its 1500 numbers. So the line is written by one compiled call from a template
(json_template): the text around the numbers, with a control byte where each number goes:

- the text pieces: a scan's head (angles and limits, the same frame after frame), the pose when
  the frame has no floor estimate, the mount's trust, the timings' keys: made once, reused while
  they stay the same;
- the numbers: the three lists, the sequence number and point count, the times (as orjson writes
  Python's ``round(t, 6)``), written into a buffer kept from frame to frame, then copied once.

Anything else (several sensors, points the kernel cannot write, a time beyond 2106) takes the
message's own dicts; tests/sinks/test_json_line.py compares both.
"""

from __future__ import annotations

import functools
import operator
from array import array
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

import numpy as np
import orjson

from depthnav_daemon.sinks.json.message import (
    SCHEMA_VERSION,
    _mount_json,
    _pose_to_json,
    _scan_geometry,
    _trust_json,
    dropoffs_trusted,
    frame_message,
    memory_to_json,
)
from depthnav_daemon.sinks.json.template import FLAT, INTEGER, PAIRS, SECONDS, template_text

if TYPE_CHECKING:
    from depthnav_daemon.pipeline import Result
    from depthnav_daemon.pipeline.scan import LaserScan
    from drivers.base import Frame

# The last frame's line: (result, version, UTF-8 JSON). Every sink that sends the whole object
# (stdout, udp with content=all) gets these bytes: made once a frame, not once a sink.
_last_line: list[tuple[Any, str, bytes]] = []
# One-entry caches, each a tuple replaced whole (threads read them): the pose's text for a mount
# object and source, and the trust's text for a verdict object (the daemon hands every frame the
# same objects until they change)
_last_pose: tuple[Any, str, bytes] | None = None
_last_trust: tuple[Any, bytes] | None = None
# the last plain frame's template, see _line: (key, mount, trust, template, what takes the
# timings' values)
_Shape = tuple[tuple[Any, ...], Any, Any, bytes, Callable[[dict[str, float]], tuple[Any, ...]]]
_last_shape: _Shape | None = None


def frame_line(frame: Frame, result: Result, version: str, wall_time_s: float) -> bytes:
    """:func:`jsonmsg.frame_message` of the frame as compact UTF-8 JSON and a newline (what the
    stdout sink writes; the udp sink sends it without the newline), made once per Result.

    The sinks of one frame share it, so they also share its ``wall_s`` (the time the first one
    asked). A new Result (the next frame) or another version makes a new line.
    """
    for last_result, last_version, last_data in _last_line[-1:]:
        if last_result is result and last_version == version:
            return last_data
    data = _line(result, version, wall_time_s)
    if data is None:
        data = orjson.dumps(frame_message(frame, result, version, wall_time_s)) + b"\n"
    _last_line[:] = [(result, version, data)]  # one entry, replaced whole (threads read it)
    return data


def frame_json(frame: Frame, result: Result, version: str, wall_time_s: float) -> bytes:
    """:func:`frame_line` without its newline (a copy)."""
    return frame_line(frame, result, version, wall_time_s)[:-1]


def _line(result: Result, version: str, wall_time_s: float) -> bytes | None:
    """The line and its newline from a template (see the module docstring); None where the
    message's dicts are needed.

    A frame like the one before (no floor estimate, memory, warning or several sensors; the same
    scan geometry, mount, trust and timing keys: nearly every frame) reuses that frame's template:
    one comparison of a tuple instead of the pieces' caches and joins. In the frame loop each
    Python step here runs with cold caches (2-6x its cost alone), so steps are what this saves.
    """
    cliff, scan = result.cliff, result.scan
    if (
        cliff is not None
        and result.pose is None
        and result.memory is None
        and result.warning is None
        and not result.sensors
        and type(scan.ranges) is np.ndarray
        and scan.ranges.ndim == 1
        and type(cliff.scan.ranges) is np.ndarray
        and cliff.scan.ranges.ndim == 1
    ):
        cs, timings = cliff.scan, result.timings_s
        # what else the template depends on: the same objects frame after frame, so the
        # comparison is mostly by identity (equal numbers make the same text, as in _head)
        key = (
            version,
            scan.angle_min,
            scan.angle_max,
            scan.angle_increment,
            scan.range_min,
            scan.range_max,
            cs.angle_min,
            cs.angle_max,
            cs.angle_increment,
            cs.range_min,
            cs.range_max,
            result.mount_source,
            *timings,
        )
        shape = _last_shape
        # the mount and the trust by identity, as _pose and _trust keep their texts (the daemon
        # hands every frame the same objects until they change)
        if (
            shape is None
            or shape[1] is not result.mount
            or shape[2] is not result.mount_trust
            or shape[0] != key
        ):
            shape = _new_shape(key, result, version)
        points = cliff.points_m
        try:
            numbers = array(
                "d",
                (
                    result.seq,
                    result.timestamp_s,
                    wall_time_s,
                    (points.size if type(points) is np.ndarray else np.size(points)) // 2,
                    *shape[4](timings),
                ),
            )
        except (TypeError, OverflowError):
            return None  # a value that is no number (None: the message writes null) or too large
        text = template_text(shape[3], scan.ranges, points, cs.ranges, numbers)
        return None if text is None else bytes(text)
    return _any_line(result, version, wall_time_s)


def _new_shape(key: tuple[Any, ...], result: Result, version: str) -> _Shape:
    """The template of a frame with a cliff and no floor estimate, memory, warning or several
    sensors, and what takes its timings' values; kept as the last shape (one tuple, replaced
    whole: threads read it)."""
    global _last_shape  # noqa: PLW0603 - a one-entry cache
    timings_text, timing_values = _timings(tuple(result.timings_s))
    template = _template(result, version, timings_text)
    shape = (key, result.mount, result.mount_trust, template, timing_values)
    _last_shape = shape
    return shape


def _template(result: Result, version: str, timings_text: bytes) -> bytes:
    """The frame's template: its text made of the pieces, with markers where the numbers go."""
    cliff, memory, warning = result.cliff, result.memory, result.warning
    if cliff is None:
        cliff_text = _NO_CLIFF
    else:
        cliff_text = b"".join(
            (
                _CLIFF_START,
                _scan_head(cliff.scan),
                _TRUSTED if dropoffs_trusted(result) else _NOT_TRUSTED,
            )
        )
    return b"".join(
        (
            _prefix(version),
            _scan_head(result.scan),
            _SCAN_END,
            cliff_text,
            b',"pose":',
            _pose(result),
            b',"mount":',
            _trust(result),
            b',"memory":',
            b"null" if memory is None else orjson.dumps(memory_to_json(memory)),
            b',"sensors":null,"timings_s":',
            timings_text,
            b',"warning":',
            b"null" if warning is None else orjson.dumps(warning),
            b',"message":null}\n',
        )
    )


def _any_line(result: Result, version: str, wall_time_s: float) -> bytes | None:
    """:func:`_line` of any frame: its template made of the pieces anew."""
    if result.sensors:
        return None
    scan, cliff = result.scan, result.cliff
    if not _is_flat(scan.ranges) or (cliff is not None and not _is_flat(cliff.scan.ranges)):
        return None
    timings = result.timings_s
    timings_text, timing_values = _timings(tuple(timings))
    # the values of the template's SECONDS and INTEGER markers, in the order of the markers
    values: tuple[Any, ...] = (result.seq, result.timestamp_s, wall_time_s)
    if cliff is not None:
        points = cliff.points_m
        values += ((points.size if type(points) is np.ndarray else np.size(points)) // 2,)
    template = _template(result, version, timings_text)
    try:
        numbers = array("d", values + timing_values(timings))
    except (TypeError, OverflowError):
        return None  # a value that is no number (None: the message writes null) or too large
    if cliff is None:
        text = template_text(template, scan.ranges, None, None, numbers)
    else:
        text = template_text(template, scan.ranges, cliff.points_m, cliff.scan.ranges, numbers)
    return None if text is None else bytes(text)


def _is_flat(values: Any) -> bool:
    """np.ndim(values) == 1, quicker for an array."""
    return values.ndim == 1 if type(values) is np.ndarray else np.ndim(values) == 1


# the template's fixed pieces (json_template's markers where the numbers go)
_SCAN_END = FLAT + b"}"
_NO_CLIFF = b',"cliff":null'
_CLIFF_START = b"".join(
    (b',"cliff":{"points_m":', PAIRS, b',"points_total":', INTEGER, b',"points_dropped":0,"scan":')
)
_TRUSTED = FLAT + b'},"trusted":true}'
_NOT_TRUSTED = FLAT + b'},"trusted":false}'


@functools.lru_cache(maxsize=8)
def _prefix(version: str) -> bytes:
    """The line's text up to its scan's head."""
    return b"".join(
        (
            b'{"v":%d,"version":' % SCHEMA_VERSION,
            orjson.dumps(version),
            b',"seq":',
            INTEGER,
            b',"t_s":',
            SECONDS,
            b',"wall_s":',
            SECONDS,
            b',"scan":',
        )
    )


@functools.lru_cache(maxsize=64)
def _timings(keys: tuple[str, ...]) -> tuple[bytes, Callable[[dict[str, float]], tuple[Any, ...]]]:
    """The timings object's template for a dict with these keys (in its order): the keys sorted,
    a SECONDS marker for each value; and what takes the values from the dict in that order."""
    ordered = sorted(keys)
    text = b"{%b}" % b",".join(orjson.dumps(k) + b":" + SECONDS for k in ordered)
    if len(ordered) > 1:
        return text, operator.itemgetter(*ordered)
    return text, lambda timings: tuple(timings[k] for k in ordered)


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


def _pose(result: Result) -> bytes:
    """The pose object's text: made once per mount when the frame has no floor estimate."""
    global _last_pose  # noqa: PLW0603 - a one-entry cache
    if result.pose is not None:
        return orjson.dumps(_pose_to_json(result))
    m, source = result.mount, result.mount_source
    last = _last_pose
    if last is not None and last[0] is m and last[1] == source:
        return last[2]
    text = orjson.dumps(dict(_mount_json(m, source)))
    _last_pose = (m, source, text)
    return text


def _trust(result: Result) -> bytes:
    """The mount object's text (its trust; ``null`` when nobody assessed it): made once per
    verdict."""
    global _last_trust  # noqa: PLW0603 - a one-entry cache
    t = result.mount_trust
    if t is None:
        return b"null"
    last = _last_trust
    if last is not None and last[0] is t:
        return last[1]
    text = orjson.dumps(_trust_json(t))
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
            the whole object (then :func:`frame_json`, the line the sinks share, when it fits).

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
