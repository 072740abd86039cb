"""StageTables: a mount change waits for its tables on a worker while the frames go on with the
nearest mount whose tables exist; only a camera's first frame builds them on the frame."""

from __future__ import annotations

import logging
import os
import threading

import numpy as np
import pytest

from depthnav_daemon.daemon.stage_tables import KEEP_READY, MAX_NICE, StageTables
from depthnav_daemon.pipeline import StageParams, prepare, scan_table
from depthnav_daemon.pipeline.cliff import CliffParams, detect_cliffs
from depthnav_daemon.pipeline.geometry import Mount
from depthnav_daemon.pipeline.scan import ScanParams, depth_to_scan
from drivers.base import Intrinsics

INTR = Intrinsics(64, 48, 60.0, 60.0, 31.5, 23.5)
OTHER = Intrinsics(80, 60, 75.0, 75.0, 39.5, 29.5)
M0 = Mount(0.5, 15.0, 0.0)
SMALL = Mount(0.503, 15.2, 0.1)  # within 1 cm / 0.5 deg
LARGE = Mount(0.6, 15.0, 0.0)


class Gate:
    """A prepare() that records its calls and waits until released."""

    def __init__(self) -> None:
        self.calls: list[tuple[Intrinsics, Mount]] = []
        self.threads: list[int] = []
        self.nice: list[int] = []
        self.release = threading.Event()
        self.fail = False

    def __call__(self, intr: Intrinsics, mount: Mount) -> None:
        self.calls.append((intr, mount))
        self.threads.append(threading.get_ident())
        if hasattr(os, "getpriority"):
            self.nice.append(os.getpriority(os.PRIO_PROCESS, threading.get_native_id()))
        assert self.release.wait(10.0)
        if self.fail:
            raise ValueError("no table for this mount")


def test_a_cameras_first_frame_applies_its_mount_at_once() -> None:
    gate = Gate()
    tables = StageTables(gate)
    assert tables.mount_for(INTR, M0) == M0
    assert tables.mount_for(OTHER, LARGE) == LARGE  # a new camera: nothing to go on with
    assert gate.calls == []  # the stages build these on the frame itself


def test_a_large_change_goes_on_with_the_old_mount_until_its_tables_exist(
    caplog: pytest.LogCaptureFixture,
) -> None:
    gate = Gate()
    tables = StageTables(gate)
    with caplog.at_level(logging.INFO, logger="depthnav_daemon.daemon.stage_tables"):
        used = [tables.mount_for(INTR, M0)] + [tables.mount_for(INTR, LARGE) for _ in range(3)]
        assert used == [M0, M0, M0, M0]  # no frame waits for LARGE's tables
        gate.release.set()
        tables.close()
        assert tables.mount_for(INTR, LARGE) == LARGE  # the first frame after they exist
        far = Mount(0.9, 30.0, 5.0)
        assert tables.mount_for(INTR, far) == LARGE  # the nearest whose tables exist
        tables.close()
        assert tables.mount_for(INTR, far) == far
    assert gate.calls == [(INTR, LARGE), (INTR, far)]
    assert threading.get_ident() not in gate.threads  # built off the frame loop's thread
    if hasattr(os, "getpriority"):  # and below its priority (unless already at the lowest)
        mine = os.getpriority(os.PRIO_PROCESS, threading.get_native_id())
        assert all(n > mine for n in gate.nice) or mine == MAX_NICE
    said = [r for r in caplog.records if "built on a worker" in r.getMessage()]
    assert len(said) == 1  # said once, not at every change


def test_frames_go_on_with_the_nearest_mount_whose_tables_exist() -> None:
    gate = Gate()
    gate.release.set()
    tables = StageTables(gate)
    near_large = Mount(0.61, 15.3, 0.0)
    tables.mount_for(INTR, M0)
    tables.mount_for(INTR, LARGE)
    tables.close()
    assert tables.mount_for(INTR, LARGE) == LARGE
    assert tables.mount_for(INTR, M0) == M0  # back to a mount whose tables exist: at once
    gate.release.clear()
    assert tables.mount_for(INTR, near_large) == LARGE  # nearer than M0, though M0 was last
    assert tables.mount_for(INTR, Mount(0.51, 15.0, 0.0)) == M0
    gate.release.set()


