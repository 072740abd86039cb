"""Lens models (plumb_bob k1, k2, p1, p2, k3; rational_polynomial; equidistant) from each place
intrinsics come from: the recording metadata, the PNG folder sidecar and the device spec options
(CameraInfo: in test_rosbag_replay.py; .oni sidecars: test_driver_openni.py), and the fakenect
export that cannot carry them."""

from __future__ import annotations

import dataclasses
import subprocess
import sys
import tomllib

import numpy as np
import pytest

import drivers
from drivers.base import KINECT_V1, Frame, Intrinsics
from drivers.errors import DeviceSpecError, RecordingError
from drivers.formats import fakenect
from drivers.formats.png_folder import write_png_folder
from drivers.formats.recording_writer import write_recording
from tests.drivers.driverkit import REPO, SMALL, ramp_frames

LENS = (-0.2, 0.05, 0.001, -0.002, 0.01)
SMALL_LENS = Intrinsics(64, 48, 61.5, 57.25, 30.25, 22.75, *LENS)


def lens_frames(n: int) -> list[Frame]:
    return [dataclasses.replace(f, intrinsics=SMALL_LENS) for f in ramp_frames(n, accel=False)]


def read_all(spec: str) -> list[Frame]:
    with drivers.opened(drivers.create_driver(spec)) as driver:
        return list(drivers.iter_frames(driver))


def test_recording_round_trips_the_coefficients(tmp_path) -> None:
    frames = lens_frames(2)
    write_recording(tmp_path / "rec", frames)
    table = tomllib.loads((tmp_path / "rec" / "recording.toml").read_text())["intrinsics"]
    assert tuple(table[k] for k in ("k1", "k2", "p1", "p2", "k3")) == LENS
    out = read_all(f"replay:{tmp_path / 'rec'}?rate=max")
    assert [f.intrinsics for f in out] == [SMALL_LENS, SMALL_LENS]
    np.testing.assert_array_equal(out[1].depth_mm, frames[1].depth_mm)


def test_pinhole_recordings_are_written_and_read_as_before(tmp_path) -> None:
    write_recording(tmp_path / "rec", ramp_frames(1, accel=False))
    table = tomllib.loads((tmp_path / "rec" / "recording.toml").read_text())["intrinsics"]
    assert set(table) == {"width", "height", "fx", "fy", "cx", "cy"}  # what old readers know
    assert read_all(f"replay:{tmp_path / 'rec'}?rate=max")[0].intrinsics == SMALL


def test_png_folder_sidecar_round_trips_the_coefficients(tmp_path) -> None:
    write_png_folder(tmp_path / "png", lens_frames(2), scale=1000.0)
    assert read_all(f"replay:{tmp_path / 'png'}?rate=max")[0].intrinsics == SMALL_LENS
    # a sidecar may give only some of them; the rest are 0
    sidecar = tmp_path / "png" / "camera.toml"
    text = sidecar.read_text()
    for key in ("k2", "p1", "p2", "k3"):
        text = "\n".join(line for line in text.splitlines() if not line.startswith(key))
    sidecar.write_text(text + "\n")
    got = read_all(f"replay:{tmp_path / 'png'}?rate=max")[0].intrinsics
    assert got.distortion == (-0.2, 0.0, 0.0, 0.0, 0.0)


@pytest.mark.parametrize(
    ("line", "says"),
    [
        ('k1 = "barrel"', "bad [intrinsics]: k1 is text, not a number"),
        ("k1 = -3.0", "bad [intrinsics]: lens distortion (k1=-3, k2=0, p1=0, p2=0, k3=0) folds"),
        ("k7 = 0.1", "unknown key [intrinsics] 'k7' (valid: width, height, fx, fy, cx, cy, "),
        ("k4 = 0.1", "k4=0.1 is not a coefficient of the plumb_bob lens model (k1, k2, p1, p2"),
        ("distortion_model = 3", "distortion_model = 3 is not text (one of plumb_bob, "),
        ('distortion_model = "fisheye"', "lens model 'fisheye' cannot be expressed (depthnav mod"),
        ('distortion_model = "equidistant"\np1 = 0.001', "p1=0.001 is not a coefficient of the"),
    ],
)
def test_bad_sidecar_coefficients_are_one_line_errors(tmp_path, line: str, says: str) -> None:
    write_png_folder(tmp_path / "png", ramp_frames(1, accel=False), scale=1000.0)
    sidecar = tmp_path / "png" / "camera.toml"
    sidecar.write_text(sidecar.read_text() + line + "\n")
    with pytest.raises(RecordingError) as info:
        read_all(f"replay:{tmp_path / 'png'}")
    assert says in str(info.value) and "\n" not in str(info.value)


def test_spec_options_set_the_coefficients(tmp_path) -> None:
    write_recording(tmp_path / "rec", ramp_frames(1, accel=False))
    got = read_all(f"replay:{tmp_path / 'rec'}?rate=max&k1=-0.2&p2=-0.002")[0].intrinsics
    assert got == dataclasses.replace(SMALL, k1=-0.2, p2=-0.002)
    # options replace a recording's own coefficients one by one
    write_recording(tmp_path / "lens", lens_frames(1))
    got = read_all(f"replay:{tmp_path / 'lens'}?rate=max&k1=0")[0].intrinsics
    assert got.distortion == (0.0, *LENS[1:])
    kinect = drivers.create_driver("kinect://0?k1=-0.25&k2=0.06")
    assert kinect.intrinsics.distortion == (-0.25, 0.06, 0.0, 0.0, 0.0)


