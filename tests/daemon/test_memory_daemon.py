"""The memory in the daemon: from a recording's odometry, from a live source, and every way the
odometry can fail (none, silent, stale, jumping); MAVLink from the memory scan."""

from __future__ import annotations

import dataclasses
import json
import logging
import math
import socket
import threading
import time
from pathlib import Path

import numpy as np
import orjson
import pytest

from depthnav_daemon.config.loader import MemorySettings, OdometrySettings, build_config
from depthnav_daemon.daemon.loop import run
from depthnav_daemon.daemon.memory_keeper import MemoryKeeper, sensor_view
from depthnav_daemon.daemon.source import DeviceSource
from depthnav_daemon.pipeline import StageParams, process
from depthnav_daemon.pipeline.cliff import CliffParams
from depthnav_daemon.pipeline.cliff_table import cliff_table
from depthnav_daemon.pipeline.coverage import floor_extent
from depthnav_daemon.pipeline.memory import MemoryResult, scan_limits
from depthnav_daemon.pipeline.scan import LaserScan, ScanParams
from depthnav_daemon.sim.fixtures import DRIVE_MOUNT
from depthnav_daemon.sinks.json.message import decode_ranges, memory_to_json
from depthnav_daemon.sinks.mavlink.sectors import UNKNOWN as UINT16_MAX
from depthnav_daemon.sinks.mavlink.sectors import memory_sectors, sectors_for
from drivers.errors import DeviceOpenError
from drivers.formats.recording import read_recording
from drivers.odometry import create_odometry
from tests.daemon.test_loop import SPEC as CORRIDOR
from tests.daemon.test_loop import CollectSink

FIXTURES = Path(__file__).resolve().parents[2] / "fixtures"
DRIVE = f"replay:{FIXTURES / 'drive_step'}?rate=max"
STEP_M = 3.0


def _ahead(scan: LaserScan) -> float:
    return float(scan.ranges[int(np.argmin(np.abs(scan.angles)))])


def _run(spec: str, *sets: str, frames: int | None = None) -> CollectSink:
    sink = CollectSink()
    cfg = build_config([], list(sets), {"device": spec})
    run(cfg, threading.Event(), max_frames=frames, sink_factory=lambda _s: sink)
    return sink


def test_replayed_drive_keeps_the_step_in_memory_through_the_dead_zone() -> None:
    results = _run(DRIVE).results
    assert len(results) == 12 and all(r.memory.status == "on" for r in results)
    mem_err, live_err = [], []
    for r in results[1:]:  # at 3 m the default 8-row cliff sampling sees the edge a frame later
        truth = STEP_M - r.memory.pose[0]
        mem_err.append(_ahead(r.memory.scan) - truth)
        live_err.append(_ahead(r.cliff.scan) - truth)
    # the cliff stage puts the edge up to ~7 cm short at 2.75 m with its default 16 px blocks
    # (the safe side); the memory keeps the nearest it was told, never farther than the edge
    assert -0.08 <= np.min(mem_err) and np.max(mem_err) <= 0.05
    # the last frames: the edge is in the lower dead zone, the live cliff scan reports the first
    # floor it sees (0.65 m) instead; the memory still has the edge
    assert min(live_err[-2:]) > 0.1
    last = results[-1]
    assert last.memory.cliff_cells > 50 and last.memory.grid.grid.shape == (160, 160)
    # MAVLink is built from the memory: 72 sectors of 5 deg around the robot, ahead = index 36
    sec = sectors_for(last, cliff=False)
    assert sec.angle_offset_deg == -180.0 and sec.increment_f_deg == 5.0
    assert sec.distances_cm[36] == pytest.approx(100 * (STEP_M - last.memory.pose[0]), abs=8)
    assert sec.distances_cm[0] == UINT16_MAX  # behind: never seen, unknown (not clear)


def test_memory_sectors_put_left_left_and_behind_first() -> None:
    inc = 2 * math.pi / 360
    ranges = np.full(360, np.inf, np.float32)
    ranges[270] = 1.0  # bearing -pi + 270 deg = +90 deg: on the left
    ranges[0] = 2.0  # -180 deg: behind
    scan = LaserScan(-math.pi, -math.pi + 359 * inc, inc, 0.0, 5.657, ranges)
    sec = memory_sectors(scan)
    # clockwise bearings: left is -90 deg -> sector (-90 + 180) / 5 = 18; behind -> sector 0
    assert sec.distances_cm[18] == 100 and sec.distances_cm[0] == 200
    assert (np.delete(sec.distances_cm, [0, 18]) == sec.max_cm + 1).all()


def test_memory_off_without_odometry_says_so_once(caplog) -> None:
    with caplog.at_level(logging.INFO):
        results = _run(CORRIDOR, frames=4).results
    assert len(results) == 4 and all(r.memory is None for r in results)
    said = [r.getMessage() for r in caplog.records if "no odometry" in r.getMessage()]
    assert len(said) == 1


