"""The ros2 sink's template CDR (sinks/ros/cdr.py) is, byte for byte, rosbags' CDR of the messages
``MessageBuilder`` makes (padded as DDS wants): over frames whose mount, cliff, ranges (NaN,
+inf, -inf) and point counts change, with other frame names, without /tf, with the image."""

from __future__ import annotations

import dataclasses
import math
import struct

import numpy as np
import pytest

from depthnav_daemon.pipeline.cliff import CliffResult
from depthnav_daemon.pipeline.geometry import Mount
from depthnav_daemon.sinks.ros.cdr import CdrEncoder, dds_bytes
from depthnav_daemon.sinks.ros.messages import NAME_OPTIONS, MessageBuilder, RosNames, typestore
from tests.sinks.conftest import make_pair

NAMES = {
    "defaults": RosNames(dict(NAME_OPTIONS)),
    # odd lengths move every later field's alignment; no /tf; with the image and CameraInfo
    "other names, no tf, image": RosNames(
        {**NAME_OPTIONS, "base_frame": "b", "scan_frame": "scan_xyz", "optical_frame": "o1"},
        tf=False,
        image=True,
    ),
}
STAMPS = (None, 0, 1_700_000_000_123_456_789, 2**31 * 10**9 - 1)


def _rosbags(builder: MessageBuilder, frame, result, t_ns) -> list[tuple[str, bytes]]:
    _, messages = builder.messages(frame, result, t_ns=t_ns)
    store = builder.store
    return [
        (topic, bytes(dds_bytes(store.serialize_cdr(m, m.__msgtype__)))) for topic, m in messages
    ]


def _frames() -> list:
    """Frames whose mount, scans and cliff points differ, in an order that returns to earlier
    mounts (templates reused) and with special ranges and points."""
    out = [make_pair(seq, Mount(0.5 + 0.01 * seq, 12.0 + seq, 1.5 - seq)) for seq in range(3)]
    frame, result = out[0]
    ranges = np.array(result.scan.ranges, dtype=np.float32)
    ranges[:5] = [math.nan, math.inf, -math.inf, 0.0, -0.0]
    scan = dataclasses.replace(result.scan, ranges=ranges)
    out.append((frame, dataclasses.replace(result, scan=scan)))
    cliff = result.cliff
    assert isinstance(cliff, CliffResult) and len(cliff.points_m) > 2
    pts = np.array(cliff.points_m, dtype=np.float32)
    pts[1] = [math.nan, 1.0]
    out.append((frame, dataclasses.replace(result, cliff=dataclasses.replace(cliff, points_m=pts))))
    none = dataclasses.replace(cliff, points_m=np.zeros((0, 2), np.float32))
    out.append((frame, dataclasses.replace(result, cliff=none)))
    out.append(make_pair(9, Mount(0.8, 40.0, 5.0, x_m=0.1, y_m=-0.05, yaw_deg=30.0), cliff=False))
    out.append(out[1])
    return out


@pytest.mark.parametrize("names", NAMES.values(), ids=NAMES.keys())
def test_every_message_is_rosbags_cdr_byte_for_byte(names):
    builder = MessageBuilder(typestore(ros1=False), names)
    encoder = CdrEncoder(builder)
    for i, (frame, result) in enumerate(_frames()):
        t_ns = STAMPS[i % len(STAMPS)]
        got = [(topic, bytes(data)) for topic, data in encoder.encode(frame, result, t_ns)]
        assert got == _rosbags(builder, frame, result, t_ns), f"frame {i}"


def test_the_templates_are_used_and_the_stamp_lands_in_every_header():
    """Not the fallback: scans, cloud, pose and /tf come from templates, each stamped."""
    builder = MessageBuilder(typestore(ros1=False), NAMES["defaults"])
    encoder = CdrEncoder(builder)
    frame, result = make_pair(0)
    t_ns = 1_700_000_000_123_456_789
    got = dict(encoder.encode(frame, result, t_ns))
    assert all(v is not None for v in encoder._scans.values())
    assert all(v is not None for v in encoder._mounts.values())
    assert encoder._points is not None
    stamp = struct.pack("<iI", 1_700_000_000, 123_456_789)
    headers = {"/scan": 1, "/cliff/scan": 1, "/cliff/points": 1, "/depth_sensor_pose": 1, "/tf": 2}
    assert {topic: bytes(data).count(stamp) for topic, data in got.items()} == headers
    assert all(len(data) % 4 == 0 and data[3] == (data[3] & 3) for data in got.values())
