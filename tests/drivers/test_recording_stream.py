"""Recordings larger than memory: write_recording spools frames to disk, replay streams them."""

from __future__ import annotations

import json
import threading
import tracemalloc
import zipfile
from collections.abc import Iterator

import numpy as np
import pytest

import drivers
from drivers import replay
from drivers.base import Frame, Intrinsics
from drivers.errors import RecordingError
from drivers.formats.recording import (
    Recording,
    RecordingStream,
    open_recording_stream,
    read_recording,
    recording_depth_nbytes,
)
from drivers.formats.recording_writer import write_recording
from tests.drivers.driverkit import SMALL, ramp_frames, run_isolated

QVGA = Intrinsics(160, 120, 150.5, 148.25, 79.75, 60.5)


def lazy_frames(n: int, intr: Intrinsics = QVGA) -> Iterator[Frame]:
    """``n`` frames made one at a time (a device), each depth distinct and easy to compress."""
    row = np.arange(intr.width, dtype=np.uint16) * 7 + 400
    for i in range(n):
        depth = np.broadcast_to(row + i, (intr.height, intr.width)).copy()
        depth[i % intr.height] = 0
        yield Frame(i, i / 30, depth, intr, (0.01 * i, -9.7, -1.4))


def test_write_holds_a_frame_not_the_recording(tmp_path, monkeypatch):
    monkeypatch.setattr("drivers.formats.recording_writer._COPY_CHUNK_BYTES", 64 << 10)
    n = 300
    total = n * QVGA.width * QVGA.height * 2  # 11.5 MB of frames
    tracemalloc.start()
    try:
        write_recording(tmp_path / "rec", lazy_frames(n))
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    # np.stack of a frame list held twice the total; streaming holds ~a frame and a chunk
    assert peak < total / 20, (peak, total)
    with np.load(tmp_path / "rec" / "frames.npz") as npz:
        assert npz["depth_mm"].shape == (n, QVGA.height, QVGA.width)


def test_round_trip_matches_np_load(tmp_path):
    frames = ramp_frames(7)
    truth = {"tilt_deg": 5.0, "name": "ramp", "ok": True, "sizes": [1, 2]}
    assert write_recording(tmp_path / "rec", frames, description="d", truth=truth) == 7
    npz_path = tmp_path / "rec" / "frames.npz"
    with zipfile.ZipFile(npz_path) as zf:
        infos = zf.infolist()
        assert [i.filename for i in infos] == [
            "depth_mm.npy",
            "intrinsics.npy",
            "timestamp_s.npy",
            "accel_mps2.npy",
        ]
        assert all(i.compress_type == zipfile.ZIP_DEFLATED for i in infos)
    with np.load(npz_path, allow_pickle=False) as npz:
        assert npz["depth_mm"].dtype == np.uint16
        np.testing.assert_array_equal(npz["depth_mm"], np.stack([f.depth_mm for f in frames]))
        np.testing.assert_array_equal(npz["timestamp_s"], [f.timestamp_s for f in frames])
        np.testing.assert_array_equal(npz["accel_mps2"], [f.accel_mps2 for f in frames])
        np.testing.assert_array_equal(npz["intrinsics"], SMALL.as_array())
    rec = read_recording(tmp_path / "rec")
    assert rec.truth == truth and rec.description == "d" and rec.intrinsics == SMALL


def test_accel_kept_only_when_every_frame_has_it(tmp_path, caplog):
    frames = ramp_frames(3)
    frames[1] = Frame(1, frames[1].timestamp_s, frames[1].depth_mm, SMALL)
    write_recording(tmp_path / "rec", frames)
    assert "only some frames had accelerometer data" in caplog.text
    with np.load(tmp_path / "rec" / "frames.npz") as npz:
        assert "accel_mps2" not in npz.files
    write_recording(tmp_path / "none", ramp_frames(2, accel=False))
    assert read_recording(tmp_path / "none").accel_mps2 is None


def test_a_stop_keeps_every_frame_taken_and_reports_progress(tmp_path):
    """cmd_record's generator ends when a signal sets its stop event: what came is written."""
    stop = threading.Event()
    taken: list[int] = []
    squeezed: list[tuple[int, int]] = []

    def until_stopped() -> Iterator[Frame]:
        for frame in lazy_frames(1000):
            if stop.is_set():
                return
            yield frame
            if frame.seq == 4:
                stop.set()  # the user pressed Ctrl-C after the fifth frame

    n = write_recording(
        tmp_path / "rec",
        until_stopped(),
        progress=taken.append,
        progress_compress=lambda done, total: squeezed.append((done, total)),
    )
    assert n == 5 and taken == [1, 2, 3, 4, 5]
    rec = read_recording(tmp_path / "rec")
    expected = list(lazy_frames(5))
    np.testing.assert_array_equal(rec.depth_mm, np.stack([f.depth_mm for f in expected]))
    total = 5 * QVGA.width * QVGA.height * 2
    assert squeezed[-1] == (total, total)
    assert [d for d, _ in squeezed] == sorted({d for d, _ in squeezed})


