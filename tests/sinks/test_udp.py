"""udp sink, real loopback socket: one datagram per frame; a lost receiver never stalls."""

from __future__ import annotations

import json
import logging
import socket
from dataclasses import replace

import numpy as np
import pytest

from depthnav_daemon.errors import ConfigError
from depthnav_daemon.sinks import create_sink
from depthnav_daemon.sinks.json import message as jsonmsg
from depthnav_daemon.sinks.json.udp import UdpSink


@pytest.fixture
def receiver():
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.bind(("127.0.0.1", 0))
    sock.settimeout(5.0)  # bounded wait; loopback delivers at once
    yield sock
    sock.close()


def test_one_datagram_per_frame(receiver, pairs, context):
    port = receiver.getsockname()[1]
    sink = create_sink(f"udp://:{port}")  # empty host = loopback
    assert isinstance(sink, UdpSink) and sink.host == "127.0.0.1"
    sink.open(context)
    for frame, result in pairs:
        sink.write(frame, result)
    sink.close()
    sink.close()
    msgs = [json.loads(receiver.recv(65536)) for _ in pairs]
    assert [m["seq"] for m in msgs] == [r.seq for _, r in pairs]
    frame, result = pairs[0]
    got = jsonmsg.decode_ranges(msgs[0]["scan"]["ranges"])
    want = result.scan.ranges.astype(np.float64)
    assert np.array_equal(np.isnan(got), np.isnan(want)) and np.array_equal(
        np.isinf(got), np.isinf(want)
    )
    fin = np.isfinite(want)
    assert np.allclose(got[fin], want[fin], atol=0.0006)
    assert msgs[0]["message"] is None and sink.sent == len(pairs) and sink.send_errors == 0


def test_full_width_scan_fits_one_datagram(receiver, pairs, context):
    # a 640-column scan with every range finite is the largest scan a Kinect frame gives
    frame, result = pairs[0]
    ranges = np.linspace(0.4, 4.999, result.scan.ranges.size).astype(np.float32)
    result = replace(result, scan=replace(result.scan, ranges=ranges))
    sink = create_sink(f"udp://127.0.0.1:{receiver.getsockname()[1]}")
    sink.open(context)
    sink.write(frame, result)
    sink.close()
    data = receiver.recv(65536)
    assert len(data) < 60000
    msg = json.loads(data)
    assert msg["message"] is None and len(msg["scan"]["ranges"]) == ranges.size


def test_oversize_message_drops_far_cliff_points_and_says_so(receiver, pairs, context):
    frame, result = pairs[0]
    rng = np.random.default_rng(3)
    pts = rng.uniform([0.5, -3.0], [5.0, 3.0], size=(8000, 2)).astype(np.float32)
    result = replace(result, cliff=replace(result.cliff, points_m=pts))
    sink = create_sink(f"udp://127.0.0.1:{receiver.getsockname()[1]}?max_bytes=30000")
    sink.open(context)
    sink.write(frame, result)
    sink.close()
    data = receiver.recv(65536)
    assert len(data) <= 30000
    msg = json.loads(data)
    assert msg["cliff"]["points_total"] == 8000 and msg["cliff"]["points_dropped"] > 0
    assert "capped" in msg["message"]


def _port_in_use(port: int) -> bool:
    """True if some other socket holds 127.0.0.1:port (UDP)."""
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    try:
        sock.bind(("127.0.0.1", port))
    except OSError:
        return True
    finally:
        sock.close()
    return False


def _free_port() -> int:
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.bind(("127.0.0.1", 0))
    port = sock.getsockname()[1]
    sock.close()
    return port


def test_lost_receiver_is_counted_never_raised(pairs, context, caplog):
    # a freed port can be taken by another process between close and send (other suites run on
    # this machine): then the run proves nothing, and a fresh port is tried
    for _attempt in range(5):
        port = _free_port()  # nobody listens: ICMP port unreachable on loopback
        sink = create_sink(f"udp://127.0.0.1:{port}")
        sink.open(context)
        frame, result = pairs[0]
        caplog.clear()
        with caplog.at_level(logging.WARNING, logger="depthnav_daemon.sinks.json.udp"):
            for seq in range(20):
                sink.write(frame, replace(result, seq=seq))  # must not raise
        sink.close()
        if sink.send_errors == 0 and _port_in_use(port):
            continue
        break
    assert sink.send_errors >= 1
    # at most one warning per 10 s, however many datagrams were lost
    lines = [r for r in caplog.records if r.name == "depthnav_daemon.sinks.json.udp"]
    assert len(lines) == 1 and "ConnectionRefusedError" in lines[0].getMessage()


