"""Odometry bounds: one check for every sample (drivers.base.check_odom_pose / check_odom_time,
drivers.odometry.check_sample), the per-kind counts and their warnings, and the receivers that use
them: JSON lines over a real loopback socket, MAVLink from a real pymavlink peer, and a
recording's ``odom`` rows."""

from __future__ import annotations

import json
import logging
import math
import os
import re
import socket

import numpy as np
import pytest

from drivers.base import (
    ODOM_POSITION_LIMIT_M,
    ODOM_TIME_LIMIT_S,
    ODOM_YAW_LIMIT_RAD,
    OdomRefusal,
    check_odom_pose,
)
from drivers.formats.recording import read_recording
from drivers.odometry import OdomBuffer, OdomRefusals, OdomSample, check_sample, create_odometry
from drivers.odometry.mavlink import MavlinkOdometry
from drivers.odometry.udp import OdometryLineError, parse_odometry_line
from tests.drivers.driverkit import SMALL, free_udp_port, ramp_frames, wait_until

HUGE = 10**400  # a 401-digit integer: float() of it raises OverflowError
DEEP = b"[" * 60_000 + b"]" * 60_000  # RecursionError in the JSON parser
DEEP_DATAGRAM = b"[" * 60_000  # as deep, in one datagram (the parser recurses before it ends)


@pytest.mark.parametrize(
    ("sample", "kind", "says"),
    [
        ((0.0, 1e19, 0.0, 0.0), "out_of_range", "x_m=1e+19 is beyond +-1e+07 m"),
        ((0.0, 1e308, 0.0, 0.0), "out_of_range", "x_m=1e+308 is beyond"),
        ((0.0, 0.0, -1e308, 0.0), "out_of_range", "y_m=-1e+308 is beyond"),
        ((0.0, math.nan, 0.0, 0.0), "not_finite", "x_m=nan is not finite"),
        ((0.0, 0.0, 0.0, math.inf), "not_finite", "yaw_rad=inf is not finite"),
        ((0.0, HUGE, 0.0, 0.0), "out_of_range", "x_m=<integer of 401 digits> is beyond"),
        ((HUGE, 0.0, 0.0, 0.0), "out_of_range", "t_s=<integer of 401 digits> is beyond"),
        ((0.0, -(10**5000), 0.0, 0.0), "out_of_range", "x_m=<-integer of about 5001 digits>"),
        ((0.0, True, 0.0, 0.0), "malformed", "x_m=True is not a number"),
        ((0.0, 0.0, "1.0", 0.0), "malformed", "y_m='1.0' is not a number"),
        ((None, 0.0, 0.0, 0.0), "malformed", "t_s=None is not a number"),
        ((0.0, [1.0], 0.0, 0.0), "malformed", "x_m=[1.0] is not a number"),
        ((0.0, np.uint64(2**64 - 1), 0.0, 0.0), "out_of_range", "x_m=18446744073709551615"),
        ((0.0, 0.0, 0.0, 1e19), "out_of_range", "yaw_rad=1e+19 is beyond +-1e+06 rad"),
        ((1e300, 0.0, 0.0, 0.0), "out_of_range", "t_s=1e+300 is beyond +-1e+10 s"),
    ],
)
def test_a_hostile_value_is_refused_with_its_kind_and_a_short_reason(sample, kind, says) -> None:
    got = check_sample(*sample)
    assert isinstance(got, OdomRefusal), got
    assert got.kind == kind and says in got.reason and str(got) == got.reason
    assert len(got.reason) < 100 and "\n" not in got.reason


def test_the_limits_are_inclusive_and_the_next_float_is_refused() -> None:
    over_m = math.nextafter(ODOM_POSITION_LIMIT_M, math.inf)
    assert check_odom_pose(ODOM_POSITION_LIMIT_M, -ODOM_POSITION_LIMIT_M, 0.0) == (1e7, -1e7, 0.0)
    assert check_odom_pose(over_m, 0.0, 0.0).kind == "out_of_range"
    assert check_odom_pose(0.0, -over_m, 0.0).kind == "out_of_range"
    assert check_odom_pose(10_000_000, 0, 0) == (1e7, 0.0, 0.0)  # integers compared exactly
    assert check_odom_pose(10_000_001, 0, 0).kind == "out_of_range"
    # yaw: up to 1e6 rad (an unwrapping source, 160,000 turns), wrapped to [-pi, pi]
    yaw = check_odom_pose(0.0, 0.0, ODOM_YAW_LIMIT_RAD)[2]
    assert -math.pi <= yaw <= math.pi and math.cos(yaw) == pytest.approx(math.cos(1e6), abs=1e-9)
    assert check_odom_pose(0.0, 0.0, math.nextafter(1e6, math.inf)).kind == "out_of_range"
    assert check_odom_pose(0.0, 0.0, 7.0)[2] == pytest.approx(7.0 - 2 * math.pi)
    assert check_sample(ODOM_TIME_LIMIT_S, 0, 0, 0) == OdomSample(1e10, 0.0, 0.0, 0.0)
    assert check_sample(-ODOM_TIME_LIMIT_S - 1, 0, 0, 0).kind == "out_of_range"
    # numpy scalars, as a recording's rows give them
    assert check_odom_pose(np.float32(1.5), np.int16(-2), np.float64(0.5)) == (1.5, -2.0, 0.5)


