"""The memory's gate for odometry in the daemon: a frame whose own pose is outside the limits
freezes the memory for that frame (one warning per kind, counted), a live source's refusals and
the frames' go out together in ``odometry_rejected``, and the loop never ends over a pose."""

from __future__ import annotations

import dataclasses
import logging
import math
import socket
import threading
import time
from pathlib import Path

import pytest

from depthnav_daemon.config.loader import MemorySettings, OdometrySettings, build_config
from depthnav_daemon.daemon.loop import run
from depthnav_daemon.daemon.memory_keeper import MemoryKeeper
from depthnav_daemon.pipeline import StageParams, process
from depthnav_daemon.pipeline.cliff import CliffParams
from depthnav_daemon.pipeline.scan import ScanParams
from depthnav_daemon.sim.fixtures import DRIVE_MOUNT
from drivers.formats.recording import read_recording
from drivers.formats.recording_writer import write_recording
from drivers.odometry import create_odometry
from tests.daemon.test_loop import CollectSink

FIXTURES = Path(__file__).resolve().parents[2] / "fixtures"
NONE_REFUSED = {"malformed": 0, "not_finite": 0, "out_of_range": 0, "out_of_order": 0}


@pytest.fixture(scope="module")
def drive():
    rec = read_recording(FIXTURES / "drive_step")
    params = StageParams(scan=ScanParams(), cliff=CliffParams())
    frames = rec.frames()
    return frames, [process(f, DRIVE_MOUNT, params) for f in frames], params


def test_a_frame_pose_outside_the_limits_freezes_the_memory_for_that_frame(drive, caplog) -> None:
    frames, results, params = drive
    poison = {2: (1e19, 0.0, 0.0), 3: (math.nan, 0.0, 0.0), 4: (0.5, 1e308, 0.0), 5: (0, 0, 1e300)}
    keeper = MemoryKeeper(MemorySettings(), OdometrySettings(max_jump_m=5.0), None)
    out = []
    with caplog.at_level(logging.WARNING):
        for i, (f, r) in enumerate(zip(frames, results, strict=True)):
            frame = dataclasses.replace(f, odom=poison[i]) if i in poison else f
            out.append(keeper.step(frame, 0.0, [(r, params)]))
    assert [m.status for m in out] == ["on"] * 2 + ["frozen"] * 4 + ["on"] * (len(frames) - 6)
    assert "x_m=1e+19 is beyond" in out[2].note and out[2].scan is None and out[2].pose is None
    assert out[-1].odometry_rejected == {**NONE_REFUSED, "not_finite": 1, "out_of_range": 3}
    assert out[0].odometry_rejected == NONE_REFUSED
    # the frozen frames changed nothing; the drive goes on where it was
    assert out[5].cliff_cells == out[1].cliff_cells and out[-1].cliff_cells > out[1].cliff_cells
    said = [r.getMessage() for r in caplog.records if "refusing a sample" in r.getMessage()]
    assert len(said) == 2  # one per kind
    assert "at frame 2: x_m=1e+19" in said[0] and "at frame 3: x_m=nan" in said[1]


def test_a_live_sources_refusals_go_out_with_the_frames(drive) -> None:
    frames, results, params = drive
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    src = create_odometry(f"odom+udp://127.0.0.1:{port}")
    src.start()
    keeper = MemoryKeeper(MemorySettings(), OdometrySettings(), src)
    try:
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as tx:
            for line in (b'{"x_m": 1e19, "y_m": 0, "yaw_rad": 0}', b"{", b'{"x_m": NaN}'):
                tx.sendto(line, ("127.0.0.1", port))
            tx.sendto(b'{"x_m": 0.5, "y_m": 0, "yaw_rad": 0}', ("127.0.0.1", port))
            end = time.monotonic() + 10
            while src.buffer.count == 0 or src.refusals.total < 3:
                assert time.monotonic() < end
                time.sleep(0.01)
        live = dataclasses.replace(frames[0], odom=None)
        got = keeper.step(live, time.monotonic(), [(results[0], params)])
        assert got.status == "on" and got.pose == (0.5, 0.0, 0.0)
        assert got.odometry_rejected == {
            **NONE_REFUSED,
            "malformed": 1,
            "not_finite": 1,
            "out_of_range": 1,
        }
    finally:
        src.stop()


def test_a_recording_with_absurd_odometry_plays_to_its_end(tmp_path, caplog) -> None:
    """In process, through the real loop: every frame comes out, the poisoned ones frozen."""
    frames = read_recording(FIXTURES / "drive_step").frames()
    frames[3] = dataclasses.replace(frames[3], odom=(1e19, 0.0, 0.0))
    frames[6] = dataclasses.replace(frames[6], odom=(math.nan, 0.0, 0.0))
    write_recording(tmp_path / "r", frames)
    sink = CollectSink()
    cfg = build_config([], ["odometry.max_jump_m=5"], {"device": f"replay:{tmp_path / 'r'}"})
    with caplog.at_level(logging.WARNING):
        run(cfg, threading.Event(), max_frames=None, sink_factory=lambda _s: sink)
    statuses = [r.memory.status for r in sink.results]
    assert len(statuses) == len(frames) and statuses.count("frozen") == 2
    assert statuses[3] == statuses[6] == "frozen"
    last = sink.results[-1].memory.odometry_rejected
    assert last == {**NONE_REFUSED, "not_finite": 1, "out_of_range": 1}
