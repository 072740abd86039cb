"""The replay driver over each format it reads, pacing, looping and bad inputs."""

from __future__ import annotations

import itertools
import re
import time

import numpy as np
import pytest

import drivers
from drivers.errors import RecordingError
from drivers.formats.fakenect import write_fakenect
from drivers.formats.png_folder import write_png_folder
from drivers.formats.recording_writer import write_recording
from drivers.replay import ReplayDriver
from tests.drivers.driverkit import SMALL, VGA, kinect_exact_frames, ramp_frames


def read_all(spec: str, limit: int = 100):
    with drivers.opened(drivers.create_driver(spec)) as driver:
        return list(drivers.iter_frames(driver))[:limit]


def test_replay_folder_yields_frames_then_none(tmp_path):
    frames = ramp_frames(3)
    write_recording(tmp_path / "rec", frames)
    out = read_all(f"replay:{tmp_path / 'rec'}?rate=max")
    assert [f.seq for f in out] == [0, 1, 2]
    for a, b in zip(frames, out, strict=True):
        np.testing.assert_array_equal(a.depth_mm, b.depth_mm)
        assert b.intrinsics == SMALL and not b.depth_mm.flags.writeable


def test_loop_repeats_with_increasing_timestamps(tmp_path):
    write_recording(tmp_path / "rec", ramp_frames(2))
    driver = drivers.create_driver(f"replay:{tmp_path / 'rec'}?rate=max&loop=1")
    with drivers.opened(driver):
        got = [driver.read_frame() for _ in range(5)]
    assert [f.seq for f in got] == [0, 1, 2, 3, 4]
    stamps = [f.timestamp_s for f in got]
    assert all(b > a for a, b in itertools.pairwise(stamps))
    np.testing.assert_array_equal(got[2].depth_mm, got[0].depth_mm)


def test_realtime_sleeps_toward_recorded_times(tmp_path):
    frames = ramp_frames(3)
    stretched = [
        type(f)(seq=f.seq, timestamp_s=f.seq * 0.2, depth_mm=f.depth_mm, intrinsics=f.intrinsics)
        for f in frames
    ]
    write_recording(tmp_path / "rec", stretched)
    start = time.monotonic()
    read_all(f"replay:{tmp_path / 'rec'}?rate=realtime")
    # A lower bound only: a slow machine may take longer, never shorter.
    assert time.monotonic() - start >= 0.35


def test_png_folder_replays_with_sidecar_intrinsics_and_scale(tmp_path):
    frames = ramp_frames(3, accel=False)
    write_png_folder(tmp_path / "png", frames, scale=5000.0)
    out = read_all(f"replay:{tmp_path / 'png'}?rate=max")
    assert len(out) == 3 and out[0].intrinsics == SMALL
    for a, b in zip(frames, out, strict=True):
        np.testing.assert_array_equal(a.depth_mm, b.depth_mm)


def test_png_folder_without_intrinsics_asks_for_them(tmp_path):
    write_png_folder(tmp_path / "png", ramp_frames(1, accel=False))
    (tmp_path / "png" / "camera.toml").unlink()
    with pytest.raises(RecordingError) as info:
        read_all(f"replay:{tmp_path / 'png'}")
    assert "fx" in str(info.value) and "camera.toml" in info.value.hint
    out = read_all(f"replay:{tmp_path / 'png'}?fx=61.5&fy=57.25&cx=30.25&cy=22.75&scale=5000")
    assert out[0].intrinsics == SMALL


def test_fakenect_folder_replays_with_accelerometer(tmp_path):
    frames = kinect_exact_frames(2)
    write_fakenect(tmp_path / "fk", frames)
    out = read_all(
        f"replay:{tmp_path / 'fk'}?rate=max&fx={VGA.fx}&fy={VGA.fy}&cx={VGA.cx}&cy={VGA.cy}"
    )
    assert len(out) == 2 and out[0].intrinsics == VGA
    for a, b in zip(frames, out, strict=True):
        np.testing.assert_array_equal(a.depth_mm, b.depth_mm)
        assert b.accel_mps2 == pytest.approx(a.accel_mps2, abs=0.02)  # one count is 0.012 m/s^2
        assert b.tilt is not None and b.tilt.status == "stopped"