@pytest.mark.parametrize(
    ("line", "kind", "says"),
    [
        (DEEP, "malformed", "nested too deeply"),
        (b'{"x_m": ' + b"9" * 400 + b', "y_m": 0, "yaw_rad": 0}', "out_of_range", "400 digits"),
        (b'{"x_m": 0, "y_m": 0, "yaw_rad": 0, "t_s": ' + b"1" * 400 + b"}", "out_of_range", "t_s"),
        (b'{"x_m": ' + b"9" * 5000 + b', "y_m": 0, "yaw_rad": 0}', "malformed", "not JSON"),
        (b'{"x_m": NaN, "y_m": 0, "yaw_rad": 0}', "not_finite", "x_m=nan"),
        (b'{"x_m": 1e308, "y_m": 0, "yaw_rad": 0}', "out_of_range", "x_m=1e+308"),
        (b'{"x_m": 1e19, "y_m": 0, "yaw_rad": 0}', "out_of_range", "x_m=1e+19"),
        (b'{"x_m": "1.0", "y_m": 0, "yaw_rad": 0}', "malformed", "x_m='1.0'"),
        (b'"a string"', "malformed", "not a JSON object but str"),
        (b"\xff\xfe garbage", "malformed", "not JSON"),
    ],
)
def test_a_hostile_line_is_one_refusal_never_an_exception(line: bytes, kind: str, says) -> None:
    with pytest.raises(OdometryLineError, match=re.escape(says)) as info:
        parse_odometry_line(line, need_time=False)
    assert info.value.kind == kind and len(str(info.value)) < 100


def test_the_buffer_offers_never_raise_and_name_time_going_back() -> None:
    b = OdomBuffer()
    assert b.offer(1.0, 0.0, 0.0, 0.0) is None
    assert b.offer(2.0, HUGE, 0, 0).kind == "out_of_range"
    assert b.offer(2.0, math.nan, 0, 0).kind == "not_finite"
    back = b.offer(0.5, 0.0, 0.0, 0.0)
    assert back.kind == "out_of_order" and "t_s=0.5" in back.reason
    assert not b.add(3.0, 1e308, 0, 0) and b.count == 1
    # yaw kept wrapped, interpolated the short way (a long spin never grows it)
    for i in range(2, 400):
        assert b.add(float(i), 0.0, 0.0, 1.0 * i)
    assert abs(b.latest().yaw_rad) <= math.pi
    pose, _ = b.pose_at(399.5)
    assert abs(pose[2]) <= math.pi


class FakeClock:
    def __init__(self) -> None:
        self.t = 100.0

    def __call__(self) -> float:
        return self.t


def test_warned_once_per_kind_then_a_summary_at_most_every_minute(caplog) -> None:
    clock = FakeClock()
    r = OdomRefusals("test", clock=clock)
    bad = {
        "out_of_range": OdomRefusal("out_of_range", "x_m=1e+19 is beyond +-1e+07 m"),
        "not_finite": OdomRefusal("not_finite", "x_m=nan is not finite"),
    }
    with caplog.at_level(logging.WARNING, logger="drivers.odometry"):
        for _ in range(50):
            r.note(bad["out_of_range"], "frame 3")
            r.note(bad["not_finite"])
            clock.t += 0.5  # 25 s in all: no summary yet
        said = [rec.getMessage() for rec in caplog.records]
        assert len(said) == 2
        assert "(out_of_range) at frame 3: x_m=1e+19 is beyond" in said[0]
        assert "(not_finite): x_m=nan" in said[1]
        clock.t += 40.0  # a minute after the first warning: the next refusal brings a summary
        r.note(bad["not_finite"])
        r.note(bad["not_finite"])  # and the one after it is quiet again
        said = [rec.getMessage() for rec in caplog.records]
        assert len(said) == 3
        assert (
            "refused 99 more samples since the last report (50 not_finite, 49 out_of_range)"
            in (said[2])
        )
        assert "101 in all" in said[2]
        r.flush()  # the one since
        assert "refused 1 more samples" in caplog.records[-1].getMessage()
        r.flush()  # nothing new: nothing said
        assert len(caplog.records) == 4
    assert r.counts() == {"malformed": 0, "not_finite": 52, "out_of_range": 50, "out_of_order": 0}
    assert r.total == 102


