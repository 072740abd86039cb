"""The mavlink sink: sector pooling pinned against the scan, and real bytes decoded by pymavlink
over a pty pair (serial) and loopback UDP."""

from __future__ import annotations

import math
import os
import select
import socket
import time
from collections.abc import Callable
from dataclasses import replace

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from depthnav_daemon.errors import ConfigError, SinkError
from depthnav_daemon.pipeline import MountState, MountTrust, Result, StageParams, process
from depthnav_daemon.pipeline.geometry import Mount
from depthnav_daemon.pipeline.scan import LaserScan
from depthnav_daemon.sim.synthetic import Box, Scene, render
from depthnav_daemon.sinks import create_sink
from depthnav_daemon.sinks.mavlink.mavlink import MavlinkSink
from depthnav_daemon.sinks.mavlink.sectors import (
    UNKNOWN,
    Schedule,
    merge_cliff,
    obstacle_sectors,
    trust_statustext,
)
from drivers.base import Frame
from tests.sinks.conftest import ASYM_640, CLIFF, SCAN

mavlink2 = pytest.importorskip("pymavlink.dialects.v20.common")


def make_scan(
    ranges, fov_deg: float = 60.0, range_min: float = 0.4, range_max: float = 5.0
) -> LaserScan:
    """A centred CCW scan over ``fov_deg`` with the given ranges (bin i at angle_min + i inc)."""
    r = np.asarray(ranges, dtype=np.float32)
    inc = math.radians(fov_deg) / r.size
    a0 = -inc * (r.size - 1) / 2.0
    return LaserScan(a0, a0 + inc * (r.size - 1), inc, range_min, range_max, r)


def reference_sectors(scan: LaserScan, n: int = 72) -> np.ndarray:
    """Slow per-sector loop written from the message spec, independent of the vectorised code."""
    inc = scan.angle_increment
    left_cw = -math.degrees(scan.angle_max + inc / 2)
    width = math.degrees(inc) * scan.ranges.size / n
    min_cm, max_cm = round(scan.range_min * 100), round(scan.range_max * 100)
    out = []
    for j in range(n):
        s_lo, s_hi = left_cw + j * width, left_cw + (j + 1) * width
        vals = []
        unknown = False
        for theta, r in zip(scan.angles, scan.ranges.astype(float), strict=True):
            b_lo, b_hi = -math.degrees(theta + inc / 2), -math.degrees(theta - inc / 2)
            if min(s_hi, b_hi) - max(s_lo, b_lo) <= 1e-6 * width:
                continue
            if math.isnan(r):
                unknown = True
                continue
            if r == math.inf:
                vals.append(max_cm + 1)
            elif r == -math.inf:
                vals.append(min_cm)
            else:
                vals.append(min(max(math.floor(r * 100), min_cm), max_cm))
        best = min(vals) if vals else UNKNOWN
        # the safety contract: "no obstacle" only where no part of the sector is unknown
        out.append(UNKNOWN if best == max_cm + 1 and unknown else best)
    return np.asarray(out)


# --- sectors --------------------------------------------------------------------------------------


def test_left_obstacle_lands_in_a_left_sector_with_clockwise_bearing():
    ranges = np.full(600, np.inf)
    i = 500  # bins grow counter-clockwise: bin 500 is left of centre
    ranges[i] = 1.5
    scan = make_scan(ranges)
    bearing_ccw = math.degrees(scan.angles[i])
    assert bearing_ccw > 0
    s = obstacle_sectors(scan)
    hit = np.flatnonzero(s.distances_cm == 150)
    assert hit.size >= 1 and np.all(hit < 36)  # MAVLink element 0 is the left-most sector
    centre_cw = s.angle_offset_deg + hit * s.increment_f_deg
    assert np.all(np.abs(centre_cw - (-bearing_ccw)) <= s.increment_f_deg)  # FRD: left = negative
    assert s.increment_f_deg == pytest.approx(60.0 / 72)
    assert s.angle_offset_deg == pytest.approx(-30.0 + 60.0 / 144)
    assert np.all(np.delete(s.distances_cm, hit) == 501)  # no obstacle = max + 1