@pytest.mark.parametrize(
    "kind",
    [
        "png_truncated",
        "png_garbage",
        "fakenect_truncated",
        "fakenect_missing",
        "fakenect_header",
        "unknown_suffix",
        "empty_folder",
    ],
)
def test_corrupt_inputs_give_one_line_errors_naming_the_file(tmp_path, kind):
    if kind.startswith("png"):
        write_png_folder(tmp_path / "rec", ramp_frames(2, accel=False))
        victim = sorted((tmp_path / "rec" / "depth").glob("*.png"))[1]
        data = victim.read_bytes()
        victim.write_bytes(data[: len(data) // 2] if kind == "png_truncated" else b"nonsense" * 10)
        target = tmp_path / "rec"
    elif kind.startswith("fakenect"):
        write_fakenect(tmp_path / "rec", kinect_exact_frames(2))
        victim = sorted((tmp_path / "rec").glob("d-*.pgm"))[1]
        if kind == "fakenect_truncated":
            victim.write_bytes(victim.read_bytes()[:1000])
        elif kind == "fakenect_missing":
            victim.unlink()
        else:
            victim.write_bytes(b"P5 320 240 65535\n" + victim.read_bytes()[17:])
        target = tmp_path / "rec"
    elif kind == "unknown_suffix":
        target = tmp_path / "frames.bag"
        target.write_bytes(b"x")
        victim = target
    else:
        target = tmp_path / "empty"
        target.mkdir()
        victim = target
    with pytest.raises(RecordingError) as info:
        read_all(f"replay:{target}?rate=max&fx=500&fy=500&cx=30&cy=20")
    message = str(info.value)
    assert victim.name in message and "\n" not in message, message


def test_open_count_returns_to_zero(tmp_path):
    write_recording(tmp_path / "rec", ramp_frames(1))
    driver = ReplayDriver(tmp_path / "rec", realtime=False)
    before = ReplayDriver.open_count
    driver.open()
    assert ReplayDriver.open_count == before + 1
    driver.close()
    driver.close()
    assert ReplayDriver.open_count == before


def test_start_skips_frames_and_seq_counts_from_zero(tmp_path):
    frames = ramp_frames(4)
    write_recording(tmp_path / "rec", frames)
    out = read_all(f"replay:{tmp_path / 'rec'}?rate=max&start=2")
    assert [f.seq for f in out] == [0, 1]
    np.testing.assert_array_equal(out[0].depth_mm, frames[2].depth_mm)
    with pytest.raises(RecordingError, match="start=9 is beyond the end"):
        read_all(f"replay:{tmp_path / 'rec'}?rate=max&start=9")


def test_a_png_folder_must_state_its_depth_scale(tmp_path):
    """A millimetre folder read at TUM's 5000 put every obstacle at a fifth of its range, and
    calibrate reported 0.218 m for a 1 m mount, with exit 0: the scale must be stated."""
    frames = ramp_frames(2, accel=False)
    write_png_folder(tmp_path / "mm", frames, scale=1000.0)
    side = tmp_path / "mm" / "camera.toml"
    side.write_text(side.read_text().replace("depth_scale = 1000.0\n", ""))
    with pytest.raises(RecordingError, match="the depth scale is not stated") as info:
        read_all(f"replay:{tmp_path / 'mm'}")
    assert "scale=1000 for millimetre" in info.value.hint and "5000 for TUM" in info.value.hint
    out = read_all(f"replay:{tmp_path / 'mm'}?scale=1000")
    assert np.array_equal(out[1].depth_mm, frames[1].depth_mm)


def test_a_tum_folder_is_unambiguous(tmp_path):
    frames = ramp_frames(2, accel=False)
    write_png_folder(tmp_path / "tum", frames, scale=5000.0)
    side = tmp_path / "tum" / "camera.toml"
    side.write_text(side.read_text().replace("depth_scale = 5000.0\n", ""))
    index = tmp_path / "tum" / "depth.txt"
    index.write_text(
        "# depth maps\n# file: 'rgbd_dataset_freiburg1_desk.bag'\n" + index.read_text()
    )
    out = read_all(f"replay:{tmp_path / 'tum'}")
    assert np.array_equal(out[0].depth_mm, frames[0].depth_mm)


@pytest.mark.parametrize(
    ("text", "says"),
    [
        ("scale = 1000\n", "unknown key 'scale' (valid: depth_scale, intrinsics)"),
        ("[depth]\nscale = 1000\n", "unknown key 'depth' (valid: depth_scale, intrinsics)"),
        ("depth_scale = 1000\n[intrinsics]\nfocal = 5\n", "unknown key [intrinsics] 'focal'"),
    ],
)
def test_unknown_sidecar_keys_are_errors_listing_the_valid_ones(tmp_path, text, says):
    write_png_folder(tmp_path / "png", ramp_frames(1, accel=False), scale=1000.0)
    (tmp_path / "png" / "camera.toml").write_text(text)
    with pytest.raises(RecordingError, match=re.escape(says)):
        read_all(f"replay:{tmp_path / 'png'}?fx=61.5&fy=57.25&cx=30.25&cy=22.75")
