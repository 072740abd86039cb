"""A bare ``.npz`` as users save one: intrinsics from the spec, float metres in ``depth_m``."""

from __future__ import annotations

import io
import logging
import os

import numpy as np
import pytest

import drivers
from drivers.errors import DeviceSpecError, RecordingError
from drivers.formats.recording import RecordingStream, open_recording_stream, read_recording
from drivers.replay import ReplayDriver
from tests.drivers.driverkit import SMALL, ramp_frames

INTR = "fx=61.5&fy=57.25&cx=30.25&cy=22.75"


def read_all(spec: str) -> list[drivers.Frame]:
    with drivers.opened(drivers.create_driver(spec)) as driver:
        return list(drivers.iter_frames(driver))


def stack(n: int = 3) -> np.ndarray:
    return np.stack([f.depth_mm for f in ramp_frames(n, accel=False)])


def test_spec_intrinsics_stand_in_for_an_npz_without_them(tmp_path):
    path = tmp_path / "x.npz"
    np.savez(path, depth_mm=stack())
    got = read_all(f"replay:{path}?rate=max&{INTR}")
    assert len(got) == 3 and all(f.intrinsics == SMALL for f in got)
    np.testing.assert_array_equal(got[1].depth_mm, stack()[1])


def test_npz_without_intrinsics_or_options_says_how_to_give_them(tmp_path):
    path = tmp_path / "x.npz"
    np.savez(path, depth_mm=stack())
    with pytest.raises(RecordingError, match="no 'intrinsics'") as info:
        read_all(f"replay:{path}?rate=max&fx=61.5")  # three of the four are missing
    assert "fx=" in info.value.hint


def test_spec_intrinsics_that_do_not_fit_are_a_usage_error(tmp_path):
    path = tmp_path / "x.npz"
    np.savez(path, depth_mm=stack())
    with pytest.raises(DeviceSpecError, match="do not fit"):
        read_all(f"replay:{path}?rate=max&fx=61.5&fy=57.25&cx=900&cy=22.75")


@pytest.mark.parametrize("dtype", [np.float32, np.float64, ">f4"])
def test_float_metres_become_millimetres(tmp_path, dtype):
    mm = stack()
    metres = (mm / 1000.0).astype(dtype)
    path = tmp_path / "m.npz"
    np.savez(path, depth_m=metres, intrinsics=SMALL.as_array())
    got = read_all(f"replay:{path}?rate=max")
    for frame, want in zip(got, mm, strict=True):
        np.testing.assert_array_equal(frame.depth_mm, want)  # 0 m stays 0: no reading
        assert frame.depth_mm.dtype == np.uint16


def test_float_metres_without_a_reading_and_beyond_uint16_become_0(tmp_path, caplog):
    metres = np.full((1, 2, 4), 1.5, np.float32)
    metres[0, 0] = [np.nan, np.inf, -np.inf, -1.0]
    metres[0, 1, :2] = [65.535, 70.0]
    path = tmp_path / "m.npz"
    np.savez(path, depth_m=metres)
    with caplog.at_level(logging.WARNING, logger="drivers"):
        rec = read_recording(path, intrinsics_override={"fx": 2, "fy": 2, "cx": 1.5, "cy": 0.5})
    assert rec.depth_mm.tolist() == [[[0, 0, 0, 0], [65535, 0, 1500, 1500]]]
    assert any("beyond 65.535 m" in r.getMessage() for r in caplog.records)


def test_the_stream_converts_float_metres_frame_by_frame(tmp_path):
    mm = stack(4)
    path = tmp_path / "m.npz"
    np.savez(path, depth_m=(mm / 1000.0).astype(np.float32), intrinsics=SMALL.as_array())
    stream = open_recording_stream(path)
    got = list(stream.iter_depth())
    np.testing.assert_array_equal(np.stack(got), mm)


def test_the_streamed_path_is_taken_for_big_float_archives(tmp_path, monkeypatch):
    mm = stack(3)
    path = tmp_path / "m.npz"
    np.savez(path, depth_m=(mm / 1000.0).astype(np.float64))
    monkeypatch.setattr("drivers.replay.CACHE_MAX_BYTES", 100)  # every archive streams
    driver = ReplayDriver(
        path,
        realtime=False,
        intrinsics_override=dict(
            zip(("fx", "fy", "cx", "cy"), (61.5, 57.25, 30.25, 22.75), strict=True)
        ),
    )
    with drivers.opened(driver):
        assert isinstance(driver._recording, RecordingStream)
        got = list(drivers.iter_frames(driver))
    np.testing.assert_array_equal(np.stack([f.depth_mm for f in got]), mm)