@settings(max_examples=40, deadline=None)
@given(n=st.sampled_from([20, 71, 72, 200, 640]), data=st.data())
def test_matches_reference_and_keeps_single_bin_obstacles(n, data):
    choices = st.sampled_from([math.nan, math.inf, -math.inf, 0.2, 0.9, 2.5, 4.99, 7.0])
    ranges = np.asarray(data.draw(st.lists(choices, min_size=n, max_size=n)), dtype=np.float32)
    spike = data.draw(st.integers(0, n - 1))
    ranges[spike] = 0.55  # a one-bin obstacle, nearer than anything else but -inf
    scan = make_scan(ranges, fov_deg=data.draw(st.sampled_from([40.0, 58.0, 87.0])))
    s = obstacle_sectors(scan)
    assert np.array_equal(s.distances_cm, reference_sectors(scan))
    assert (s.distances_cm <= 55).any()  # never resampled away


def test_coarse_scan_leaves_no_holes():
    s = obstacle_sectors(make_scan(np.full(20, 3.0)))
    assert np.all(s.distances_cm == 300)


def test_special_values_and_limits():
    s = obstacle_sectors(make_scan(np.full(640, np.nan)))
    assert np.all(s.distances_cm == UNKNOWN)  # no data anywhere
    s = obstacle_sectors(make_scan(np.full(640, -np.inf)))
    assert np.all(s.distances_cm == 40)  # closer than range_min -> min_distance
    s = obstacle_sectors(make_scan(np.full(640, 1.2349)))
    assert np.all(s.distances_cm == 123) and (s.min_cm, s.max_cm) == (40, 500)  # floored to cm


def test_real_scene_thin_post_on_the_right(pairs):
    _, result = pairs[0]  # a 4 cm post at x=1.2, y=-0.3 (right), a box left at 1.6 m
    s = obstacle_sectors(result.scan)
    assert np.array_equal(s.distances_cm, reference_sectors(result.scan))
    bearing_cw = math.degrees(math.atan2(0.3, 1.2 - 0.02))
    j = round((bearing_cw - s.angle_offset_deg) / s.increment_f_deg)
    assert j > 36
    assert abs(int(s.distances_cm[j]) - 100 * math.hypot(1.18, 0.3)) <= 5


def test_cliff_merge_adds_detections_and_unknown_floor():
    """Drop-offs come in; "no drop-off" changes nothing; where the cliff stage did not read the
    floor (NaN) a "no obstacle" sector becomes unknown (a drop-off may be there)."""
    obstacles = obstacle_sectors(make_scan(np.full(640, np.inf)))
    cliff = np.full(640, np.inf)
    cliff[:100] = np.nan  # the right-most bins (clockwise sectors at the end)
    cliff[600] = 2.0  # a drop-off ahead-left
    merged = merge_cliff(obstacles, make_scan(cliff))
    d = merged.distances_cm
    assert (d == 200).sum() >= 1 and np.flatnonzero(d == 200)[0] < 36
    unknown = np.flatnonzero(d == UNKNOWN)
    assert unknown.size >= 10 and unknown.min() > 36  # the right: the end of the clockwise row
    assert np.all(d[(d != 200) & (d != UNKNOWN)] == 501)
    far = np.full(640, np.inf)
    far[300] = 6.0  # beyond the 5 m max_distance: not an obstacle at 5 m
    assert np.all(merge_cliff(obstacles, make_scan(far)).distances_cm == 501)


def test_stale_scans_are_not_repeated(pairs):
    sink = MavlinkSink("x", udp=("127.0.0.1", 9), stale_s=0.5)
    frame, result = pairs[0]
    sink._thread = object()  # write() without open(): only the hand-over is tested
    sink.write(frame, result)
    sent_at = sink._latest[2]
    assert sink.latest_for(sent_at + 0.4) is not None
    assert sink.latest_for(sent_at + 0.6) is None


# --- real transports ------------------------------------------------------------------------------


def collect(
    read: Callable[[float], bytes], want: Callable[[list], bool], timeout_s: float = 10.0
) -> list:
    """Decode MAVLink from ``read`` until ``want(messages)`` or the deadline (bounded wait)."""
    parser = mavlink2.MAVLink(None)
    msgs: list = []
    deadline = time.monotonic() + timeout_s
    while not want(msgs):
        left = deadline - time.monotonic()
        if left <= 0:
            break
        data = read(min(left, 0.5))
        if data:
            msgs += parser.parse_buffer(data) or []
    return msgs


