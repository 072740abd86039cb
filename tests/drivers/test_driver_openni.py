"""OpenNI2 through the real libOpenNI2: .oni files we write, played by libOniFile, and DummyDevice.

Every test that loads the native library runs in a child process, so a crash fails that test only.
"""

from __future__ import annotations

import itertools
import json
import math
import struct

import numpy as np
import pytest

from drivers.errors import RecordingError
from drivers.formats.oni import check_oni, write_oni
from drivers.openni.native import find_library
from tests.drivers.driverkit import SMALL, ramp_frames, run_isolated, skip_without


@pytest.fixture(autouse=True)
def _needs_openni():
    skip_without(find_library() is None, "libopenni2-0")


READ_ALL = """
import json, sys, numpy as np, drivers
from tests.drivers.driverkit import ramp_frames
spec, n_read = sys.argv[1], int(sys.argv[2])
expected = ramp_frames(int(sys.argv[3]))
offset = int(sys.argv[4])
out = []
try:
    with drivers.opened(drivers.create_driver(spec)) as d:
        for _ in range(n_read):
            f = d.read_frame(2.0)
            if f is None:
                out.append(None); break
            want = expected[(f.seq + offset) % len(expected)].depth_mm
            i = f.intrinsics
            equal = bool(np.array_equal(f.depth_mm, want))
            out.append({"seq": f.seq, "t": f.timestamp_s, "equal": equal,
                        "intr": [i.width, i.height, i.fx, i.fy, i.cx, i.cy]})
    print(json.dumps({"frames": out}))
except drivers.DriverError as exc:
    print(json.dumps({"error": type(exc).__name__, "message": str(exc), "hint": exc.hint}))
"""


def run(spec: str, n_read: int = 10, n_written: int = 4, offset: int = 0) -> dict:
    proc = run_isolated(READ_ALL, spec, str(n_read), str(n_written), str(offset))
    assert proc.returncode == 0, f"child exited {proc.returncode}: {proc.stderr[-2000:]}"
    return json.loads(proc.stdout.strip().splitlines()[-1])


@pytest.fixture
def oni_file(tmp_path):
    path = tmp_path / "ramp.oni"
    write_oni(path, ramp_frames(4))
    return path


@pytest.mark.parametrize("scheme", ["openni:", "replay:"])
def test_oni_plays_back_bit_exact_through_libonifile(oni_file, scheme):
    result = run(f"{scheme}{oni_file}?rate=max")
    frames = result["frames"]
    assert frames[-1] is None and len(frames) == 5  # four frames, then a clean end of stream
    assert [f["seq"] for f in frames[:-1]] == [0, 1, 2, 3]
    assert all(f["equal"] for f in frames[:-1])
    assert [f["t"] for f in frames[:-1]] == pytest.approx([0, 1 / 30, 2 / 30, 3 / 30], abs=1e-6)
    width, height, fx, fy, cx, cy = frames[0]["intr"]
    # The file stores the field of view only, so fx, fy survive (as float32) and the principal
    # point comes back at the image centre.
    assert (width, height) == (SMALL.width, SMALL.height)
    assert fx == pytest.approx(SMALL.fx, rel=1e-6) and fy == pytest.approx(SMALL.fy, rel=1e-6)
    assert (cx, cy) == ((width - 1) / 2, (height - 1) / 2)


def test_oni_loop_keeps_time_increasing(oni_file):
    frames = run(f"openni:{oni_file}?loop=1", n_read=9)["frames"]
    assert len(frames) == 9 and all(f["equal"] for f in frames)
    stamps = [f["t"] for f in frames]
    assert all(b > a for a, b in itertools.pairwise(stamps))


def test_dummy_device_smoke():
    code = """
import drivers
with drivers.opened(drivers.create_driver("openni://Dummy")) as d:
    frames = [d.read_frame(3.0) for _ in range(3)]
row = frames[0].depth_mm[0]
shapes = [f.depth_mm.shape for f in frames]
print(shapes, int(row.min()), int(row.max()), frames[0].intrinsics.width)
"""
    proc = run_isolated(code)
    assert proc.returncode == 0, proc.stderr[-2000:]  # a segfault would be -11
    assert (
        proc.stdout.strip().splitlines()[-1] == "[(240, 320), (240, 320), (240, 320)] 2000 2000 320"
    )


def test_missing_device_and_bad_mode_give_hints():
    result = run("openni://no-such-device-uri")
    assert result["error"] == "DeviceOpenError" and "no-such-device-uri" in result["message"]
    assert "depthnav devices" in result["hint"]
    result = run("openni://Dummy?mode=1x1@5")
    assert result["error"] == "DeviceOpenError" and "320x240@30" in result["hint"]


def _corrupt(tmp_path, oni_file):
    data = oni_file.read_bytes()
    cases = {
        "truncated.oni": data[: len(data) - 5000],
        "header_only.oni": data[:24],
        "empty.oni": b"",
        "not_oni.oni": b"PK\x03\x04" + data[4:],
        "bad_record.oni": data[:24] + b"\xff" * 28 + data[52:],
    }
    paths = []
    for name, content in cases.items():
        path = tmp_path / name
        path.write_bytes(content)
        paths.append(path)
    return paths


def test_corrupt_oni_files_fail_before_reaching_the_native_player(tmp_path, oni_file):
    for path in _corrupt(tmp_path, oni_file):
        with pytest.raises(RecordingError) as info:
            check_oni(path)
        assert path.name in str(info.value) and "\n" not in str(info.value)


def test_corrupt_oni_through_the_driver_is_a_one_line_error(tmp_path, oni_file):
    path = _corrupt(tmp_path, oni_file)[0]
    result = run(f"replay:{path}?rate=max")
    assert result["error"] == "RecordingError" and "truncated" in result["message"]
    assert path.name in result["message"]


def test_writer_layout_matches_the_documented_header(oni_file):
    head = oni_file.read_bytes()[:24]
    magic, major, minor, maint, build, max_ts, max_node = struct.unpack("<4sBBHIQI", head)
    assert (magic, major, minor, maint, build, max_node) == (b"NI10", 1, 0, 1, 0, 1)
    assert max_ts == round(3 / 30 * 1e6)
    summary = check_oni(oni_file)
    assert (summary.depth_nodes, summary.frames, summary.has_end) == (1, 4, True)
    assert math.isclose(np.float32(0.0), 0.0)


def test_calibration_options_replace_the_fov_intrinsics(oni_file):
    spec = f"openni:{oni_file}?fx={SMALL.fx}&fy={SMALL.fy}&cx={SMALL.cx}&cy={SMALL.cy}"
    frames = run(spec)["frames"]
    assert frames[0]["intr"] == [SMALL.width, SMALL.height, SMALL.fx, SMALL.fy, SMALL.cx, SMALL.cy]


def test_start_skips_by_reading_never_by_seeking(oni_file):
    # OpenNI2's PlaybackSupport.seek() hangs the Debian build forever; start= must not use it.
    frames = run(f"replay:{oni_file}?rate=max&start=2", offset=2)["frames"]
    assert [f["seq"] for f in frames[:-1]] == [0, 1] and frames[-1] is None
    assert all(f["equal"] for f in frames[:-1])  # seq 0 is the file's third frame
