"""StageTables: a mount change waits for its tables on a worker while the frames go on with the
nearest mount whose tables exist; only a camera's first frame builds them on the frame."""

from __future__ import annotations

import dataclasses
import logging
import os
import sys
import threading

import numpy as np
import pytest

from depthnav_daemon.daemon.stage_tables import BUILD_SWITCH_S, KEEP_READY, StageTables
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
        self.switch: list[float] = []  # the interpreter's switch interval during the build
        self.called = threading.Event()
        self.release = threading.Event()
        self.fail = False

    def __call__(self, intr: Intrinsics, mount: Mount) -> None:
        self.calls.append((intr, mount))
        self.threads.append(threading.get_ident())
        self.switch.append(sys.getswitchinterval())
        self.called.set()
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
    if hasattr(os, "getpriority"):
        # at the frame loop's own priority: a niced worker, preempted on a busy machine while it
        # held the interpreter lock, kept frames waiting for it tens of ms (stage_tables._serve)
        mine = os.getpriority(os.PRIO_PROCESS, threading.get_native_id())
        assert gate.nice and all(n == mine for n in gate.nice)
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


PRIOR_A = ("window", 1)  # stand-ins for the pose stage's PoseParams (anything hashable)
PRIOR_B = ("window", 2)


def test_a_new_prior_window_is_built_on_the_worker_while_the_estimate_searches_the_last() -> None:
    gate, priors = Gate(), Gate()
    tables = StageTables(gate, prepare_prior=priors)
    assert tables.prior_for(INTR, PRIOR_A) == PRIOR_A  # a camera's first: built on the frame
    assert tables.prior_for(OTHER, PRIOR_B) == PRIOR_B  # another camera's first too
    assert tables.prior_for(INTR, PRIOR_B) == PRIOR_A  # a new window: the last one meanwhile
    assert tables.prior_for(INTR, PRIOR_B) == PRIOR_A
    priors.release.set()
    tables.close()
    assert tables.prior_for(INTR, PRIOR_B) == PRIOR_B  # once the worker has built it
    assert tables.prior_for(INTR, PRIOR_A) == PRIOR_A  # a window whose table exists: at once
    assert priors.calls == [(INTR, PRIOR_B)]  # one build, however many frames asked
    assert gate.calls == []
    assert threading.get_ident() not in priors.threads


def test_a_mount_change_builds_the_pose_window_around_the_new_mount_too() -> None:
    gate, priors = Gate(), Gate()
    tables = StageTables(gate, prepare_prior=priors)
    tables.mount_for(INTR, M0)
    assert tables.prior_for(INTR, PRIOR_A) == PRIOR_A
    asked: list[Mount] = []

    def window() -> tuple[str, int]:
        asked.append(LARGE)
        return PRIOR_B

    assert tables.mount_for(INTR, LARGE, window) == M0
    assert tables.mount_for(INTR, LARGE, window) == M0
    assert tables.prior_for(INTR, PRIOR_B) == PRIOR_A  # the job under way makes it
    gate.release.set()
    priors.release.set()
    tables.close()
    assert tables.prior_for(INTR, PRIOR_B) == PRIOR_B
    assert tables.mount_for(INTR, LARGE, window) == LARGE
    assert gate.calls == [(INTR, LARGE)] and priors.calls == [(INTR, PRIOR_B)]
    assert len(asked) == 1  # asked once, when the build started
    assert threading.get_ident() not in gate.threads + priors.threads
    assert gate.threads == priors.threads  # one job: the mount's tables, then its window


def test_a_window_whose_table_exists_is_not_built_again_with_a_mount() -> None:
    gate, priors = Gate(), Gate()
    gate.release.set()
    tables = StageTables(gate, prepare_prior=priors)
    tables.mount_for(INTR, M0)
    tables.prior_for(INTR, PRIOR_A)
    tables.mount_for(INTR, LARGE, lambda: PRIOR_A)
    tables.close()
    tables.mount_for(INTR, SMALL, lambda: None)  # no pose stage: nothing to build
    tables.close()
    assert gate.calls == [(INTR, LARGE), (INTR, SMALL)]
    assert priors.calls == []


def test_a_failed_window_build_leaves_the_error_to_the_estimate() -> None:
    priors = Gate()
    priors.fail = True
    priors.release.set()
    tables = StageTables(Gate(), prepare_prior=priors)
    assert tables.prior_for(INTR, PRIOR_A) == PRIOR_A
    assert tables.prior_for(INTR, PRIOR_B) == PRIOR_A
    tables.close()
    assert tables.prior_for(INTR, PRIOR_B) == PRIOR_B  # estimate_pose then raises the error


