"""depthnav's recording format: write, read, atomicity and corrupt-file messages."""

from __future__ import annotations

import os
import tomllib

import numpy as np
import pytest

from drivers.errors import RecordingError
from drivers.formats.recording import read_recording
from drivers.formats.recording_writer import write_recording
from tests.drivers.driverkit import SMALL, ramp_frames


def test_round_trip_is_bit_exact(tmp_path):
    frames = ramp_frames(5)
    n = write_recording(
        tmp_path / "rec", frames, description="ramp", truth={"tilt_deg": 5.0, "ok": True}
    )
    assert n == 5
    rec = read_recording(tmp_path / "rec")
    assert rec.intrinsics == SMALL
    assert rec.description == "ramp" and rec.truth == {"tilt_deg": 5.0, "ok": True}
    for frame, back in zip(frames, rec.frames(), strict=True):
        np.testing.assert_array_equal(back.depth_mm, frame.depth_mm)
        assert back.timestamp_s == frame.timestamp_s
        assert back.accel_mps2 == pytest.approx(frame.accel_mps2)


def test_files_and_arrays_follow_the_documented_layout(tmp_path):
    write_recording(tmp_path / "rec", ramp_frames(2))
    assert sorted(os.listdir(tmp_path / "rec")) == ["frames.npz", "recording.toml"]
    meta = tomllib.loads((tmp_path / "rec" / "recording.toml").read_text())
    assert meta["format_version"] == 1
    assert meta["intrinsics"] == {
        "width": 64,
        "height": 48,
        "fx": 61.5,
        "fy": 57.25,
        "cx": 30.25,
        "cy": 22.75,
    }
    with np.load(tmp_path / "rec" / "frames.npz", allow_pickle=False) as npz:
        assert npz["depth_mm"].dtype == np.uint16 and npz["depth_mm"].shape == (2, 48, 64)
        np.testing.assert_array_equal(npz["intrinsics"], [61.5, 57.25, 30.25, 22.75])
        assert npz["accel_mps2"].shape == (2, 3)


def test_interrupted_write_leaves_no_recording(tmp_path, monkeypatch):
    def frames():
        yield from ramp_frames(2)
        raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        write_recording(tmp_path / "early", frames())
    assert not (tmp_path / "early").exists()

    # A crash between the two renames: frames.npz is complete, recording.toml never appeared.
    real_replace = os.replace

    def crash_on_metadata(src, dst):
        if str(dst).endswith("recording.toml"):
            raise KeyboardInterrupt
        real_replace(src, dst)

    monkeypatch.setattr(os, "replace", crash_on_metadata)
    with pytest.raises(KeyboardInterrupt):
        write_recording(tmp_path / "late", ramp_frames(2))
    monkeypatch.undo()
    assert sorted(os.listdir(tmp_path / "late")) == ["frames.npz"]  # no .partial left behind
    with pytest.raises(RecordingError, match=r"no recording\.toml"):
        read_recording(tmp_path / "late")


def test_refuses_to_overwrite_a_non_empty_folder(tmp_path):
    (tmp_path / "rec").mkdir()
    (tmp_path / "rec" / "notes.txt").write_text("keep me")
    with pytest.raises(RecordingError, match="not empty"):
        write_recording(tmp_path / "rec", ramp_frames(1))
    assert (tmp_path / "rec" / "notes.txt").read_text() == "keep me"


def test_bad_truth_writes_nothing(tmp_path):
    with pytest.raises(RecordingError, match=r"truth\.bad"):
        write_recording(tmp_path / "rec", ramp_frames(1), truth={"bad": object()})
    assert not (tmp_path / "rec").exists() or not any((tmp_path / "rec").iterdir())


def test_bare_npz_without_timestamps_gets_default_rate(tmp_path):
    frames = ramp_frames(3, accel=False)
    np.savez(
        tmp_path / "x.npz",
        depth_mm=np.stack([f.depth_mm for f in frames]),
        intrinsics=SMALL.as_array(),
    )
    rec = read_recording(tmp_path / "x.npz", default_fps=10.0)
    np.testing.assert_allclose(rec.timestamp_s, [0.0, 0.1, 0.2])
    assert rec.accel_mps2 is None and rec.intrinsics == SMALL


def _corrupt_cases(tmp_path):
    good = tmp_path / "good"
    write_recording(good, ramp_frames(3))
    data = (good / "frames.npz").read_bytes()
    cases = {}
    for name, mutate in {
        "truncated": lambda d: d[: len(d) // 2],
        "garbage": lambda d: b"\x00not a zip" * 20,
        "empty": lambda d: b"",
    }.items():
        p = tmp_path / f"{name}.npz"
        p.write_bytes(mutate(data))
        cases[name] = p
    p = tmp_path / "pickled.npz"
    np.savez(p, depth_mm=np.array([object()], dtype=object), intrinsics=SMALL.as_array())
    cases["pickle"] = p
    p = tmp_path / "float.npz"
    np.savez(p, depth_mm=np.zeros((1, 48, 64), np.float32), intrinsics=SMALL.as_array())
    cases["float"] = p
    p = tmp_path / "nointr.npz"
    np.savez(p, depth_mm=np.zeros((1, 48, 64), np.uint16))
    cases["nointr"] = p
    p = tmp_path / "badts.npz"
    np.savez(
        p,
        depth_mm=np.zeros((2, 48, 64), np.uint16),
        intrinsics=SMALL.as_array(),
        timestamp_s=np.array([1.0, 0.5]),
    )
    cases["backwards"] = p
    newer = tmp_path / "newer"
    write_recording(newer, ramp_frames(1))
    meta = newer / "recording.toml"
    meta.write_text(meta.read_text().replace("format_version = 1", "format_version = 2"))
    cases["newer"] = newer
    badtoml = tmp_path / "badtoml"
    write_recording(badtoml, ramp_frames(1))
    (badtoml / "recording.toml").write_text("format_version = [\n")
    cases["badtoml"] = badtoml
    return cases


def test_corrupt_recordings_give_one_line_errors_naming_the_file(tmp_path):
    for name, path in _corrupt_cases(tmp_path).items():
        with pytest.raises(RecordingError) as info:
            read_recording(path)
        message = str(info.value)
        assert str(path) in message, (name, message)
        assert "\n" not in message, (name, message)
    with pytest.raises(RecordingError, match="update depthnav"):
        try:
            read_recording(tmp_path / "newer")
        except RecordingError as exc:
            raise RecordingError(f"{exc} {exc.hint}") from None