def test_receiver_coming_back_gets_data_again(pairs, context):
    frame, result = pairs[0]
    for _attempt in range(5):
        port = _free_port()
        sink = create_sink(f"udp://127.0.0.1:{port}")
        sink.open(context)
        again = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        try:
            for seq in range(3):
                sink.write(frame, replace(result, seq=seq))
            try:
                again.bind(("127.0.0.1", port))
            except OSError:
                continue  # another process took the freed port meanwhile: try a fresh one
            again.settimeout(5.0)
            sink.write(frame, replace(result, seq=99))
            assert json.loads(again.recv(65536))["seq"] == 99
            return
        finally:
            again.close()
            sink.close()
    pytest.fail("no free loopback UDP port stayed free long enough")


@pytest.mark.parametrize(
    "spec", ["udp://", "udp://host", "udp://:0", "udp://h:1?max_bytes=99", "udp://h:1?ttl=3"]
)
def test_bad_specs(spec):
    with pytest.raises(ConfigError):
        create_sink(spec)


def test_ipv6_spec():
    sink = create_sink("udp://[::1]:5600?max_bytes=1400")
    assert (sink.host, sink.port, sink.max_bytes) == ("::1", 5600, 1400)


def _datagrams(receiver, sink, pairs, context) -> list[bytes]:
    sink.open(context)
    for frame, result in pairs:
        sink.write(frame, result)
    sink.close()
    receiver.settimeout(0.5)  # loopback delivers at once; this only ends the read
    out = []
    try:
        while True:
            out.append(receiver.recv(65536))
    except TimeoutError:
        return out


def test_slim_datagrams_scan_only_in_millimetres(receiver, pairs, context):
    port = receiver.getsockname()[1]
    full = _datagrams(receiver, create_sink(f"udp://:{port}"), pairs[:1], context)[0]
    slim = _datagrams(
        receiver, create_sink(f"udp://:{port}?content=scan&ranges=mm"), pairs[:1], context
    )[0]
    msg = json.loads(slim)
    assert set(msg) == {
        "v",
        "version",
        "seq",
        "t_s",
        "wall_s",
        "scan",
        "pose",
        "mount",
        "warning",
        "message",
    }
    assert "estimate" not in msg["pose"] and msg["scan"]["ranges_unit"] == "mm"
    assert len(slim) < len(full) / 2  # what a Wi-Fi link sees: fewer fragments
    want = json.loads(full)["scan"]["ranges"]
    for mm, m in zip(msg["scan"]["ranges"], want, strict=True):
        if isinstance(m, float):  # a number: the same range, in whole millimetres
            assert isinstance(mm, int) and abs(mm - m * 1000) <= 0.5
        else:  # null (no reading) and the REP 117 markers stay as they are
            assert mm == m


def test_no_cliff_scan_keeps_the_cliff_points(receiver, pairs, context):
    port = receiver.getsockname()[1]
    msg = json.loads(
        _datagrams(receiver, create_sink(f"udp://:{port}?cliff_scan=0"), pairs[:1], context)[0]
    )
    assert "scan" not in msg["cliff"] and "points_m" in msg["cliff"]


def test_every_and_rate_decimate_by_frame_count_and_sensor_time(receiver, pairs, context):
    port = receiver.getsockname()[1]
    n = len(pairs)
    sent = _datagrams(receiver, create_sink(f"udp://:{port}?every=3"), pairs, context)
    assert [json.loads(d)["seq"] for d in sent] == [r.seq for _, r in pairs][::3]
    # the pairs are 30 frames/s of sensor time: 10 Hz is every third frame
    sent = _datagrams(receiver, create_sink(f"udp://:{port}?rate=10"), pairs, context)
    assert [json.loads(d)["seq"] for d in sent] == [r.seq for _, r in pairs][::3]
    assert n >= 4


@pytest.mark.parametrize(
    "option", ["content=all2", "ranges=cm", "every=0", "rate=-1", "rate=inf", "cliff_scan=maybe"]
)
def test_bad_slimming_options_are_one_line_config_errors(option):
    with pytest.raises(ConfigError, match=option.split("=")[0]):
        create_sink(f"udp://:5600?{option}")


def test_frames_too_big_for_max_bytes_are_summed_up_at_close(receiver, pairs, context, caplog):
    port = receiver.getsockname()[1]
    sink = create_sink(f"udp://:{port}?max_bytes=5000")
    with caplog.at_level(logging.INFO, logger="depthnav_daemon.sinks.json.udp"):
        sent = _datagrams(receiver, sink, pairs, context)
    assert sent == [] and sink.sent == 0
    text = caplog.text
    assert "content=scan" in text  # the per-frame line says how to slim it
    assert f"0 frames sent, {len(pairs)} skipped as larger than max_bytes=5000" in text