def test_memory_disabled_is_off_even_with_odometry() -> None:
    results = _run(DRIVE, "memory.enabled=false", frames=3).results
    assert all(r.memory is None for r in results)


def test_a_source_that_never_speaks_is_one_line_and_the_daemon_runs_on(caplog) -> None:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    with caplog.at_level(logging.WARNING):
        sink = CollectSink()
        cfg = build_config(
            [],
            [f'odometry.source="odom+udp://127.0.0.1:{port}"', "odometry.timeout_s=0.05"],
            {"device": CORRIDOR.replace("rate=max", "rate=realtime")},
        )
        run(cfg, threading.Event(), max_frames=6, sink_factory=lambda _s: sink)
    assert len(sink.results) == 6 and all(r.memory is None for r in sink.results)
    said = [r.getMessage() for r in caplog.records if "has sent nothing" in r.getMessage()]
    assert len(said) == 1 and "\n" not in said[0]


def test_a_source_that_cannot_open_ends_the_start_up_and_closes_the_device(monkeypatch) -> None:
    """As a device or a serial tilt port that cannot open: the robot asked for the memory."""
    closed = []
    real_close = DeviceSource.close
    monkeypatch.setattr(DeviceSource, "close", lambda self: closed.append(1) or real_close(self))
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as busy:
        busy.bind(("127.0.0.1", 0))
        spec = f"odom+udp://127.0.0.1:{busy.getsockname()[1]}"
        with pytest.raises(DeviceOpenError, match="cannot listen") as info:
            _run(CORRIDOR, f'odometry.source="{spec}"', frames=2)
    assert "\n" not in str(info.value) and info.value.hint
    assert closed  # the depth device opened before it is closed again


@pytest.fixture(scope="module")
def drive():
    """The drive fixture's frames (odometry taken off) and their results."""
    rec = read_recording(FIXTURES / "drive_step")
    params = StageParams(scan=ScanParams(), cliff=CliffParams())
    frames = rec.frames()
    results = [process(f, DRIVE_MOUNT, params) for f in frames]
    return frames, results, params


def test_live_odometry_stale_freezes_and_fresh_resumes(drive, caplog) -> None:
    frames, results, params = drive
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    src = create_odometry(f"odom+udp://127.0.0.1:{port}")
    src.start()
    keeper = MemoryKeeper(MemorySettings(), OdometrySettings(stale_s=0.5), src)
    tx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    try:

        def speak(x: float) -> float:
            n = src.buffer.count
            tx.sendto(b'{"x_m": %f, "y_m": 0, "yaw_rad": 0}' % x, ("127.0.0.1", port))
            end = time.monotonic() + 10
            while src.buffer.count == n:
                assert time.monotonic() < end
                time.sleep(0.01)
            return src.buffer.latest().t_s

        live = [dataclasses.replace(f, odom=None) for f in frames]
        t = speak(0.0)
        on = keeper.step(live[0], t + 0.01, [(results[0], params)])
        assert on.status == "on" and on.pose == (0.0, 0.0, 0.0)
        with caplog.at_level(logging.WARNING):
            a = keeper.step(live[1], t + 0.8, [(results[1], params)])
            b = keeper.step(live[2], t + 1.6, [(results[2], params)])
        assert a.status == b.status == "frozen" and a.scan is None and a.pose is None
        assert a.cliff_cells == on.cliff_cells  # not updated while frozen
        said = [r.getMessage() for r in caplog.records if "frozen" in r.getMessage()]
        assert len(said) == 1  # once per stale spell
        t = speak(0.25)
        back = keeper.step(live[1], t, [(results[1], params)])
        assert back.status == "on" and back.pose[0] == pytest.approx(0.25)
    finally:
        tx.close()
        src.stop()


def test_odometry_jump_resets_the_memory(drive, caplog) -> None:
    frames, results, params = drive
    keeper = MemoryKeeper(MemorySettings(), OdometrySettings(max_jump_m=0.5), None)
    first = keeper.step(frames[1], 0.0, [(results[1], params)])
    assert first.status == "on" and first.cliff_cells > 0
    jumped = dataclasses.replace(frames[2], odom=(5.0, 0.0, 0.0))
    with caplog.at_level(logging.WARNING):
        out = keeper.step(jumped, 0.0, [(results[2], params)])
    # from x = 0.25 (frame 1) to 5.0
    assert out.status == "reset" and "jumped 4.75 m" in out.note and keeper.resets == 1
    # only this frame's view is in it: everything it holds is ahead of the new pose
    assert np.nanmin(out.scan.ranges) > 1.0
    assert any("jumped" in r.getMessage() for r in caplog.records)
    turned = dataclasses.replace(frames[3], odom=(5.0, 0.0, math.radians(90)))
    assert keeper.step(turned, 0.0, [(results[3], params)]).status == "reset"  # 90 > 45 deg


