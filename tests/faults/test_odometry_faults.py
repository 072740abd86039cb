"""Hostile odometry through the real CLI in a child process: absurd values in a recording's
``odom`` and over loopback UDP keep the daemon running (one warning per kind, the counts in the
JSON line, no internal error); a bad odometry spec is a usage error (exit 2, one line and a hint)
and a source that cannot open ends the start-up in one line (exit 1)."""

from __future__ import annotations

import dataclasses
import json
import math
import socket
import threading
from pathlib import Path

import numpy as np
import pytest

from drivers.formats.recording import read_recording
from drivers.formats.recording_writer import write_recording
from tests.faults.kit import (
    FAST,
    FIXTURE,
    ROOT,
    WAIT_S,
    depthnav,
    finish,
    free_udp_port,
    json_lines,
    one_error_line,
    read_lines,
    start,
)

DRIVE = ROOT / "fixtures" / "drive_step"
NONE_REFUSED = {"malformed": 0, "not_finite": 0, "out_of_range": 0, "out_of_order": 0}


def _warnings_per_kind(stderr: str) -> dict[str, int]:
    """How many first-refusal warnings each kind got."""
    out: dict[str, int] = {}
    for line in stderr.splitlines():
        if "refusing a sample (" in line:
            kind = line.split("refusing a sample (", 1)[1].split(")", 1)[0]
            out[kind] = out.get(kind, 0) + 1
    return out


def _clean(stderr: str) -> None:
    assert "Traceback" not in stderr and "internal error" not in stderr, stderr
    assert "error:" not in stderr, stderr


def test_a_recording_with_absurd_odometry_runs_on_with_one_warning_per_kind(tmp_path) -> None:
    frames = read_recording(DRIVE).frames()
    bad = {2: (1e19, 0.0, 0.0), 4: (1e308, 0.0, 0.0), 6: (math.nan, 0.0, 0.0), 8: (0, -1e300, 0)}
    for i, pose in bad.items():
        frames[i] = dataclasses.replace(frames[i], odom=pose)
    write_recording(tmp_path / "poisoned", frames)
    p = depthnav(
        "run",
        "--device",
        f"replay:{tmp_path / 'poisoned'}?rate=max",
        "--sink",
        "stdout",
        "--set",
        "odometry.max_jump_m=5",
    )
    assert p.returncode == 0, p.stderr
    _clean(p.stderr)
    lines = json_lines(p.stdout)
    assert len(lines) == len(frames)
    assert [i for i, m in enumerate(lines) if m["memory"]["status"] == "frozen"] == sorted(bad)
    assert "x_m=1e+19 is beyond" in lines[2]["memory"]["note"]
    assert lines[-1]["memory"]["status"] == "on"
    assert lines[-1]["memory"]["odometry_rejected"] == {
        **NONE_REFUSED,
        "not_finite": 1,
        "out_of_range": 3,
    }
    assert _warnings_per_kind(p.stderr) == {"out_of_range": 1, "not_finite": 1}


def test_a_bare_npz_with_uint64_max_odometry_runs_on(tmp_path) -> None:
    rec = read_recording(DRIVE)
    odom = np.zeros(rec.odom.shape, np.uint64)  # a robot standing still, in integers
    odom[5, 0] = np.iinfo(np.uint64).max
    np.savez(
        tmp_path / "u64.npz",
        depth_mm=rec.depth_mm,
        intrinsics=np.array(
            [rec.intrinsics.fx, rec.intrinsics.fy, rec.intrinsics.cx, rec.intrinsics.cy]
        ),
        timestamp_s=rec.timestamp_s,
        odom=odom,
    )
    p = depthnav("run", "--device", f"replay:{tmp_path / 'u64.npz'}?rate=max", "--sink", "stdout")
    assert p.returncode == 0, p.stderr
    _clean(p.stderr)
    lines = json_lines(p.stdout)
    assert len(lines) == len(rec.odom) and lines[5]["memory"]["status"] == "frozen"
    assert "x_m=1.8446744073709552e+19 is beyond" in lines[5]["memory"]["note"]
    assert lines[-1]["memory"]["odometry_rejected"] == {**NONE_REFUSED, "out_of_range": 1}
    assert _warnings_per_kind(p.stderr) == {"out_of_range": 1}


HOSTILE_LINES = [
    (b'{"x_m": ' + b"9" * 400 + b', "y_m": 0, "yaw_rad": 0}', "out_of_range"),
    (b'{"x_m": 0, "y_m": 0, "yaw_rad": 0, "t_s": ' + b"9" * 400 + b"}", "out_of_range"),
    (b'{"x_m": 1e308, "y_m": 0, "yaw_rad": 0}', "out_of_range"),
    (b'{"x_m": 1e19, "y_m": 0, "yaw_rad": 0}', "out_of_range"),
    (b'{"x_m": NaN, "y_m": 0, "yaw_rad": 0}', "not_finite"),
    (b"[" * 60_000, "malformed"),  # nested 60,000 deep: RecursionError in the parser
    (b'"not an object"', "malformed"),
    (b"\x00\xff\x1b[2J garbage", "malformed"),
]