def test_the_udp_receiver_refuses_every_hostile_line_and_takes_the_next_good_one(caplog) -> None:
    port = free_udp_port()
    src = create_odometry(f"odom+udp://127.0.0.1:{port}?clock=message")
    hostile = [
        b'{"t_s": 1, "x_m": ' + b"7" * 400 + b', "y_m": 0, "yaw_rad": 0}',  # out_of_range
        b'{"t_s": ' + b"7" * 400 + b', "x_m": 0, "y_m": 0, "yaw_rad": 0}',  # out_of_range
        b'{"t_s": 1, "x_m": 1e308, "y_m": 0, "yaw_rad": 0}',  # out_of_range
        b'{"t_s": 1, "x_m": 1e19, "y_m": 0, "yaw_rad": 0}',  # out_of_range
        b'{"t_s": 1, "x_m": NaN, "y_m": 0, "yaw_rad": 0}',  # not_finite
        b'{"t_s": 1, "x_m": 0, "y_m": -Infinity, "yaw_rad": 0}',  # not_finite
        DEEP_DATAGRAM,  # malformed (RecursionError)
        b"[1, 2, 3]",  # malformed
        b"\x00\xff garbage \x1b[31m",  # malformed
        b'{"t_s": 1, "x_m": true, "y_m": 0, "yaw_rad": 0}',  # malformed
    ]
    src.start()
    try:
        with (
            caplog.at_level(logging.WARNING),
            socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as tx,
        ):
            for line in hostile:
                tx.sendto(line, ("127.0.0.1", port))
            good = {"t_s": 5.0, "x_m": 1.25, "y_m": -0.5, "yaw_rad": 0.3}
            tx.sendto(json.dumps(good).encode(), ("127.0.0.1", port))
            wait_until(lambda: src.buffer.count == 1)
            # time going back after the good line: refused, counted
            tx.sendto(b'{"t_s": 4, "x_m": 0, "y_m": 0, "yaw_rad": 0}', ("127.0.0.1", port))
            wait_until(lambda: src.refusals.total == len(hostile) + 1)
        assert src.buffer.latest() == OdomSample(5.0, 1.25, -0.5, 0.3)
        assert src.refusals.counts() == {
            "malformed": 4,
            "not_finite": 2,
            "out_of_range": 4,
            "out_of_order": 1,
        }
        assert src._thread is not None and src._thread.is_alive() and src.restarts == 0
        said = [r.getMessage() for r in caplog.records if r.name.startswith("drivers.odometry")]
        assert len(said) == 4  # one warning per kind
        assert all("\n" not in m and "\x1b" not in m and len(m) < 400 for m in said)
        assert any("400 digits" in m for m in said) and any("nan" in m for m in said)
    finally:
        src.stop()


def test_a_line_whose_handling_raises_anything_is_one_malformed_refusal(monkeypatch) -> None:
    """Each line has its own guard: whatever handling a line raises (here a stand-in for a bug
    in the parser) is a refusal of that line, not of the receiver."""
    from drivers.odometry import udp

    real = udp.parse_odometry_line

    def buggy(line: bytes, need_time: bool):
        if line.startswith(b"BOOM"):
            raise RuntimeError("a bug")
        return real(line, need_time)

    monkeypatch.setattr(udp, "parse_odometry_line", buggy)
    port = free_udp_port()
    src = create_odometry(f"odom+udp://127.0.0.1:{port}")
    src.start()
    try:
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as tx:
            tx.sendto(b'BOOM\n{"x_m": 1, "y_m": 2, "yaw_rad": 0}', ("127.0.0.1", port))
            wait_until(lambda: src.buffer.count == 1)
        assert src.refusals.counts()["malformed"] == 1 and src.restarts == 0
        assert src._thread is not None and src._thread.is_alive()
    finally:
        src.stop()


def test_a_failing_receive_loop_is_reported_and_started_again(monkeypatch, caplog) -> None:
    port = free_udp_port()
    src = create_odometry(f"odom+udp://127.0.0.1:{port}")
    real = src._receive
    failures = []

    def flaky() -> bytes | None:
        if not failures:
            failures.append(1)
            raise RuntimeError("a bug in the loop")
        return real()

    monkeypatch.setattr(src, "_receive", flaky)
    monkeypatch.setattr("drivers.odometry.udp.RESTART_PAUSE_S", 0.01)
    with caplog.at_level(logging.ERROR):
        src.start()
        try:
            with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as tx:

                def sent() -> bool:
                    tx.sendto(b'{"x_m": 1, "y_m": 2, "yaw_rad": 0}', ("127.0.0.1", port))
                    return src.buffer.count > 0

                wait_until(sent)
            assert src.restarts == 1 and src._thread.is_alive()
        finally:
            src.stop()
    said = [r.getMessage() for r in caplog.records if "receiver failed" in r.getMessage()]
    assert len(said) == 1 and "RuntimeError: a bug in the loop" in said[0]


