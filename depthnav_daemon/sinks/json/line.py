"""The frame's JSON line as bytes, made once a frame and shared by the ``stdout`` and ``udp`` sinks.

The line is ``orjson.dumps(message.frame_message(...))`` and a newline: the message's dicts, its
arrays through numpy (rounded to 1 mm, ``tolist``), one orjson call. It costs 0.1-0.15 ms a frame
at 640x480 and 1280x720 (0.3-0.5 % of a core at 30 frames/s; ``depthnav bench``, the JSON line's
row); docs/performance-notes.md says why no hand-written writer replaces it.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import TYPE_CHECKING, Any

import numpy as np
import orjson

from depthnav_daemon.sinks.json.message import frame_message

if TYPE_CHECKING:
    from depthnav_daemon.pipeline import Result
    from drivers.base import Frame

# The last frame's line: (result, version, UTF-8 JSON). Every sink that sends the whole object
# (stdout, udp with content=all) gets these bytes: made once a frame, not once a sink.
_last_line: list[tuple[Any, str, bytes]] = []


def frame_line(frame: Frame, result: Result, version: str, wall_time_s: float) -> bytes:
    """:func:`message.frame_message` of the frame as compact UTF-8 JSON and a newline (what the
    stdout sink writes; the udp sink sends it without the newline), made once per Result.

    The sinks of one frame share it, so they also share its ``wall_s`` (the time the first one
    asked). A new Result (the next frame) or another version makes a new line.
    """
    for last_result, last_version, last_data in _last_line[-1:]:
        if last_result is result and last_version == version:
            return last_data
    data = orjson.dumps(frame_message(frame, result, version, wall_time_s)) + b"\n"
    _last_line[:] = [(result, version, data)]  # one entry, replaced whole (threads read it)
    return data


def frame_json(frame: Frame, result: Result, version: str, wall_time_s: float) -> bytes:
    """:func:`frame_line` without its newline (a copy)."""
    return frame_line(frame, result, version, wall_time_s)[:-1]


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
