"""The JSON line the stdout and udp sinks share (json_line.frame_line) is the message's line, byte
for byte: ``orjson.dumps(jsonmsg.frame_message(...))`` and a newline, for every kind of frame the
daemon sends; it is made once per Result."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import orjson

from depthnav_daemon.pipeline import MountTrust
from depthnav_daemon.pipeline.merge import SensorState
from depthnav_daemon.sinks.json import line as json_line
from depthnav_daemon.sinks.json import message as jsonmsg
from tests.sinks.conftest import with_memory

DOUBT = MountTrust(
    source="default",
    floor="contradicted",
    floor_height_m=0.61234,
    floor_tilt_deg=14.56789,
    floor_roll_deg=-0.5,
    dropoffs_trusted=False,
    note="the floor says 0.612 m, 14.6 deg",
)


def _variants(pairs):
    """(name, frame, result): the kinds of frames a daemon sends."""
    frame, result = pairs[1]
    _, with_pose = pairs[2]  # this frame's floor estimate
    _, warned = pairs[3]
    cliff = result.cliff
    assert cliff is not None and with_pose.pose is not None and warned.warning
    special = result.scan.ranges.copy()
    special[:4] = [np.nan, np.inf, -np.inf, -0.0]
    yield "plain", frame, result
    yield "floor estimate", frame, with_pose
    yield "warning", frame, warned
    yield "no cliff stage", frame, replace(result, cliff=None)
    yield "special ranges", frame, replace(result, scan=replace(result.scan, ranges=special))
    yield (
        "no cliff points",
        frame,
        replace(result, cliff=replace(cliff, points_m=np.zeros((0, 2), np.float32))),
    )
    trusted = replace(result.mount_state, trust=MountTrust(floor="confirmed"))
    yield "trusted", frame, replace(result, mount_state=trusted)
    doubtful = replace(result.mount_state, trust=DOUBT)
    yield "not trusted", frame, replace(result, mount_state=doubtful, warning=DOUBT.note)
    yield "memory", frame, with_memory(result)
    yield (
        "more timings",
        frame,
        replace(
            result, timings_s={"scan": 0.0012345, "pose": 0.0009, "cliff": 5.5e-05, "memory": 1e-9}
        ),
    )
    yield "control characters", frame, replace(warned, warning="a\x01b\x02c\x03d\x04\n")
    yield "one timing", frame, replace(result, timings_s={"scan": 0.5})
    yield "no timings", frame, replace(result, timings_s={})
    yield (
        "float64 ranges",
        frame,
        replace(result, scan=replace(result.scan, ranges=result.scan.ranges.astype(np.float64))),
    )


def test_the_line_is_the_messages_line_for_every_kind_of_frame(pairs) -> None:
    for name, frame, result in _variants(pairs):
        line = json_line.frame_line(frame, result, "1.2.3", 1796194456.0331335)
        want = orjson.dumps(jsonmsg.frame_message(frame, result, "1.2.3", 1796194456.0331335))
        assert line == want + b"\n", name
        assert json_line.frame_json(frame, result, "1.2.3", 0.0) == want, name
        assert b"NaN" not in line and b"Infinity," not in line  # strict JSON: codes are strings


def test_special_ranges_keep_their_codes_in_the_line(pairs) -> None:
    frame, result = pairs[1]
    ranges = np.array([np.nan, np.inf, -np.inf, -0.0, 1.23449, 1.2355, 1e13], np.float64)
    res = replace(result, scan=replace(result.scan, ranges=ranges))
    got = orjson.loads(json_line.frame_line(frame, res, "1", 2.0))["scan"]["ranges"]
    assert got == [None, "Infinity", "-Infinity", -0.0, 1.234, 1.236, 1e13]
    assert got == jsonmsg.encode_ranges(ranges)
    back = jsonmsg.decode_ranges(got)
    assert np.isnan(back[0]) and back[1] == np.inf and back[2] == -np.inf


def test_the_line_is_made_once_per_result_and_shared(pairs) -> None:
    """The sinks of one frame get the same bytes (and so the same wall_s); the next Result or
    another version makes a new line."""
    (f0, r0), (f1, r1) = pairs[0], pairs[1]
    first = json_line.frame_line(f0, r0, "1", 2.0)
    assert json_line.frame_line(f0, r0, "1", 9.0) is first  # the second sink of the frame
    assert orjson.loads(first)["wall_s"] == 2.0
    other = json_line.frame_line(f1, r1, "1", 3.0)
    assert orjson.loads(other)["seq"] == r1.seq and orjson.loads(other)["wall_s"] == 3.0
    assert json_line.frame_line(f1, r1, "2", 4.0) != other


def test_frames_the_numbers_cannot_describe_plainly_still_make_strict_json(pairs) -> None:
    """Several sensors, cliff points that are not finite, a timing that is not a number, a time
    of 2**33 s: the line is still the message's and strict JSON."""
    frame, result = pairs[1]
    assert result.cliff is not None
    bad = np.array(result.cliff.points_m, dtype=np.float32)
    bad[0] = [np.nan, 1.0]
    sensors = (SensorState("left", "ok", 0.01, result), SensorState("right", "stale", 0.9, None))
    for res in (
        replace(result, cliff=replace(result.cliff, points_m=bad)),
        replace(result, sensors=sensors),
        replace(result, timings_s={"scan": None, "cliff": 0.001}),
        replace(result, timestamp_s=2.0**33),
    ):
        line = json_line.frame_line(frame, res, "1", 2.0)
        assert line == orjson.dumps(jsonmsg.frame_message(frame, res, "1", 2.0)) + b"\n"
        msg = orjson.loads(line)
        assert msg["seq"] == result.seq
    dropped = orjson.loads(
        json_line.frame_line(
            frame, replace(result, cliff=replace(result.cliff, points_m=bad)), "1", 2.0
        )
    )["cliff"]
    assert dropped["points_dropped"] == 1 and len(dropped["points_m"]) == len(bad) - 1
