"""``depthnav bench``'s large mount change: the real frame path serves every new mount from the
worker's build, and the report has its figures (reported, never asserted: no timing checks)."""

from __future__ import annotations

import contextlib
import dataclasses
import math
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

from depthnav_daemon.commands.bench import rebuild as bench_rebuild
from depthnav_daemon.commands.bench.rebuild import RebuildTiming, format_rebuild, rebuild_timing
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
    # paced: back to back, 600 frames of 160x120 last ~0.15 s, and on a loaded machine the
    # worker's build could take longer than that (the change would count as never served)
    t = rebuild_timing("160x120", SMALL, changes=3, pace_hz=100.0, n_frames=3)
    assert isinstance(t, RebuildTiming) and t.changes == 3 and t.resolution == "160x120"
    # every change served within the bench's bound (it would report MAX_CHANGE_FRAMES)
    assert 1 <= t.switch_frames < bench_rebuild.MAX_CHANGE_FRAMES
    assert all(
        math.isfinite(v)
        for v in (t.frame_ms, t.extra_worst_ms, t.extra_p90_ms, t.noise_worst_ms, t.noise_p90_ms)
    )
    assert t.frame_ms > 0 and t.build_ms > 0 and t.extra_worst_ms >= t.extra_p90_ms
    # every frame of a change and before it is timed once; preemptions are counted on Linux
    assert t.noise_frames == 3 * 3 * 3 and t.frames >= 3 * bench_rebuild.AFTER_SWITCH
    if sys.platform == "linux":
        assert 0 <= t.preempted <= t.frames and 0 <= t.noise_preempted <= t.noise_frames
        running = t.extra_running_worst_ms
        assert (running is None) == (t.preempted == t.frames)
        assert running is None or running <= t.extra_worst_ms
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


def _stat(pid: int) -> list[str] | None:
    """The fields of /proc/PID/stat after the command name (None: no such process)."""
    try:
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    except (OSError, IndexError):
        return None


def _alive(pid: int) -> bool:
    fields = _stat(pid)
    return fields is not None and fields[0] != "Z"


def _children_of(parent: int) -> set[int]:
    """The processes whose parent is ``parent`` and that are not zombies (Linux)."""
    out = set()
    for entry in Path("/proc").iterdir():
        if entry.name.isdigit():
            fields = _stat(int(entry.name))
            if fields is not None and int(fields[1]) == parent and fields[0] != "Z":
                out.add(int(entry.name))
    return out


def _running_children() -> set[int]:
    return _children_of(os.getpid())


@pytest.mark.skipif(sys.platform != "linux", reason="reads /proc")
def test_the_busy_processes_spin_while_the_block_runs_and_end_with_it() -> None:
    before = _running_children()
    started: set[int] = set()
    with pytest.raises(RuntimeError), bench_rebuild.busy_processes(2):
        started = _running_children() - before
        raise RuntimeError("the timed block failed")  # the processes end all the same
    assert len(started) == 2
    assert not started & _running_children()


_KILLED_PARENT = """
import sys, time
from depthnav_daemon.commands.bench.rebuild import busy_processes
with busy_processes(2):
    print("spinning", flush=True)
    time.sleep(120)
"""


@pytest.mark.skipif(sys.platform != "linux", reason="reads /proc")
def test_the_busy_processes_end_when_the_bench_is_killed() -> None:
    parent = subprocess.Popen(
        [sys.executable, "-c", _KILLED_PARENT], stdout=subprocess.PIPE, text=True
    )
    try:
        assert parent.stdout is not None and parent.stdout.readline() == "spinning\n"
        spinners = _children_of(parent.pid)
        assert len(spinners) == 2
    finally:
        parent.kill()  # no finally block runs in it
        parent.wait()
    deadline = time.monotonic() + 30.0  # each spinner looks at its parent every ~10 ms
    try:
        while spinners and time.monotonic() < deadline:
            spinners = {pid for pid in spinners if _alive(pid)}
            time.sleep(0.05)
        assert not spinners
    finally:  # never leave a spinner behind, even when the test fails
        for pid in spinners:
            with contextlib.suppress(OSError):
                os.kill(pid, signal.SIGKILL)


def test_the_report_says_how_many_frames_were_preempted_and_the_load() -> None:
    t = RebuildTiming(
        "640x480", 5, 1.3, 5.7, 0.5, 0.6, 0.3, 80.0, 4.0, 30.0,
        load=2, frames=36, preempted=2, extra_running_worst_ms=0.41, noise_frames=90,
        noise_preempted=0,
    )  # fmt: skip
    text = format_rebuild([t])
    assert "640x480 with 2 busy processes beside: 5 changes" in text
    assert "preempted: 2 of 36 frames during the changes (0 of 90 before them)" in text
    assert "worst extra of the frames not preempted 0.41 ms" in text
    every = dataclasses.replace(t, preempted=36, extra_running_worst_ms=None)
    assert "frames not preempted none" in format_rebuild([every])
    unknown = dataclasses.replace(t, preempted=-1, noise_preempted=-1)
    assert "preempted" not in format_rebuild([unknown])


@pytest.mark.parametrize(("cores", "load"), [(2, 2), (None, 1), (64, bench_rebuild.MAX_LOAD)])
def test_the_loaded_run_has_a_busy_process_per_core_up_to_a_bound(
    monkeypatch: pytest.MonkeyPatch, cores: int | None, load: int
) -> None:
    runs: list[tuple[str, int]] = []

    def timing(name: str, intr: Intrinsics, *args: object, load: int = 0) -> str:
        runs.append((name, load))  # what would be timed, not the timing (seconds each)
        return name

    monkeypatch.setattr(bench_rebuild, "rebuild_timing", timing)
    monkeypatch.setattr(bench_rebuild.os, "cpu_count", lambda: cores)
    bench_rebuild.rebuild_timings(changes=1)
    assert runs == [("640x480", 0), ("1280x720", 0), (bench_rebuild.LOADED, load)]
    runs.clear()
    bench_rebuild.rebuild_timings(changes=1, loaded=False)
    assert [n for _, n in runs] == [0, 0]
