"""Serial tilt source over a real pty pair, with a simulator thread on the master side."""

from __future__ import annotations

import math
import os
import threading
import time
import tty

import pytest
from pymavlink.dialects.v20 import common as mavlink2

from drivers.base import tilt_roll_to_accel
from drivers.errors import DeviceLost, DeviceOpenError, DeviceSpecError
from drivers.tilt.serialtilt import (
    SerialTiltSource,
    format_line,
    nmea_checksum,
    parse_line,
)

WAIT_S = 10.0  # generous bound for a slow machine; the tests return as soon as data arrives


@pytest.fixture
def pty_pair():
    master, slave = os.openpty()
    tty.setraw(master)
    tty.setraw(slave)
    yield master, os.ttyname(slave)
    for fd in (master, slave):
        try:
            os.close(fd)
        except OSError:
            pass


def wait_for(source: SerialTiltSource, predicate, timeout_s: float = WAIT_S):
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        reading = source.latest()
        if reading is not None and predicate(reading):
            return reading
        time.sleep(0.01)
    raise AssertionError(f"no matching reading within {timeout_s} s (last: {source.latest()})")


def simulate(master: int, chunks: list[bytes]) -> threading.Thread:
    def run() -> None:
        for chunk in chunks:
            os.write(master, chunk)
            time.sleep(0.005)

    thread = threading.Thread(target=run, daemon=True)
    thread.start()
    return thread


def test_checksum_is_xor_between_dollar_and_star():
    assert nmea_checksum(b"TILT,15.0,-2.5") == 0x1B
    assert parse_line(b"$TILT,15.0,-2.5*1B\r\n") == (15.0, -2.5)
    assert parse_line(b"$TILT,15.0,-2.5*1C") is None
    assert parse_line(b"$TILT,95.0,0*" + f"{nmea_checksum(b'TILT,95.0,0'):02X}".encode()) is None


def test_line_protocol_over_a_pty_with_split_and_corrupt_lines(pty_pair):
    master, port = pty_pair
    good = format_line(12.5, -3.0)
    with SerialTiltSource(port, "line") as source:
        assert source.latest() is None
        simulate(master, [b"garbage\r\n", b"$TILT,1.0,1.0*00\r\n", good[:7], good[7:]]).join(WAIT_S)
        reading = wait_for(source, lambda r: True)
        assert (reading.tilt_deg, reading.roll_deg) == (12.5, -3.0)
        assert source.bad_messages == 2
        simulate(master, [format_line(-4.25, 7.5)]).join(WAIT_S)
        reading = wait_for(source, lambda r: r.tilt_deg == -4.25)
        assert reading.roll_deg == 7.5
        assert source.latest(max_age_s=60.0) is not None


def test_mavlink_attitude_is_converted_to_our_signs(pty_pair):
    master, port = pty_pair
    mav = mavlink2.MAVLink(None, srcSystem=1, srcComponent=1)
    # Autopilot: nose 10 degrees DOWN (pitch -10 deg, nose-up positive), right side 5 degrees down.
    attitude = mav.attitude_encode(1000, math.radians(5.0), math.radians(-10.0), 0.3, 0.0, 0.0, 0.0)
    heartbeat = mav.heartbeat_encode(2, 3, 0, 0, 4)
    with SerialTiltSource(port, "mavlink") as source:
        # Line noise with a stray start byte, then the autopilot's usual stream of messages.
        noise = b"\x00\xfd\x05junk"
        simulate(master, [heartbeat.pack(mav), noise] + [attitude.pack(mav)] * 30).join(WAIT_S)
        reading = wait_for(source, lambda r: True)
        assert reading.tilt_deg == pytest.approx(10.0, abs=1e-4)  # pitched down -> positive tilt
        assert reading.roll_deg == pytest.approx(5.0, abs=1e-4)  # right side down = left side up


def test_port_vanishing_is_device_lost(pty_pair):
    master, port = pty_pair
    with SerialTiltSource(port, "line") as source:
        simulate(master, [format_line(1.0, 2.0)]).join(WAIT_S)
        wait_for(source, lambda r: True)
        os.close(master)
        deadline = time.monotonic() + WAIT_S
        with pytest.raises(DeviceLost, match=port):
            while time.monotonic() < deadline:
                source.latest()
                time.sleep(0.01)


def test_missing_port_names_it():
    source = SerialTiltSource("/dev/does-not-exist-depthnav")
    with pytest.raises(DeviceOpenError, match="does-not-exist-depthnav") as info:
        source.start()
    assert info.value.hint
    source.stop()


def test_spec_grammar():
    source = SerialTiltSource.from_spec("serialtilt:///dev/ttyUSB0?protocol=mavlink&baud=57600")
    assert (source.port, source.protocol, source.baudrate) == ("/dev/ttyUSB0", "mavlink", 57600)
    assert SerialTiltSource.from_spec("serialtilt:loop://").port == "loop://"
    with pytest.raises(DeviceSpecError, match="valid options"):
        SerialTiltSource.from_spec("serialtilt:/dev/ttyUSB0?parity=E")
    with pytest.raises(DeviceSpecError):
        SerialTiltSource.from_spec("serialtilt:/dev/ttyUSB0?protocol=nmea")


@pytest.mark.parametrize(("tilt", "roll"), [(0.0, 0.0), (15.0, 0.0), (-10.0, 5.0), (20.0, -8.0)])
def test_attitude_as_accelerometer_follows_the_convention(tilt, roll):
    ax, ay, az = tilt_roll_to_accel(tilt, roll)
    g = 9.80665
    t, r = math.radians(tilt), math.radians(roll)
    assert ax == pytest.approx(-g * math.sin(r) * math.cos(t))  # roll: left side up -> ax < 0
    assert math.degrees(math.atan2(-az, -ay / math.cos(r))) == pytest.approx(tilt)
    assert math.sqrt(ax * ax + ay * ay + az * az) == pytest.approx(g)
    if roll == 0.0:
        assert (ax, ay, az) == pytest.approx((0.0, -g * math.cos(t), -g * math.sin(t)))
