"""OpenNI2 through the real libOpenNI2: .oni files we write, played by libOniFile, and DummyDevice.

Every test that loads the native library runs in a child process, so a crash fails that test only.
"""

from __future__ import annotations

import dataclasses
import itertools
import json
import math
import struct

import numpy as np
import pytest

from drivers.base import Intrinsics
from drivers.errors import RecordingError
from drivers.formats.oni import check_oni, sidecar_path, write_oni
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
                        "intr": [i.width, i.height, i.fx, i.fy, i.cx, i.cy],
                        "lens": [i.distortion_model, *i.distortion]})
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
    # the principal point is off the centre, which the file cannot hold: its camera.toml does
    assert frames[0]["intr"] == [SMALL.width, SMALL.height, SMALL.fx, SMALL.fy, SMALL.cx, SMALL.cy]
    assert frames[0]["lens"] == ["plumb_bob", 0.0, 0.0, 0.0, 0.0, 0.0]


def test_without_its_sidecar_an_oni_file_gives_its_field_of_view(oni_file):
    sidecar_path(oni_file).unlink()
    width, height, fx, fy, cx, cy = run(f"openni:{oni_file}")["frames"][0]["intr"]
    # The file stores the field of view only, so fx, fy survive (as float32) and the principal
    # point comes back at the image centre.
    assert (width, height) == (SMALL.width, SMALL.height)
    assert fx == pytest.approx(SMALL.fx, rel=1e-6) and fy == pytest.approx(SMALL.fy, rel=1e-6)
    assert (cx, cy) == ((width - 1) / 2, (height - 1) / 2)


def test_a_centred_pinhole_needs_no_sidecar(tmp_path):
    centred = Intrinsics(SMALL.width, SMALL.height, 61.5, 57.25, 31.5, 23.5)
    path = tmp_path / "centred.oni"
    write_oni(path, ramp_frames(2, intr=centred))
    assert not sidecar_path(path).exists()
    assert run(f"openni:{path}")["frames"][0]["intr"][4:] == [31.5, 23.5]


LENSES = {
    "rational": {"distortion_model": "rational_polynomial", "k1": 0.2, "k4": 0.3, "p2": 1e-3},
    "fisheye": {"distortion_model": "equidistant", "k1": 0.01, "k3": -0.002},
}


@pytest.mark.parametrize("name", LENSES)
def test_a_lens_travels_beside_the_oni_file(tmp_path, name):
    """Issue 33 item 3: the .oni export dropped the lens (and the principal point); now
    NAME.camera.toml beside it carries them and both schemes' replay reads it."""
    intr = dataclasses.replace(SMALL, **LENSES[name])
    path = tmp_path / "lens.oni"
    assert write_oni(path, ramp_frames(2, intr=intr)) == 2
    text = sidecar_path(path).read_text()
    assert f"distortion_model = '{intr.distortion_model}'" in text
    for scheme in ("openni:", "replay:"):
        frames = run(f"{scheme}{path}?rate=max", n_written=2)["frames"]
        assert len(frames) == 3 and all(f["equal"] for f in frames[:2])
        assert frames[0]["intr"] == [intr.width, intr.height, intr.fx, intr.fy, intr.cx, intr.cy]
        assert frames[0]["lens"] == [intr.distortion_model, *intr.distortion]
    # options still win, the lens fields they do not name are kept
    got = run(f"openni:{path}?fx=70", n_written=2)["frames"][0]
    assert got["intr"][2] == 70.0 and got["lens"] == [intr.distortion_model, *intr.distortion]


def test_a_sidecar_that_does_not_fit_is_a_one_line_error(oni_file, tmp_path):
    side = sidecar_path(oni_file)
    side.write_text(side.read_text().replace("width = 64", "width = 640"))
    result = run(f"openni:{oni_file}")
    assert result["error"] == "RecordingError" and "width = 640" in result["message"]
    assert "64x48" in result["message"] and "\n" not in result["message"]
    side.write_text("[intrinsics]\nfx = 60.0\nfy = 60.0\ncx = 31.5\ncy = 23.5\nk9 = 1\n")
    result = run(f"replay:{oni_file}")
    assert (
        result["error"] == "RecordingError" and "unknown key [intrinsics] 'k9'" in result["message"]
    )


def test_an_existing_sidecar_is_not_overwritten(tmp_path):
    path = tmp_path / "x.oni"
    sidecar_path(path).write_text("# someone's\n")
    with pytest.raises(RecordingError, match=r"x\.camera\.toml: exists; refusing to overwrite"):
        write_oni(path, ramp_frames(1))
    assert not path.exists() and sidecar_path(path).read_text() == "# someone's\n"


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


PACED_RUNS = """
import json, sys, time, drivers
spec, runs, late_s = sys.argv[1], int(sys.argv[2]), float(sys.argv[3])
out = []
for _ in range(runs):
    with drivers.opened(drivers.create_driver(spec)) as d:
        time.sleep(late_s)  # a reader late for the first frame, as the daemon's first compile is
        stamps = []
        while (f := d.read_frame(2.0)) is not None:
            stamps.append(f.timestamp_s)
    out.append(stamps)
print(json.dumps(out))
"""


def test_fixture_export_replays_every_frame_at_the_recorded_rate(tmp_path):
    """Issue 33 item 2: at speed 1 libOniFile's own thread pushed frames on its clock, so a
    reader late by a second kept 9 of the fixture's 12 (the daemon: 2 of 12). Now the player is
    manual and the driver paces: every frame, in order, at the recorded times, three runs."""
    import drivers
    from tests.drivers.driverkit import REPO

    fixture = REPO / "fixtures" / "drive_step"
    with drivers.opened(drivers.create_driver(f"replay:{fixture}?rate=max")) as d:
        frames = list(iter(lambda: d.read_frame(2.0), None))
    assert len(frames) == 12
    path = tmp_path / "drive_step.oni"
    assert write_oni(path, frames) == 12
    recorded = [f.timestamp_s - frames[0].timestamp_s for f in frames]
    proc = run_isolated(PACED_RUNS, f"replay:{path}", "3", "1.0", timeout_s=120.0)
    assert proc.returncode == 0, proc.stderr[-2000:]
    runs = json.loads(proc.stdout.strip().splitlines()[-1])
    assert len(runs) == 3
    for stamps in runs:
        assert stamps == pytest.approx(recorded, abs=1e-5)  # 12 of 12, none skipped
