"""``depthnav bench``'s large mount change: the real frame path serves every new mount from the
worker's build, and the report has its figures (reported, never asserted: no timing checks)."""

from __future__ import annotations

import math
import threading

import pytest

from depthnav_daemon.commands import bench_rebuild
from depthnav_daemon.commands.bench_rebuild import RebuildTiming, format_rebuild, rebuild_timing
from depthnav_daemon.pipeline import scan_table
from drivers.base import Intrinsics

SMALL = Intrinsics(160, 120, 142.6, 142.6, 79.5, 59.5)


def test_every_change_is_built_off_the_frame_thread_and_then_served(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    threads: list[int] = []
    real = scan_table.exact_codes_kernel

    def spy(*args):  # the real kernel, noting the thread that runs it
        threads.append(threading.get_ident())
        return real(*args)

    monkeypatch.setattr(scan_table, "exact_codes_kernel", spy)
    t = rebuild_timing("160x120", SMALL, changes=3, pace_hz=0.0, n_frames=3)
    assert isinstance(t, RebuildTiming) and t.changes == 3 and t.resolution == "160x120"
    # every change served within the bench's bound (it would report MAX_CHANGE_FRAMES)
    assert 1 <= t.switch_frames < bench_rebuild.MAX_CHANGE_FRAMES
    assert all(
        math.isfinite(v)
        for v in (t.frame_ms, t.extra_worst_ms, t.extra_p90_ms, t.noise_worst_ms, t.noise_p90_ms)
    )
    assert t.frame_ms > 0 and t.build_ms > 0 and t.extra_worst_ms >= t.extra_p90_ms
    me = threading.get_ident()
    # on this thread: the build timed alone (3 mounts) and the camera's first frame; the three
    # changes on the worker
    assert threads.count(me) == 4 and len(threads) - threads.count(me) == 3


def test_the_report_names_the_goal_and_every_figure() -> None:
    t = RebuildTiming("640x480", 5, 1.3, 0.7, 0.5, 0.6, 0.3, 80.0, 4.0, 30.0)
    text = format_rebuild([t])
    assert "no frame > 2 ms late" in text
    assert "640x480: 5 changes" in text and "extra worst 0.70 ms, p90 0.50 ms" in text
    assert "without a change: worst 0.60, p90 0.30 ms" in text
    assert "build 80 ms" in text and "served after 4 frames" in text