def of_type(msgs, name):
    return [m for m in msgs if m.get_type() == name]


@pytest.fixture
def pty_pair():
    master, slave = os.openpty()
    yield master, os.ttyname(slave)
    for fd in (master, slave):
        try:
            os.close(fd)
        except OSError:
            pass


def pty_reader(master: int) -> Callable[[float], bytes]:
    def read(timeout: float) -> bytes:
        ready, _, _ = select.select([master], [], [], timeout)
        return os.read(master, 65536) if ready else b""

    return read


def check_obstacle_message(msg, result, sysid: int, compid: int) -> None:
    s = obstacle_sectors(result.scan)
    assert list(msg.distances) == s.distances_cm.tolist()
    assert msg.frame == 12 and msg.sensor_type == 2  # MAV_FRAME_BODY_FRD, infrared
    assert msg.increment_f == pytest.approx(s.increment_f_deg, rel=1e-6)
    assert msg.angle_offset == pytest.approx(s.angle_offset_deg, rel=1e-6)
    assert (msg.min_distance, msg.max_distance) == (40, 500)
    assert (msg.get_srcSystem(), msg.get_srcComponent()) == (sysid, compid)


def test_serial_over_pty(pty_pair, pairs, context):
    master, port = pty_pair
    sink = create_sink(f"mavlink:{port}?baud=115200&rate=20")
    sink.open(context)
    try:
        frame, result = pairs[1]
        sink.write(frame, result)
        msgs = collect(
            pty_reader(master),
            lambda m: of_type(m, "OBSTACLE_DISTANCE") and of_type(m, "HEARTBEAT"),
        )
    finally:
        sink.close()
        sink.close()
    hb = of_type(msgs, "HEARTBEAT")[0]
    assert hb.type == 18 and hb.autopilot == 8  # ONBOARD_CONTROLLER, AUTOPILOT_INVALID
    assert (hb.get_srcSystem(), hb.get_srcComponent()) == (1, 196)
    check_obstacle_message(of_type(msgs, "OBSTACLE_DISTANCE")[0], result, 1, 196)


def test_unplugged_serial_port_is_a_sink_error(pty_pair, pairs, context):
    master, port = pty_pair
    sink = create_sink(f"mavlink:{port}")
    sink.open(context)
    os.close(master)  # the far end goes away: writes on the slave fail
    frame, result = pairs[0]
    deadline = time.monotonic() + 10.0
    with pytest.raises(SinkError, match="failed") as info:
        while time.monotonic() < deadline:
            sink.write(frame, result)
            time.sleep(0.05)
    assert "\n" not in str(info.value) and info.value.hint
    sink.close()


@pytest.fixture
def udp_receiver():
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.bind(("127.0.0.1", 0))
    yield sock
    sock.close()


def udp_reader(sock: socket.socket) -> Callable[[float], bytes]:
    def read(timeout: float) -> bytes:
        sock.settimeout(timeout)
        try:
            return sock.recv(65536)
        except TimeoutError:
            return b""

    return read


def test_udp_loopback_with_ids_and_repeats(udp_receiver, pairs, context):
    port = udp_receiver.getsockname()[1]
    sink = create_sink(f"mavlink+udp://127.0.0.1:{port}?sysid=7&compid=158&rate=20&stale=10")
    sink.open(context)
    try:
        read = udp_reader(udp_receiver)
        # heartbeats flow before any frame, and nothing claims obstacle data yet
        before = collect(read, lambda m: bool(of_type(m, "HEARTBEAT")))
        assert of_type(before, "HEARTBEAT") and not of_type(before, "OBSTACLE_DISTANCE")
        frame, result = pairs[2]
        sink.write(frame, result)
        # the newest scan is re-sent at the configured rate, decoupled from the frame rate
        msgs = collect(read, lambda m: len(of_type(m, "OBSTACLE_DISTANCE")) >= 3)
    finally:
        sink.close()
    obstacle = of_type(msgs, "OBSTACLE_DISTANCE")
    assert len(obstacle) >= 3 and len({m.time_usec for m in obstacle}) == 1
    check_obstacle_message(obstacle[0], result, 7, 158)