@pytest.mark.parametrize(
    ("spec", "says"),
    [
        ("kinect?p1=3", "option p1='3' in 'kinect?p1=3' is out of range (accepted: -1..1)"),
        ("kinect?k2=oops", "option k2='oops'"),
        ("kinect?k1=-2", "lens distortion (k1=-2, k2=0, p1=0, p2=0, k3=0) folds back"),
    ],
)
def test_bad_coefficient_options_are_usage_errors(spec: str, says: str) -> None:
    with pytest.raises(DeviceSpecError) as info:
        drivers.create_driver(spec)
    assert says in str(info.value) and "\n" not in str(info.value)


# --- the other lens models, and exports that cannot carry a camera -------------------------------

RATIONAL_SMALL = dataclasses.replace(
    SMALL_LENS, k4=0.3, k5=0.05, k6=0.01, distortion_model="rational_polynomial"
)
FISHEYE_SMALL = Intrinsics(
    64, 48, 40.0, 40.0, 31.0, 24.5, k1=0.02, k2=-0.01, k4=0.001, distortion_model="equidistant"
)


@pytest.mark.parametrize("intr", [RATIONAL_SMALL, FISHEYE_SMALL], ids=["rational", "fisheye"])
def test_png_folder_camera_toml_round_trips_every_model(tmp_path, intr: Intrinsics) -> None:
    frames = [dataclasses.replace(f, intrinsics=intr) for f in ramp_frames(2, accel=False)]
    write_png_folder(tmp_path / "png", frames, scale=1000.0)
    table = tomllib.loads((tmp_path / "png" / "camera.toml").read_text())["intrinsics"]
    assert table["distortion_model"] == intr.distortion_model
    assert tuple(table[k] for k in intr.distortion_keys) == intr.distortion
    got = read_all(f"replay:{tmp_path / 'png'}?rate=max")
    assert [f.intrinsics for f in got] == [intr, intr]
    # an option replaces one coefficient and keeps the model
    got = read_all(f"replay:{tmp_path / 'png'}?rate=max&k1=0")[0].intrinsics
    assert got == dataclasses.replace(intr, k1=0.0)


@pytest.mark.parametrize("intr", [RATIONAL_SMALL, FISHEYE_SMALL], ids=["rational", "fisheye"])
def test_a_recording_never_replays_a_lens_as_another(tmp_path, intr: Intrinsics) -> None:
    """recording.toml: the lens comes back whole, or the recording is refused at its first frame
    (a reader that knows only plumb_bob would read a fisheye's k1-k3 as plumb_bob's)."""
    frames = [dataclasses.replace(f, intrinsics=intr) for f in ramp_frames(2, accel=False)]
    try:
        write_recording(tmp_path / "rec", frames)
    except RecordingError as exc:
        assert "would not read back" in str(exc) and "--format png" in exc.hint
        assert not (tmp_path / "rec" / "recording.toml").exists()
        return
    assert [f.intrinsics for f in read_all(f"replay:{tmp_path / 'rec'}?rate=max")] == [intr] * 2


def record(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "depthnav_daemon", "record", "--frames", "2", *args],
        capture_output=True, text=True, cwd=REPO, timeout=300,
    )  # fmt: skip


@pytest.mark.parametrize("fmt", ["fakenect", "oni"])
def test_exports_keep_a_camera_their_format_cannot_hold(tmp_path, fmt: str) -> None:
    """Issue 33 item 3: fakenect has no intrinsics (replay assumed the Kinect v1's 580 px: a
    calibrate 3.5 cm / 2.9 deg off) and .oni no principal point or lens; the exports said so in
    an INFO line only. Now a camera.toml beside them carries the camera, and replay reads it."""
    vga = Intrinsics(640, 480, 583.0, 575.5, 318.25, 243.75, k1=-0.1, k2=0.02)
    source = tmp_path / "src"
    write_recording(source, ramp_frames(2, intr=vga, accel=False))
    out = tmp_path / ("out.oni" if fmt == "oni" else "out")
    side = tmp_path / "out.camera.toml" if fmt == "oni" else out / "camera.toml"
    device = ("--device", f"replay:{source}?rate=max")
    if fmt == "oni":  # an old camera.toml beside the target is refused, before the device opens
        side.write_text("# someone's\n")
        proc = record(*device, "--format", fmt, str(out))
        assert proc.returncode == 2 and f"{side}: exists; refusing to overwrite" in proc.stderr
        side.unlink()
    proc = record(*device, "--format", fmt, str(out))
    assert proc.returncode == 0, proc.stderr
    assert "camera.toml" in proc.stderr  # the INFO line says where the camera goes
    assert tomllib.loads(side.read_text())["intrinsics"]["cx"] == 318.25
    if fmt == "fakenect":  # (the .oni replay needs libOpenNI2: test_driver_openni.py)
        got = read_all(f"replay:{out}?rate=max")
        assert [f.intrinsics for f in got] == [vga, vga]
        want = ramp_frames(2, intr=vga, accel=False)[1].depth_mm
        quantised = fakenect.disparity_to_mm(fakenect.mm_to_disparity(want))
        np.testing.assert_array_equal(got[1].depth_mm, quantised)
    # a Kinect v1's own frames leave libfreenect's layout as it was
    write_recording(tmp_path / "kinect", ramp_frames(2, intr=KINECT_V1, accel=False))
    proc = record("--device", f"replay:{tmp_path / 'kinect'}?rate=max", "--format", "fakenect",
                  str(tmp_path / "fk2"))  # fmt: skip
    assert proc.returncode == 0 and not (tmp_path / "fk2" / "camera.toml").exists()
