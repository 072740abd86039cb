"""Odometry in: the buffer's interpolation, JSON lines over loopback UDP and MAVLink from a real
pymavlink peer, and ``odom`` in recordings (write, read, stream, replay, bad shapes)."""

from __future__ import annotations

import dataclasses
import json
import logging
import math
import os
import socket

import numpy as np
import pytest

from drivers import create_driver
from drivers.errors import DeviceOpenError, DeviceSpecError, RecordingError
from drivers.formats.recording import open_recording_stream, read_recording
from drivers.formats.recording_writer import write_recording
from drivers.odometry import OdomBuffer, create_odometry
from drivers.odometry.mavlink import MavlinkOdometry, quaternion_yaw
from drivers.odometry.udp import OdometryLineError, parse_odometry_line
from tests.drivers.driverkit import SMALL, free_udp_port, ramp_frames, wait_until


def test_buffer_interpolates_and_turns_the_short_way_across_pi() -> None:
    b = OdomBuffer()
    assert b.pose_at(0.0) is None
    b.add(1.0, 0.0, 0.0, math.radians(170))
    b.add(2.0, 1.0, -2.0, math.radians(-170))  # 20 deg further counter-clockwise, not 340 back
    pose, age = b.pose_at(1.5)
    assert pose[:2] == pytest.approx((0.5, -1.0)) and age == 0.0
    assert math.degrees(pose[2]) == pytest.approx(180.0)
    assert b.pose_at(0.5) is None  # before the first sample: no guess
    pose, age = b.pose_at(2.7)  # after the last: held, never extrapolated; the age says how old
    assert pose[:2] == (1.0, -2.0) and age == pytest.approx(0.7)
    assert not b.add(1.5, 0, 0, 0)  # back in time
    assert not b.add(3.0, math.nan, 0, 0)
    assert b.count == 2


def test_buffer_is_bounded() -> None:
    b = OdomBuffer(maxlen=10)
    for i in range(1000):
        b.add(float(i), float(i), 0.0, 0.0)
    assert b.pose_at(989.5) is None and b.pose_at(995.5)[0][0] == pytest.approx(995.5)


@pytest.mark.parametrize(
    ("line", "kind", "why"),
    [
        (b"not json", "malformed", "not JSON"),
        (b"[1, 2]", "malformed", "not a JSON object"),
        (b'{"x_m": 1, "y_m": 2}', "malformed", "yaw_rad is missing"),
        (b'{"x_m": true, "y_m": 0, "yaw_rad": 0}', "malformed", "x_m=True is not a number"),
        (b'{"x_m": 1e999, "y_m": 0, "yaw_rad": 0}', "not_finite", "x_m=inf is not finite"),
    ],
)
def test_bad_lines_are_named(line: bytes, kind: str, why: str) -> None:
    with pytest.raises(OdometryLineError, match=why) as info:
        parse_odometry_line(line, need_time=False)
    assert info.value.kind == kind


def test_json_lines_over_loopback_udp(caplog) -> None:
    port = free_udp_port()
    src = create_odometry(f"odom+udp://127.0.0.1:{port}?clock=message")
    src.start()
    try:
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as tx:
            lines = [
                {"t_s": 10.0 + i, "x_m": 0.1 * i, "y_m": -0.05 * i, "yaw_rad": 0.2 * i}
                for i in range(3)
            ]
            tx.sendto(b"\n".join(json.dumps(x).encode() for x in lines), ("127.0.0.1", port))
            with caplog.at_level(logging.WARNING):
                tx.sendto(b'{"x_m": "oops"}\n', ("127.0.0.1", port))
                # the receiver counts the line, then logs it: wait for both (on a loaded machine
                # the log record came after the count)
                wait_until(
                    lambda: (
                        src.bad_messages == 1
                        and src.buffer.count == 3
                        and any("oops" in r.getMessage() for r in caplog.records)
                    )
                )
        pose, age = src.buffer.pose_at(11.5)  # matched by the sender's t_s
        assert pose == pytest.approx((0.15, -0.075, 0.3)) and age == 0.0
        # one line naming the problem, never a traceback
        msgs = [r.getMessage() for r in caplog.records if "odometry" in r.getMessage()]
        assert len(msgs) == 1 and "x_m='oops'" in msgs[0] and "\n" not in msgs[0]
    finally:
        src.stop()
        src.stop()  # twice is fine


def test_udp_odometry_refuses_a_non_loopback_address_and_a_busy_port() -> None:
    with pytest.raises(DeviceSpecError, match="not a loopback address"):
        create_odometry("odom+udp://192.0.2.1:5700")
    with pytest.raises(DeviceSpecError, match="unknown option"):
        create_odometry("odom+udp://127.0.0.1:5700?rate=3")
    with pytest.raises(DeviceSpecError, match="unknown odometry source"):
        create_odometry("gps://x")
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as busy:
        busy.bind(("127.0.0.1", 0))
        src = create_odometry(f"odom+udp://127.0.0.1:{busy.getsockname()[1]}")
        with pytest.raises(DeviceOpenError, match="cannot listen"):
            src.start()