def test_an_error_mid_stream_leaves_nothing(tmp_path):
    other = Intrinsics(160, 120, 100.0, 100.0, 80.0, 60.0)

    def switching() -> Iterator[Frame]:
        yield from lazy_frames(3)
        yield Frame(3, 0.1, np.zeros((120, 160), np.uint16), other)

    with pytest.raises(RecordingError, match="frame 3 has intrinsics"):
        write_recording(tmp_path / "rec", switching())
    assert not (tmp_path / "rec").exists()
    (tmp_path / "empty").mkdir()
    with pytest.raises(RecordingError, match="no frames"):
        write_recording(tmp_path / "empty", iter(()))
    assert list((tmp_path / "empty").iterdir()) == []  # the folder was there: it stays, empty


DISK_FULL = """
import json, resource, signal, sys
import numpy as np
from drivers.base import Frame, Intrinsics
from drivers.errors import RecordingError
from drivers.formats.recording_writer import write_recording

intr = Intrinsics(160, 120, 150.0, 150.0, 80.0, 60.0)
rng = np.random.default_rng(5)
frames = [
    Frame(i, i / 30, rng.integers(0, 65535, (120, 160), dtype=np.uint16), intr) for i in range(8)
]
raw = 8 * 160 * 120 * 2
limit = raw // 2 if sys.argv[2] == "recording" else raw + 64
signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
resource.setrlimit(resource.RLIMIT_FSIZE, (limit, limit))
try:
    write_recording(sys.argv[1], frames)
    print(json.dumps({"error": None}))
except RecordingError as exc:
    print(json.dumps({"error": str(exc), "hint": exc.hint}))
"""


@pytest.mark.parametrize("phase", ["recording", "compressing"])
def test_a_full_disk_gives_one_line_and_leaves_nothing(tmp_path, phase):
    """A file-size limit fails writes with EFBIG the way a full disk fails with ENOSPC: while
    the frames are spooled, or (noise does not compress) while frames.npz is written."""
    out = tmp_path / "rec"
    p = run_isolated(DISK_FULL, str(out), phase)
    assert p.returncode == 0, p.stderr
    got = json.loads(p.stdout)
    assert got["error"] and "\n" not in got["error"], got
    assert str(out) in got["error"] and "File too large" in got["error"]
    assert "free some disk space" in got["hint"]
    assert not out.exists()


def test_the_stream_gives_the_frames_read_recording_gives(tmp_path):
    write_recording(tmp_path / "rec", ramp_frames(6), description="six", truth={"a": 1})
    rec = read_recording(tmp_path / "rec")
    stream = open_recording_stream(tmp_path / "rec")
    assert stream.shape == rec.depth_mm.shape and stream.depth_nbytes == rec.depth_mm.nbytes
    assert recording_depth_nbytes(tmp_path / "rec") == rec.depth_mm.nbytes
    assert (stream.intrinsics, stream.description, stream.truth) == (SMALL, "six", {"a": 1})
    np.testing.assert_array_equal(stream.timestamp_s, rec.timestamp_s)
    np.testing.assert_array_equal(stream.accel_mps2, rec.accel_mps2)
    for _ in range(2):  # every call starts again at frame 0
        got = list(stream.iter_depth())
        assert all(f.dtype == np.uint16 and f.shape == (48, 64) for f in got)
        np.testing.assert_array_equal(np.stack(got), rec.depth_mm)


def _bare(tmp_path, name, save, depth, version=None):
    path = tmp_path / name
    if version is None:
        save(path, depth_mm=depth, intrinsics=SMALL.as_array())
    else:
        with zipfile.ZipFile(path, "w") as zf:
            for key, value in (("depth_mm", depth), ("intrinsics", SMALL.as_array())):
                with zf.open(key + ".npy", "w") as fid:
                    np.lib.format.write_array(fid, value, version=version)
    return path