def test_a_keeper_with_nothing_to_do_is_skipped_only_once_it_has_said_so(drive, caplog) -> None:
    """The loop skips the memory step for frames that cannot change it (a step's call was ~2 % of
    the frame loop): only after the step has said why the memory is off, and never for a frame
    that carries its own pose."""
    frames, results, params = drive
    without_pose = dataclasses.replace(frames[1], odom=None)
    off = MemoryKeeper(MemorySettings(enabled=False), OdometrySettings(), None)
    assert off.idle_for(without_pose) and off.idle_for(frames[1])
    keeper = MemoryKeeper(MemorySettings(), OdometrySettings(), None)
    assert not keeper.idle_for(without_pose)  # not said yet: the step says it
    with caplog.at_level(logging.INFO):
        assert keeper.step(without_pose, 0.0, [(results[1], params)]) is None
    assert any("no odometry" in r.getMessage() for r in caplog.records)
    assert keeper.idle_for(without_pose)
    assert not keeper.idle_for(frames[2])  # a recording's own pose: the memory takes it
    assert keeper.step(frames[2], 0.0, [(results[2], params)]).status == "on"


def test_the_keeper_gives_the_memory_each_stages_rows_and_its_sensors_limits(drive) -> None:
    """The cliff stage samples fewer rows than the scan reads (its view ends nearer): the memory
    clears drop-off-free floor only where the cliff rows see it. The blind radius is the
    sensor's dead zone straight ahead, range_max the 8 m grid's reach (3.9 m) below the scan's
    5 m."""
    frames, results, params = drive
    view = sensor_view(results[1], params)
    table = cliff_table(
        results[1].intrinsics,
        results[1].mount,
        params.cliff,
        view.scan.angle_min,
        view.scan.angle_increment,
        view.scan.ranges.size,
    )
    assert view.cliff_rows == (int(table.rows.min()), results[1].intrinsics.height, 1)
    assert view.rows[0] < view.cliff_rows[0]
    keeper = MemoryKeeper(MemorySettings(), OdometrySettings(), None)
    out = keeper.step(frames[1], 0.0, [(results[1], params)])
    blind, rmax = scan_limits(keeper.state)
    sc = view.scan
    near, _ = floor_extent(
        results[1].intrinsics,
        DRIVE_MOUNT,
        sc.angle_min,
        sc.angle_increment,
        sc.ranges.size,
        view.rows,
    )
    # the dead zone straight ahead and a cell's diagonal (the fill marks cells only whole)
    diag = 1.5 * math.sqrt(2) * keeper.state.params.cell_m
    assert blind == pytest.approx(float(near[int(np.argmin(np.abs(sc.angles)))]) + diag)
    assert rmax == out.scan.range_max == pytest.approx(3.9)


def test_unknown_and_clear_memory_bins_reach_json_and_mavlink_as_such() -> None:
    """REP 117 through the sinks: NaN (unknown) is JSON null and MAVLink UINT16_MAX; +inf (known
    free to range_max) is "Infinity" and max_distance + 1."""
    inc = 2 * math.pi / 360
    ranges = np.full(360, np.nan, np.float32)
    ranges[170:191] = np.inf  # ahead: known free
    ranges[270] = 1.0  # left: an obstacle
    scan = LaserScan(-math.pi, -math.pi + 359 * inc, inc, 0.0, 3.9, ranges)
    sec = memory_sectors(scan)
    assert sec.max_cm == 390 and sec.distances_cm[36] == sec.max_cm + 1  # ahead
    assert sec.distances_cm[18] == 100 and sec.distances_cm[0] == UINT16_MAX  # left; behind
    result = MemoryResult("on", scan, 1, 0, (0.0, 0.0, 0.0), None, 8.0, 0.05)
    out = json.loads(orjson.dumps(memory_to_json(result)))
    decoded = decode_ranges(out["scan"]["ranges"])
    assert out["scan"]["ranges"][0] is None and out["scan"]["ranges"][180] == "Infinity"
    np.testing.assert_array_equal(decoded, ranges.astype(np.float64))
    assert out["scan"]["range_max"] == 3.9


def test_a_memory_sector_with_a_hidden_bin_is_unknown() -> None:
    """A memory bin read NaN because a view's shadow lies in front of its remembered point
    (MemoryScan.hidden) may hide something nearer than the sector's other points: the sector is
    unknown, not their minimum; a plain unknown bin beside a point leaves the point."""
    inc = 2 * math.pi / 360
    ranges = np.full(360, np.inf, np.float32)
    ranges[178:181] = 2.0  # ahead, sector 36 (177.5-182.5 deg from behind)
    ranges[181] = np.nan
    scan = LaserScan(-math.pi, -math.pi + 359 * inc, inc, 0.0, 3.9, ranges)
    assert memory_sectors(scan).distances_cm[36] == 200
    hidden = np.zeros(360, bool)
    hidden[181] = True
    got, before = (
        memory_sectors(scan, hidden=hidden).distances_cm,
        memory_sectors(scan).distances_cm,
    )
    assert got[36] == UINT16_MAX
    assert np.array_equal(np.delete(got, 36), np.delete(before, 36))  # the others as they were