def test_mavlink_local_position_and_attitude_from_a_real_peer() -> None:
    os.environ.setdefault("MAVLINK20", "1")
    from pymavlink import mavutil

    port = free_udp_port()
    src = create_odometry(f"mavlink+udp://127.0.0.1:{port}")
    assert isinstance(src, MavlinkOdometry)
    src.start()
    tx = mavutil.mavlink_connection(f"udpout:127.0.0.1:{port}", source_system=1)
    try:
        # NED: 2 m north, 0.5 m EAST (= right, so y = -0.5 in REP 103), heading 30 deg CLOCKWISE
        # from north (= yaw -30 deg counter-clockwise)
        def send() -> None:
            tx.mav.attitude_send(1000, 0.0, 0.0, math.radians(30.0), 0.0, 0.0, 0.0)
            tx.mav.local_position_ned_send(1000, 2.0, 0.5, 0.0, 0.0, 0.0, 0.0)

        wait_until(lambda: send() or src.buffer.count > 0)
        latest = src.buffer.latest()
        assert (latest.x_m, latest.y_m) == pytest.approx((2.0, -0.5))
        assert math.degrees(latest.yaw_rad) == pytest.approx(-30.0, abs=1e-4)
    finally:
        src.stop()
        tx.close()


def test_mavlink_odometry_message_ned_and_flu() -> None:
    src = MavlinkOdometry("udpin:127.0.0.1:1")
    q = (math.cos(math.radians(20)), 0.0, 0.0, math.sin(math.radians(20)))  # yaw 40 deg
    assert math.degrees(quaternion_yaw(*q)) == pytest.approx(40.0)

    from pymavlink.dialects.v20 import common as mavlink2

    def msg(frame_id: int):  # a real decoded-message object, as recv_match returns it
        cov = [math.nan] * 21
        return mavlink2.MAVLink_odometry_message(
            0, frame_id, 12, 1.0, 2.0, 0.0, q, 0, 0, 0, 0, 0, 0, cov, cov
        )

    src.take(msg(1), 1.0)  # LOCAL_NED: y and yaw change sign
    src.take(msg(21), 2.0)  # LOCAL_FLU: as is
    src.take(msg(8), 3.0)  # another frame: counted, ignored
    a, b = src.buffer.pose_at(1.0)[0], src.buffer.pose_at(2.0)[0]
    assert a == pytest.approx((1.0, -2.0, math.radians(-40.0)))
    assert b == pytest.approx((1.0, 2.0, math.radians(40.0)))
    assert src.bad_messages == 1 and src.buffer.count == 2


def test_recording_round_trips_odometry(tmp_path) -> None:
    odom = [(0.1 * i, -0.02 * i, 0.3 * i) for i in range(4)]
    frames = [dataclasses.replace(f, odom=o) for f, o in zip(ramp_frames(4), odom, strict=True)]
    write_recording(tmp_path / "r", frames)
    rec = read_recording(tmp_path / "r")
    np.testing.assert_array_equal(rec.odom, np.array(odom))
    assert [f.odom for f in rec.frames()] == odom
    assert open_recording_stream(tmp_path / "r").odom.tolist() == [list(o) for o in odom]
    # replay hands it over on every Frame
    drv = create_driver(f"replay:{tmp_path / 'r'}?rate=max")
    drv.open()
    try:
        got = [drv.read_frame(1.0).odom for _ in range(4)]
    finally:
        drv.close()
    assert got == odom


def test_partial_odometry_is_not_stored(tmp_path, caplog) -> None:
    frames = ramp_frames(3)
    frames[1] = dataclasses.replace(frames[1], odom=(1.0, 0.0, 0.0))
    with caplog.at_level(logging.WARNING):
        write_recording(tmp_path / "r", frames)
    assert read_recording(tmp_path / "r").odom is None
    assert any("only some frames had odometry" in r.getMessage() for r in caplog.records)


@pytest.mark.parametrize(
    ("odom", "why"),
    [
        (np.zeros((3, 2)), r"'odom' must be \(3, 3\) numbers \[x_m, y_m, yaw_rad\]"),
        (np.zeros((4, 3)), r"'odom' must be \(3, 3\)"),
        (np.array([["a", "b", "c"]] * 3), r"'odom' must be \(3, 3\) numbers"),
    ],
)
def test_bad_odometry_in_a_bare_npz_is_one_line(tmp_path, odom, why: str) -> None:
    frames = ramp_frames(3, accel=False)
    np.savez(
        tmp_path / "x.npz",
        depth_mm=np.stack([f.depth_mm for f in frames]),
        intrinsics=SMALL.as_array(),
        odom=odom,
    )
    with pytest.raises(RecordingError, match=why) as info:
        read_recording(tmp_path / "x.npz")
    assert "\n" not in str(info.value) and "x.npz" in str(info.value)