def test_udp_without_receiver_never_raises(pairs, context):
    probe = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    probe.bind(("127.0.0.1", 0))
    port = probe.getsockname()[1]
    probe.close()
    sink = create_sink(f"mavlink+udp://127.0.0.1:{port}?rate=50")
    sink.open(context)
    frame, result = pairs[0]
    try:
        for seq in range(20):
            sink.write(frame, replace(result, seq=seq))
            time.sleep(0.02)
    finally:
        sink.close()
    assert sink.sent_heartbeat >= 1


@pytest.mark.parametrize(
    "spec",
    [
        "mavlink:",
        "mavlink:/dev/x?rate=0.5",
        "mavlink:/dev/x?rate=abc",
        "mavlink:/dev/x?sysid=0",
        "mavlink+udp://h:1?baud=9600",
        "mavlink:/dev/x?sensor=sonar",
        "mavlink:/dev/x?cliff=maybe",
    ],
)
def test_bad_specs(spec):
    with pytest.raises(ConfigError):
        create_sink(spec)


def test_spec_defaults():
    sink = create_sink("mavlink+udp://")
    assert sink.udp == ("127.0.0.1", 14550) and sink.rate_hz == 10.0
    sink = create_sink("mavlink:/dev/ttyACM0?baud=921600&cliff=1&sensor=laser")
    assert (sink.serial_port, sink.baud, sink.cliff, sink.sensor_type) == (
        "/dev/ttyACM0",
        921600,
        True,
        0,
    )


@pytest.mark.parametrize("rate", [10.0, 15.0, 50.0])
def test_schedule_rates_on_a_simulated_clock(rate):
    # wake-ups at jittery times, as the thread sees them on a busy machine
    rng = np.random.default_rng(0)
    clock = Schedule(1.0 / rate, 1000.0)
    now, beats, scans = 1000.0, 0, 0
    while now < 1010.0:
        hb, obs = clock.due(now)
        beats += hb
        scans += obs
        now = max(now, clock.next_wakeup) + rng.uniform(0.0, 0.2 / rate)
    assert 10 <= beats <= 11  # 1 Hz over 10 s
    assert 0.8 * rate * 10 <= scans <= rate * 10 + 1


def test_schedule_never_bursts_after_a_stall():
    clock = Schedule(0.1, 0.0)
    clock.due(0.0)
    assert clock.due(5.0) == (True, True)  # a 5 s stall: one of each, not 50 queued scans
    assert clock.due(5.01) == (False, False)


# --- mount trust ----------------------------------------------------------------------------------

FLOOR_ONLY = Scene(boxes=(Box(1.6, 0.3, 0.3, 0.3, 0.4),))
CONTRADICTED = MountTrust(
    source="config",
    pinned=True,
    floor="contradicted",
    floor_height_m=0.5,
    floor_tilt_deg=12.0,
    floor_roll_deg=0.0,
    dropoffs_trusted=False,
    note="the floor says height 0.50 m ...",
)


def wrong_mount_pair(seq: int, trust: MountTrust) -> tuple[Frame, Result]:
    """A camera at 0.5 m processed with a mount 0.2 m too low: the floor becomes drop-offs."""
    view = render(FLOOR_ONLY, ASYM_640, Mount(0.5, 12.0, 0.0))
    frame = Frame(seq, seq / 30.0, view.depth_mm, ASYM_640)
    params = StageParams(scan=SCAN, cliff=CLIFF)
    return frame, process(frame, MountState(mount=Mount(0.3, 12.0, 0.0), trust=trust), params)