def test_the_frame_loop_builds_no_table_after_a_cameras_first_frame(monkeypatch) -> None:
    """Through FrameStep (as the daemon runs it): a camera configured on a mast, outside the pose
    window, finds its floor elsewhere; the new mount's scan tables and the pose window around it
    are built on the worker, and what it serves equals a fresh build."""
    from depthnav_daemon.config.loader import build_config
    from depthnav_daemon.daemon.frame_step import FrameStep
    from depthnav_daemon.pipeline import pose_fit, process
    from depthnav_daemon.sim.synthetic import Scene, render
    from drivers.base import Frame
    from tests.pipeline.scenes import ASYM_640

    builds: dict[str, list[int]] = {"scan": [], "pose": []}

    def spy(name: str, kernel):  # the real kernel, noting the thread that runs it
        def run(*args):
            builds[name].append(threading.get_ident())
            return kernel(*args)

        return run

    monkeypatch.setattr(
        scan_table, "exact_codes_kernel", spy("scan", scan_table.exact_codes_kernel)
    )
    monkeypatch.setattr(
        pose_fit, "pose_envelope_kernel", spy("pose", pose_fit.pose_envelope_kernel)
    )
    cfg = build_config(
        [],
        [
            "mount.height_m=0.9",  # configured; the pose window below does not contain it
            "mount.tilt_deg=20.0",
            "pose.height_max_m=0.6",
            "pose.min_inlier_ratio=0.2113",  # a window no other test builds
            "daemon.pose_every_frames=1",
        ],
        {"device": "synthetic"},
    )
    true_mount = Mount(1.1, 24.0, 0.0)
    step = FrameStep(cfg, StageParams(scan=cfg.scan, cliff=cfg.cliff), None)
    view = render(Scene(), ASYM_640, true_mount)
    results = []
    try:
        for seq in range(8):
            # the first frame sees no floor: the configured mount serves it, the floor found on
            # the second frame is a large change
            depth = view.depth_mm if seq else np.zeros_like(view.depth_mm)
            results.append(step.run(Frame(seq, seq / 30.0, depth, ASYM_640)))
            if seq == 2:
                step.close()  # the worker's build done: the next frames use it
    finally:
        step.close()
    me = threading.get_ident()
    # the first frame builds the configured mount's tables and its pose window; nothing else
    # is built on the frame loop's thread
    assert builds["scan"][0] == me and builds["pose"][0] == me
    assert builds["scan"][1:] and all(t != me for t in builds["scan"][1:])
    assert builds["pose"][1:] and all(t != me for t in builds["pose"][1:])
    first, last = results[1], results[-1]
    assert results[0].mount.height_m == 0.9 and first.mount.height_m == 0.9
    assert first.pose is not None and first.pose.ok
    assert last.pose is not None and last.pose.ok  # the estimate searched the new window
    assert last.mount.height_m == pytest.approx(1.1, abs=0.02)
    assert last.mount.tilt_deg == pytest.approx(24.0, abs=0.5)
    # what the worker built serves exactly what a fresh build gives
    window = dataclasses.replace(
        cfg.pose, height_min_m=0.8, height_max_m=1.4, tilt_min_deg=14.0, tilt_max_deg=34.0
    )
    cached = pose_fit._pose_table(ASYM_640, window)
    fresh = pose_fit._pose_table.__wrapped__(ASYM_640, window)
    for f in dataclasses.fields(cached):
        a, b = getattr(cached, f.name), getattr(fresh, f.name)
        assert np.array_equal(a, b) if isinstance(a, np.ndarray) else a == b
    frame = Frame(99, 0.0, view.depth_mm, ASYM_640)
    served = process(frame, last.mount, step.params)
    scan_table.exact_table.cache_clear()  # a fresh build of every table of this mount
    again = process(frame, last.mount, step.params)
    assert np.array_equal(served.scan.ranges, again.scan.ranges, equal_nan=True)
    assert served.cliff is not None and again.cliff is not None
    assert np.array_equal(served.cliff.scan.ranges, again.cliff.scan.ranges, equal_nan=True)


def test_the_switch_interval_is_short_while_a_build_runs_and_restored_after() -> None:
    # a frame loop waiting for the interpreter lock while the worker runs Python code waits
    # the switch interval before it asks for it
    before = sys.getswitchinterval()
    assert before > BUILD_SWITCH_S  # Python's default, 5 ms
    a, b = Gate(), Gate()
    one, two = StageTables(a), StageTables(b)  # two sensors build at once
    one.mount_for(INTR, M0)
    two.mount_for(OTHER, M0)
    one.mount_for(INTR, LARGE)
    two.mount_for(OTHER, LARGE)
    assert a.called.wait(10.0) and b.called.wait(10.0)  # both builds under way
    a.release.set()
    one.close()
    # (Python keeps the interval in whole microseconds: 1e-4 reads back as 9.999...e-05)
    assert sys.getswitchinterval() == pytest.approx(BUILD_SWITCH_S)  # the other build still runs
    b.release.set()
    two.close()
    assert a.switch == b.switch == [pytest.approx(BUILD_SWITCH_S)]
    assert sys.getswitchinterval() == before


def test_a_build_goes_to_the_worker_started_with_the_tables_and_ends_with_them() -> None:
    import gc

    gate = Gate()
    gate.release.set()
    tables = StageTables(gate)
    worker = tables._worker
    assert worker is not None and worker.is_alive()  # started before any frame
    tables.mount_for(INTR, M0)
    tables.mount_for(INTR, LARGE)
    assert gate.called.wait(10.0)
    assert gate.threads == [worker.ident]  # no thread started by the frame that changed mount
    tables.close()
    assert not worker.is_alive()  # close() stops it ...
    assert tables.mount_for(INTR, LARGE) == LARGE
    far = Mount(0.9, 30.0, 5.0)
    assert tables.mount_for(INTR, far) == LARGE  # ... and a later build starts one again
    tables.close()
    assert tables.mount_for(INTR, far) == far
    assert len(gate.threads) == 2 and threading.get_ident() not in gate.threads
    left = StageTables(gate)  # never closed: its worker ends when the tables are collected
    lone = left._worker
    assert lone is not None
    del left
    gc.collect()
    lone.join(10.0)
    assert not lone.is_alive()
