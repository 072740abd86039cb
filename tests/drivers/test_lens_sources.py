"""Lens coefficients (plumb_bob k1, k2, p1, p2, k3) from each place intrinsics come from: the
recording metadata, the PNG folder sidecar and the device spec options (CameraInfo: in
test_rosbag_replay.py)."""

from __future__ import annotations

import dataclasses
import tomllib

import numpy as np
import pytest

import drivers
from drivers.base import Frame, Intrinsics
from drivers.errors import DeviceSpecError, RecordingError
from drivers.formats.png_folder import write_png_folder
from drivers.formats.recording_writer import write_recording
from tests.drivers.driverkit import SMALL, ramp_frames

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
        ("k4 = 0.1", "unknown key [intrinsics] 'k4' (valid: width, height, fx, fy, cx, cy, k1,"),
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
