"""``depthnav record --format``: a recording exported for other tools, read back by replay and by
the real native libraries (OpenNI2's libOniFile, Debian's libfreenect fakenect)."""

from __future__ import annotations

import hashlib
import itertools
import json
from pathlib import Path

import numpy as np
import pytest

import drivers
from drivers.formats.fakenect import disparity_to_mm, mm_to_disparity
from drivers.formats.oni import write_oni
from drivers.formats.recording import read_recording
from drivers.kinect.freenect import find_library as find_freenect
from drivers.openni.native import find_library as find_openni
from tests.drivers.driverkit import VGA, ramp_frames, run_isolated, skip_without
from tests.test_cli import FIXTURE, depthnav

N = 3
SOURCE = read_recording(FIXTURE)
WANT = SOURCE.depth_mm[:N]


def record(out: Path, fmt: str, *extra: str) -> None:
    p = depthnav(
        "record", "--device", f"replay:{FIXTURE}?rate=max", "--frames", str(N), "--format", fmt,
        *extra, str(out),
    )  # fmt: skip
    assert p.returncode == 0, p.stderr


def read_all(spec: str) -> list[drivers.Frame]:
    with drivers.opened(drivers.create_driver(spec)) as driver:
        return list(drivers.iter_frames(driver))


CHILD = """
import hashlib, json, sys, drivers
with drivers.opened(drivers.create_driver(sys.argv[1])) as d:
    out = []
    for f in drivers.iter_frames(d):
        i = f.intrinsics
        out.append([hashlib.sha1(f.depth_mm.astype("<u2").tobytes()).hexdigest(), f.timestamp_s,
                    [i.width, i.height, i.fx, i.fy, i.cx, i.cy]])
print(json.dumps(out))
"""


def read_native(spec: str) -> list:
    proc = run_isolated(CHILD, spec)
    assert proc.returncode == 0, proc.stderr[-2000:]
    return json.loads(proc.stdout.strip().splitlines()[-1])


def sha(depth: np.ndarray) -> str:
    return hashlib.sha1(depth.astype("<u2").tobytes()).hexdigest()


def test_depthnav_format_is_the_default_and_exact(tmp_path):
    record(tmp_path / "rec", "depthnav", "--description", "x")
    rec = read_recording(tmp_path / "rec")
    np.testing.assert_array_equal(rec.depth_mm, WANT)
    assert rec.intrinsics == SOURCE.intrinsics and rec.description == "x"


def test_png_export_replays_exact_with_intrinsics_and_timestamps(tmp_path):
    record(tmp_path / "png", "png")
    assert (tmp_path / "png" / "camera.toml").is_file()
    got = read_all(f"replay:{tmp_path / 'png'}?rate=max")  # scale and intrinsics from camera.toml
    np.testing.assert_array_equal(np.stack([f.depth_mm for f in got]), WANT)
    assert all(f.intrinsics == SOURCE.intrinsics for f in got)
    stamps = [f.timestamp_s for f in got]
    np.testing.assert_allclose(stamps, SOURCE.timestamp_s[:N] - SOURCE.timestamp_s[0], atol=1e-6)


def test_oni_export_replays_exact_through_libonifile(tmp_path):
    skip_without(find_openni() is None, "libopenni2-0")
    record(tmp_path / "x.oni", "oni")
    for scheme in ("openni:", "replay:"):
        got = read_native(f"{scheme}{tmp_path / 'x.oni'}?rate=max")
        assert [g[0] for g in got] == [sha(d) for d in WANT]
        width, height, fx, fy, _, _ = got[0][2]
        intr = SOURCE.intrinsics
        assert (width, height) == (intr.width, intr.height)
        assert fx == pytest.approx(intr.fx, rel=1e-6) and fy == pytest.approx(intr.fy, rel=1e-6)


def test_fakenect_export_replays_through_our_reader_and_debians_fakenect(tmp_path):
    record(tmp_path / "fk", "fakenect")
    quantised = [disparity_to_mm(mm_to_disparity(d)) for d in WANT]  # 11-bit disparity steps
    got = read_all(f"replay:{tmp_path / 'fk'}?rate=max")
    assert [sha(f.depth_mm) for f in got] == [sha(d) for d in quantised]
    skip_without(find_freenect(fakenect=True) is None, "libfreenect0.5")
    native = read_native(f"kinect://?fakenect={tmp_path / 'fk'}&accel=freenect")
    assert [g[0] for g in native] == [sha(d) for d in quantised]


@pytest.mark.parametrize(
    ("fmt", "out", "extra", "says"),
    [
        ("oni", "x.bin", (), "named *.oni"),
        ("png", "full", (), "not an empty folder"),
        ("png", "new", ("--odometry", "odom+udp://127.0.0.1:9"), "--format depthnav only"),
        ("fakenect", "new", ("--device", "replay:SMALL"), "640x480"),
    ],
)
def test_bad_exports_are_one_line_errors(tmp_path, fmt, out, extra, says):
    (tmp_path / "full").mkdir()
    (tmp_path / "full" / "keep.txt").write_text("mine")
    small = tmp_path / "small.oni"
    write_oni(small, ramp_frames(2))
    device = ("--device", f"replay:{FIXTURE}?rate=max")
    if "--device" in extra:
        device, extra = (), tuple(e.replace("SMALL", str(tmp_path / "small.npz")) for e in extra)
        np.savez(
            tmp_path / "small.npz",
            depth_mm=np.stack([f.depth_mm for f in ramp_frames(2)]),
            intrinsics=ramp_frames(1)[0].intrinsics.as_array(),
        )
    p = depthnav("record", *device, "--format", fmt, *extra, str(tmp_path / out))
    assert p.returncode != 0
    errors = [line for line in p.stderr.splitlines() if "error:" in line]
    assert len(errors) == 1 and says in errors[0], p.stderr
    assert (tmp_path / "full" / "keep.txt").read_text() == "mine"
    assert not (tmp_path / "new").exists()  # a refused export leaves nothing behind


def test_the_oni_writer_holds_one_frame_at_a_time(tmp_path):
    """Each frame is in the file before the next is asked for (no list of every frame)."""
    path = tmp_path / "s.oni"
    partial = tmp_path / "s.oni.partial"
    sizes = []

    def frames():
        for frame in ramp_frames(4, intr=VGA):  # frames bigger than the file's buffer
            sizes.append(partial.stat().st_size if partial.exists() else 0)
            yield frame

    assert write_oni(path, frames()) == 4
    frame_bytes = VGA.width * VGA.height * 2
    assert all(b - a >= frame_bytes for a, b in itertools.pairwise(sizes[1:]))
    assert sizes[1] > 0 and path.is_file() and not partial.exists()