@pytest.mark.parametrize(
    ("save", "version"), [(np.savez, None), (np.savez_compressed, None), (None, (2, 0))]
)
def test_the_stream_reads_stored_members_and_npy_2_headers(tmp_path, save, version):
    depth = np.stack([f.depth_mm for f in ramp_frames(3)])
    path = _bare(tmp_path, "x.npz", save, depth, version)
    stream = open_recording_stream(path, default_fps=10.0)
    np.testing.assert_array_equal(np.stack(list(stream.iter_depth())), depth)
    np.testing.assert_allclose(stream.timestamp_s, [0.0, 0.1, 0.2])
    assert stream.accel_mps2 is None


@pytest.mark.parametrize("kind", ["fortran", "float", "big_endian", "2d"])
def test_the_stream_refuses_layouts_it_cannot_read_a_frame_at_a_time(tmp_path, kind):
    depth = np.stack([f.depth_mm for f in ramp_frames(3)])
    depth = {
        "fortran": np.asfortranarray(depth),
        "float": depth.astype(np.float32),
        "big_endian": depth.astype(">u2"),
        "2d": depth[0],
    }[kind]
    path = _bare(tmp_path, "x.npz", np.savez, depth)
    with pytest.raises(RecordingError, match="'depth_mm' must be uint16") as info:
        open_recording_stream(path)
    assert str(path) in str(info.value) and "\n" not in str(info.value)


def test_damaged_archives_give_one_line_errors(tmp_path):
    write_recording(tmp_path / "rec", lazy_frames(20))
    data = (tmp_path / "rec" / "frames.npz").read_bytes()
    truncated = tmp_path / "truncated.npz"
    truncated.write_bytes(data[: len(data) // 2])
    for call in (open_recording_stream, recording_depth_nbytes, read_recording):
        with pytest.raises(RecordingError) as info:
            call(truncated)
        assert str(truncated) in str(info.value) and "\n" not in str(info.value)

    # a flipped byte inside the compressed frames: only reading them finds it
    flipped = tmp_path / "flipped.npz"
    with zipfile.ZipFile(tmp_path / "rec" / "frames.npz") as zf:
        info_ = zf.getinfo("depth_mm.npy")
    at = info_.header_offset + 30 + len(info_.filename) + len(info_.extra) + 2000
    flipped.write_bytes(data[:at] + bytes([data[at] ^ 0x55]) + data[at + 1 :])
    stream = open_recording_stream(flipped)
    with pytest.raises(RecordingError) as err:
        list(stream.iter_depth())
    assert str(flipped) in str(err.value) and "\n" not in str(err.value)


def _replay(spec: str, count: int) -> tuple[list[Frame], object]:
    driver = drivers.create_driver(spec)
    with drivers.opened(driver):
        kind = type(driver._recording)
        return [driver.read_frame() for _ in range(count)], kind


def test_replay_streams_above_the_cap_and_loops_like_the_cache(tmp_path, monkeypatch):
    write_recording(tmp_path / "rec", ramp_frames(4))
    spec = f"replay:{tmp_path / 'rec'}?rate=max&loop=1&start=1"
    cached, kind = _replay(spec, 10)
    assert kind is Recording
    monkeypatch.setattr(replay, "CACHE_MAX_BYTES", 1000)  # the recording is 24 kB decoded
    streamed, kind = _replay(spec, 10)
    assert kind is RecordingStream
    assert [f.seq for f in streamed] == list(range(10))
    for a, b in zip(cached, streamed, strict=True):
        np.testing.assert_array_equal(a.depth_mm, b.depth_mm)
        assert (a.timestamp_s, a.accel_mps2, a.intrinsics) == (
            b.timestamp_s,
            b.accel_mps2,
            b.intrinsics,
        )
    originals = ramp_frames(4)
    np.testing.assert_array_equal(streamed[0].depth_mm, originals[1].depth_mm)
    np.testing.assert_array_equal(streamed[3].depth_mm, originals[0].depth_mm)  # looped


def test_replay_of_a_damaged_streamed_recording_is_one_line(tmp_path, monkeypatch):
    monkeypatch.setattr(replay, "CACHE_MAX_BYTES", 0)
    write_recording(tmp_path / "rec", lazy_frames(20))
    path = tmp_path / "cut.npz"
    data = (tmp_path / "rec" / "frames.npz").read_bytes()
    path.write_bytes(data[: len(data) // 2])
    driver = drivers.create_driver(f"replay:{path}?rate=max")
    with pytest.raises(RecordingError) as info, drivers.opened(driver):
        list(drivers.iter_frames(driver))
    assert str(path) in str(info.value) and "\n" not in str(info.value)