def test_hostile_udp_odometry_lines_are_refused_and_the_next_good_ones_used() -> None:
    port = free_udp_port()
    proc = start(
        "run",
        "--device",
        f"replay:{FIXTURE}?rate=realtime&loop=1",
        "--odometry",
        f"odom+udp://127.0.0.1:{port}",
        "--sink",
        "stdout",
    )
    robot_stop = threading.Event()
    try:
        read_lines(proc, 1)  # running: the source is listening
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as tx:
            for line, _kind in HOSTILE_LINES:
                tx.sendto(line, ("127.0.0.1", port))

            def robot() -> None:  # then a well-behaved robot, 50 lines a second
                with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as good:
                    i = 0
                    while not robot_stop.wait(0.02):
                        line = {"x_m": 0.001 * i, "y_m": 0.5, "yaw_rad": 0.25}
                        good.sendto(json.dumps(line).encode(), ("127.0.0.1", port))
                        i += 1

            threading.Thread(target=robot, daemon=True).start()
            expected = dict(NONE_REFUSED)
            for _line, kind in HOSTILE_LINES:
                expected[kind] += 1
            got = None
            for _ in range(int(WAIT_S * 30)):  # frames at 30 a second
                msg = json.loads(read_lines(proc, 1)[0])
                if msg["memory"] and msg["memory"]["status"] == "on":
                    got = msg["memory"]
                    if got["odometry_rejected"] == expected:
                        break
            assert got is not None, "the memory never came on"
            assert got["odometry_rejected"] == expected
            assert got["odom"]["y_m"] == 0.5  # the good lines after the bad ones are used
        code, rest, err = finish(proc)
    finally:
        robot_stop.set()
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert code == 0, err
    _clean(err)
    json_lines(rest)  # nothing half-written
    assert _warnings_per_kind(err) == {"out_of_range": 1, "not_finite": 1, "malformed": 1}
    assert "receiver failed" not in err


@pytest.mark.parametrize(
    ("spec", "needle"),
    [
        ("odom+udp://127.0.0.1:0", "needs a port 1..65535"),
        ("odom+udp://127.0.0.1:70000", "needs a port 1..65535"),
        ("odom+udp://192.0.2.1:5700", "is not a loopback address"),
        ("odom+tcp://127.0.0.1:5700", "unknown odometry source 'odom+tcp://127.0.0.1:5700'"),
        ("file:///tmp/odom.jsonl", "unknown odometry source 'file:///tmp/odom.jsonl'"),
        ("odom+udp://127.0.0.1:5700?clock=bogus", "clock='bogus'"),
        ("odom+udp://127.0.0.1:5700?rate=3", "unknown option 'rate'"),
        ("mavlink+udp://127.0.0.1:70000", "needs a port 1..65535"),
        ("mavlink:/dev/ttyUSB0?baud=0", "baud='0'"),
        ("", "--odometry needs a spec"),
        ("   ", "--odometry needs a spec"),
    ],
)
def test_a_bad_odometry_spec_is_a_usage_error(spec: str, needle: str) -> None:
    p = depthnav("run", "--device", FAST, "--odometry", spec, "--max-frames", "1")
    assert p.returncode == 2, p.stderr
    assert needle in one_error_line(p.stderr)
    assert "depthnav: hint:" in p.stderr and p.stdout == ""


def test_a_bad_odometry_source_in_the_config_file_is_a_usage_error(tmp_path: Path) -> None:
    cfg = tmp_path / "robot.toml"
    cfg.write_text('[odometry]\nsource = "zzz://q"\n')
    p = depthnav("run", "--config", str(cfg), "--device", FAST, "--max-frames", "1")
    assert p.returncode == 2, p.stderr
    assert "unknown odometry source 'zzz://q'" in one_error_line(p.stderr)
    assert "depthnav: hint:" in p.stderr


def test_a_bad_odometry_spec_is_refused_with_the_configuration_before_anything_opens() -> None:
    """Checked with the configuration: before the device (which would fail too) is opened, and
    even with the memory off (a bad spec is a bad config, whether or not it is used)."""
    p = depthnav("run", "--device", "replay:/nonexistent/rec", "--odometry", "gps://x")
    assert p.returncode == 2 and "unknown odometry source" in one_error_line(p.stderr)
    p = depthnav("run", "--device", FAST, "--odometry", "gps://x", "--set", "memory.enabled=false")
    assert p.returncode == 2 and "unknown odometry source" in one_error_line(p.stderr)


def test_record_refuses_a_bad_odometry_spec_before_recording(tmp_path: Path) -> None:
    out = tmp_path / "rec"
    p = depthnav(
        "record", "--device", FAST, "--odometry", "odom+tcp://x:1", "--frames", "2", str(out)
    )
    assert p.returncode == 2, p.stderr
    assert "unknown odometry source" in one_error_line(p.stderr)
    assert not out.exists()


def test_mavlink_on_a_path_that_is_no_serial_port_ends_the_start_up_in_one_line() -> None:
    """As ``serialtilt:/dev/null`` does: the spec is fine, the port cannot be opened (exit 1)."""
    p = depthnav("run", "--device", FAST, "--odometry", "mavlink:/dev/null", "--max-frames", "1")
    assert p.returncode == 1, p.stderr
    assert "cannot open /dev/null" in one_error_line(p.stderr)
    assert "depthnav: hint:" in p.stderr and p.stdout == ""