@pytest.mark.parametrize("policy", ["send", "drop"])
def test_untrusted_dropoffs_option_and_statustext(udp_receiver, context, policy):
    port = udp_receiver.getsockname()[1]
    sink = create_sink(
        f"mavlink+udp://127.0.0.1:{port}?cliff=1&rate=20&stale=10&untrusted_dropoffs={policy}"
    )
    _frame, result = wrong_mount_pair(0, CONTRADICTED)
    with_cliff = merge_cliff(obstacle_sectors(result.scan), result.cliff.scan).distances_cm
    without = obstacle_sectors(result.scan).distances_cm
    assert (with_cliff != without).any()  # the flagged drop-offs do change the message
    sink.open(context)
    try:
        read = udp_reader(udp_receiver)
        for seq in range(3):  # untrusted on every frame: one STATUSTEXT, not three
            sink.write(*wrong_mount_pair(seq, CONTRADICTED))
        msgs = collect(read, lambda m: len(of_type(m, "OBSTACLE_DISTANCE")) >= 3)
        trusted = replace(CONTRADICTED, floor="confirmed", dropoffs_trusted=True, note=None)
        sink.write(*wrong_mount_pair(3, trusted))
        msgs += collect(read, lambda m: len(of_type(m, "STATUSTEXT")) >= 1)
        msgs += collect(read, lambda m: False, timeout_s=0.5)  # nothing more comes
    finally:
        sink.close()
    texts = [(m.severity, m.text) for m in of_type(msgs, "STATUSTEXT")]
    verb = "sent" if policy == "send" else "dropped"
    assert texts == [
        (4, f"depthnav: floor contradicts mount, cliffs {verb}"),  # MAV_SEVERITY_WARNING
        (6, "depthnav: mount trusted again"),  # MAV_SEVERITY_INFO
    ]
    obstacle = of_type(msgs, "OBSTACLE_DISTANCE")
    untrusted = [m for m in obstacle if m.time_usec == obstacle[0].time_usec]
    expected = with_cliff if policy == "send" else without
    assert list(untrusted[0].distances) == expected.tolist()
    # trusted again: the drop-offs go out whatever the policy
    assert list(obstacle[-1].distances) == with_cliff.tolist()


UNCONFIRMED = MountTrust(
    source="default",
    dropoffs_trusted=False,
    trusted=False,
    note="the mount is not configured (...): mount unconfirmed, every range unknown",
)


def test_an_unconfirmed_mount_sends_every_sector_unknown(udp_receiver, context):
    """While nobody knows the mount the sectors are all UINT16_MAX, whatever the scan holds (the
    daemon makes its ranges NaN too; the sink does not rely on it), then normal once known."""
    port = udp_receiver.getsockname()[1]
    sink = create_sink(f"mavlink+udp://127.0.0.1:{port}?cliff=1&rate=20&stale=10")
    _frame, result = wrong_mount_pair(0, UNCONFIRMED)
    with_cliff = merge_cliff(obstacle_sectors(result.scan), result.cliff.scan).distances_cm
    assert (with_cliff != UNKNOWN).all()  # what this scan would say through a known mount
    sink.open(context)
    try:
        read = udp_reader(udp_receiver)
        for seq in range(3):
            sink.write(*wrong_mount_pair(seq, UNCONFIRMED))
        msgs = collect(read, lambda m: len(of_type(m, "OBSTACLE_DISTANCE")) >= 3)
        known = MountTrust(source="floor", floor="confirmed")
        sink.write(*wrong_mount_pair(3, known))
        msgs += collect(read, lambda m: len(of_type(m, "STATUSTEXT")) >= 1)
        msgs += collect(read, lambda m: False, timeout_s=0.5)  # nothing more comes
    finally:
        sink.close()
    texts = [(m.severity, m.text) for m in of_type(msgs, "STATUSTEXT")]
    assert texts == [
        (4, "depthnav: mount unconfirmed, sectors unknown"),  # MAV_SEVERITY_WARNING
        (6, "depthnav: mount confirmed by the floor"),  # MAV_SEVERITY_INFO
    ]
    obstacle = of_type(msgs, "OBSTACLE_DISTANCE")
    unconfirmed = [m for m in obstacle if m.time_usec == obstacle[0].time_usec]
    assert unconfirmed and all(set(m.distances) == {UNKNOWN} for m in unconfirmed)
    assert list(obstacle[-1].distances) == with_cliff.tolist()


def test_default_unconfirmed_mount_statustext_and_bad_policy():
    trust = MountTrust(source="default", dropoffs_trusted=False, note="not configured")
    assert trust_statustext(trust, True, "drop") == (
        4,
        "depthnav: mount not configured, cliffs dropped",
    )
    assert trust_statustext(trust, False, "send") == (4, "depthnav: mount not configured")
    assert all(
        len(trust_statustext(t, c, p)[1]) <= 50
        for t in (trust, CONTRADICTED, None)
        for c in (True, False)
        for p in ("send", "drop")
    )
    with pytest.raises(ConfigError, match="untrusted_dropoffs"):
        create_sink("mavlink+udp://127.0.0.1:14550?untrusted_dropoffs=maybe")
    assert create_sink("mavlink+udp://").untrusted_dropoffs == "send"