def test_mavlink_absurd_values_from_a_real_peer_are_refused_and_reading_goes_on() -> None:
    os.environ.setdefault("MAVLINK20", "1")
    from pymavlink import mavutil

    port = free_udp_port()
    src = create_odometry(f"mavlink+udp://127.0.0.1:{port}")
    src.start()
    tx = mavutil.mavlink_connection(f"udpout:127.0.0.1:{port}", source_system=1)
    try:
        # LOCAL_POSITION_NED x is a float32 on the wire: 1e19 and NaN travel as they are
        def send_bad() -> None:
            tx.mav.attitude_send(1000, 0.0, 0.0, 0.1, 0.0, 0.0, 0.0)
            tx.mav.local_position_ned_send(1000, 1e19, 0.0, 0.0, 0.0, 0.0, 0.0)
            tx.mav.local_position_ned_send(1000, 0.0, math.nan, 0.0, 0.0, 0.0, 0.0)

        wait_until(lambda: send_bad() or src.refusals.counts()["not_finite"] > 0)
        assert src.refusals.counts()["out_of_range"] > 0 and src.buffer.count == 0

        def send_good() -> bool:
            tx.mav.attitude_send(1000, 0.0, 0.0, 0.1, 0.0, 0.0, 0.0)
            tx.mav.local_position_ned_send(1000, 2.0, 0.5, 0.0, 0.0, 0.0, 0.0)
            return src.buffer.count > 0

        wait_until(send_good)
        assert src.buffer.latest().x_m == pytest.approx(2.0)
        assert src._thread is not None and src._thread.is_alive()
    finally:
        src.stop()
        tx.close()


def test_mavlink_odometry_message_with_absurd_values_is_refused_per_kind() -> None:
    from pymavlink.dialects.v20 import common as mavlink2

    src = MavlinkOdometry("udpin:127.0.0.1:1")
    cov = [math.nan] * 21

    def odometry(x: float, y: float, q=(1.0, 0.0, 0.0, 0.0)):
        return mavlink2.MAVLink_odometry_message(
            0, 1, 12, x, y, 0.0, list(q), 0, 0, 0, 0, 0, 0, cov, cov
        )

    src.take(odometry(1e308, 0.0), 1.0)
    src.take(odometry(0.0, 1e19), 2.0)
    src.take(odometry(0.0, 0.0, q=(math.nan, 0.0, 0.0, 0.0)), 3.0)
    src.take(mavlink2.MAVLink_attitude_message(0, 0.0, 0.0, math.inf, 0.0, 0.0, 0.0), 4.0)
    src.take(odometry(1.0, 2.0), 5.0)
    assert src.refusals.counts() == {
        "malformed": 0,
        "not_finite": 2,
        "out_of_range": 2,
        "out_of_order": 0,
    }
    assert src.buffer.count == 1 and src.buffer.latest().x_m == 1.0


@pytest.mark.parametrize(
    "row",
    [
        np.array([1e19, 0.0, 0.0]),
        np.array([1e308, 0.0, 0.0]),
        np.array([np.nan, 0.0, 0.0]),
        np.array([0.0, -np.inf, 0.0]),
        np.array([2**64 - 1, 0, 0], dtype=np.uint64),
    ],
    ids=["1e19", "1e308", "nan", "-inf", "uint64-max"],
)
def test_a_recording_with_an_absurd_odom_row_loads_and_keeps_its_other_rows(tmp_path, row) -> None:
    frames = ramp_frames(3, accel=False)
    odom = np.zeros((3, 3), dtype=row.dtype)
    odom[1] = row
    odom[2] = np.array([2, 1, 0], dtype=row.dtype)
    np.savez(
        tmp_path / "x.npz",
        depth_mm=np.stack([f.depth_mm for f in frames]),
        intrinsics=SMALL.as_array(),
        odom=odom,
    )
    rows = [f.odom for f in read_recording(tmp_path / "x.npz").frames()]
    assert rows[0] == (0.0, 0.0, 0.0) and rows[2] == (2.0, 1.0, 0.0)
    assert isinstance(check_odom_pose(*rows[1]), OdomRefusal)  # the memory refuses this one