@pytest.mark.parametrize(
    ("arrays", "says"),
    [
        ({"depth_mm": np.zeros((1, 4, 4), np.float32)}, "'depth_mm' must be uint16"),
        ({"depth_m": np.zeros((1, 4, 4), np.float16)}, "'depth_m' must be float32 or float64"),
        ({"depth_m": np.zeros((4, 4), np.float32)}, "'depth_m' must be float32 or float64"),
        ({"depth": np.zeros((1, 4, 4), np.uint16)}, "no 'depth_mm'"),
    ],
)
def test_bare_npz_layouts_it_cannot_read_are_one_line(tmp_path, arrays, says):
    path = tmp_path / "x.npz"
    np.savez(path, intrinsics=SMALL.as_array(), **arrays)
    with pytest.raises(RecordingError, match=says) as info:
        read_all(f"replay:{path}?rate=max")
    assert "\n" not in str(info.value)


def test_a_recording_folder_does_not_take_depth_m(tmp_path):
    from drivers.formats.recording_writer import write_recording

    write_recording(tmp_path / "rec", ramp_frames(1))
    np.savez(tmp_path / "rec" / "frames.npz", depth_m=np.ones((1, 48, 64), np.float32))
    with pytest.raises(RecordingError, match="no 'depth_mm'"):
        read_all(f"replay:{tmp_path / 'rec'}?rate=max")


# --- a bare .npy ---------------------------------------------------------------------------------
@pytest.mark.parametrize("kind", ["mm", "metres", "one frame"])
def test_npy_depth_replays_with_spec_intrinsics(tmp_path, kind):
    mm = stack()
    array = {"mm": mm, "metres": (mm / 1000.0).astype(np.float32), "one frame": mm[0]}[kind]
    np.save(tmp_path / "d.npy", array)
    got = read_all(f"replay:{tmp_path / 'd.npy'}?rate=max&fps=10&{INTR}")
    want = mm[:1] if kind == "one frame" else mm
    np.testing.assert_array_equal(np.stack([f.depth_mm for f in got]), want)
    assert all(f.intrinsics == SMALL for f in got)
    assert [f.timestamp_s for f in got] == pytest.approx([i / 10 for i in range(len(want))])


def _npy_header(shape: tuple[int, ...], descr: str = "<u2") -> bytes:
    out = io.BytesIO()
    np.lib.format.write_array_header_1_0(
        out, {"descr": descr, "fortran_order": False, "shape": shape}
    )
    return out.getvalue()


@pytest.mark.parametrize(
    ("content", "says"),
    [
        (_npy_header((3, 48, 64)) + bytes(100), "truncated"),
        (_npy_header((3, 40000, 40000)) + bytes(100), "40000"),
        (_npy_header((48, 64), "<i4") + bytes(48 * 64 * 4), "expected"),
        (_npy_header((48, 64), "|O") + bytes(64), "expected"),
        (b"\x93NUMPY\x01\x00\xff\xff" + b"{" * 50, "not a readable .npy"),
        (b"not numpy", "not a readable .npy"),
    ],
)
def test_bad_npy_files_are_one_line_before_anything_is_read(tmp_path, content, says):
    path = tmp_path / "d.npy"
    path.write_bytes(content)
    with pytest.raises(RecordingError, match=says) as info:
        read_all(f"replay:{path}?rate=max&{INTR}")
    assert "\n" not in str(info.value)


def test_npy_without_intrinsics_says_how_to_give_them(tmp_path):
    np.save(tmp_path / "d.npy", stack())
    with pytest.raises(RecordingError, match="no intrinsics") as info:
        read_all(f"replay:{tmp_path / 'd.npy'}?rate=max")
    assert "fx=" in info.value.hint


def test_a_fifo_named_npy_is_refused_not_waited_on(tmp_path):
    os.mkfifo(tmp_path / "d.npy")
    with pytest.raises(RecordingError, match="not a regular file"):
        read_all(f"replay:{tmp_path / 'd.npy'}?rate=max&{INTR}")


def test_spec_lens_options_reach_an_npz_without_intrinsics(tmp_path):
    path = tmp_path / "x.npz"
    np.savez(path, depth_mm=stack(1))
    got = read_all(f"replay:{path}?rate=max&{INTR}&k1=-0.25&p2=0.001")
    assert (got[0].intrinsics.k1, got[0].intrinsics.p2) == (-0.25, 0.001)
    assert got[0].intrinsics.fx == SMALL.fx