def test_another_placement_is_not_served_by_this_ones_tables() -> None:
    gate = Gate()
    tables = StageTables(gate)
    tables.mount_for(INTR, M0)
    placed = Mount(0.5, 15.0, 0.0, x_m=0.2, yaw_deg=30.0)
    assert tables.mount_for(INTR, placed) == placed  # built on the frame, as a first frame
    assert gate.calls == []


def test_a_small_change_goes_on_with_the_old_mount_until_its_tables_exist() -> None:
    gate = Gate()
    tables = StageTables(gate)
    tables.mount_for(INTR, M0)
    assert tables.mount_for(INTR, SMALL) == M0  # building: frames go on with M0
    assert tables.mount_for(INTR, SMALL) == M0
    gate.release.set()
    tables.close()
    assert gate.calls == [(INTR, SMALL)]  # one build, however many frames asked
    assert tables.mount_for(INTR, SMALL) == SMALL
    assert tables.mount_for(INTR, M0) == M0  # back to a mount whose tables exist: at once
    assert len(gate.calls) == 1


def test_a_failed_build_leaves_the_error_to_the_frame_loop() -> None:
    gate = Gate()
    gate.fail = True
    gate.release.set()
    tables = StageTables(gate)
    tables.mount_for(INTR, M0)
    assert tables.mount_for(INTR, SMALL) == M0
    tables.close()
    assert tables.mount_for(INTR, SMALL) == SMALL  # process() then raises the error itself


def test_ready_mounts_are_bounded() -> None:
    gate = Gate()
    gate.release.set()
    tables = StageTables(gate)
    tables.mount_for(INTR, M0)
    for k in range(3 * KEEP_READY):
        tables.mount_for(INTR, Mount(0.5, 15.0 + 0.001 * k, 0.0))
        tables.close()
    assert len(tables._ready) <= KEEP_READY


def test_prepare_builds_exactly_the_tables_a_frame_uses() -> None:
    mount = Mount(0.55, 14.31, 0.7)  # a mount no other test builds
    scan, cliff = ScanParams(), CliffParams(block_size=8, row_step=2, col_step=2)
    prepare(INTR, mount, StageParams(scan=scan, cliff=cliff))
    before = scan_table.exact_table.cache_info()
    depth = np.full((INTR.height, INTR.width), 1500, dtype=np.uint16)
    s = depth_to_scan(depth, INTR, mount, scan)
    detect_cliffs(depth, INTR, mount, cliff, s.angle_min, s.angle_increment, s.ranges.size)
    after = scan_table.exact_table.cache_info()
    assert after.misses == before.misses and after.hits > before.hits


@pytest.mark.parametrize("method", ["exact", "paper"])
@pytest.mark.parametrize("change", [SMALL, LARGE, Mount(1.2, 50.0, -8.0)])
def test_real_tables_built_on_the_worker_serve_the_next_frames(method: str, change: Mount) -> None:
    params = StageParams(scan=ScanParams(method=method, scan_height=40))
    tables = StageTables(lambda i, m: prepare(i, m, params))
    assert tables.mount_for(INTR, M0) == M0
    prepare(INTR, M0, params)
    assert tables.mount_for(INTR, change) == M0
    tables.close()
    assert tables.mount_for(INTR, change) == change
    before = scan_table.exact_table.cache_info()
    depth_to_scan(np.full((INTR.height, INTR.width), 900, np.uint16), INTR, change, params.scan)
    if method == "exact":  # the frame finds the worker's tables
        assert scan_table.exact_table.cache_info().misses == before.misses
