"""What a large mount change costs the frames of ``depthnav run`` (issue 16's goal: no frame later
than 2 ms because of a rebuild).

The real frame path (``StageTables`` picks the mount, ``pipeline.process`` runs the stages, as
``daemon.frame_step`` does) runs over synthetic corridor frames, paced at the sensor's rate, while
large mount changes (10 cm, 10 deg of tilt, 5 deg of roll, never seen before) are built on the
worker. Each change is timed in three passes over the same frames: on the mount in use (before),
while the new mount's tables are built and until they serve, and on the new mount (after). A
frame's extra time is its time during the change minus the median time of the same frame on the
mount it was processed with, outside a change. Reported, never asserted: the figures depend on
the machine and its load.

A preempted frame (an involuntary context switch of the frame thread, Linux: another process, or
the worker when every core is taken, ran in its place) is late by the machine's doing as much as
the change's: such frames are counted, and the worst extra time of the frames that were not is
reported beside the worst of all. A frame waiting for the interpreter lock held by the worker is
not preempted: those waits stay in that figure. The 640x480 case also runs with one busy process
per core beside it (``load``): a robot's computer is busy, and a table worker at a lower priority
than the frame loop, preempted while it held the lock, made frames wait for it tens of ms only
then (stage_tables._serve).
"""

from __future__ import annotations

import contextlib
import dataclasses
import logging
import os
import statistics
import subprocess
import sys
import time
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass

import numpy as np

try:
    import resource
except ImportError:  # not on Windows
    resource = None  # type: ignore[assignment]

from depthnav_daemon.daemon.frame_step import pose_prior
from depthnav_daemon.daemon.mount_tracker import MountTracker, TrackerParams
from depthnav_daemon.daemon.stage_tables import StageTables
from depthnav_daemon.pipeline import StageParams, prepare, process
from depthnav_daemon.pipeline.cliff import CliffParams
from depthnav_daemon.pipeline.geometry import Mount
from depthnav_daemon.pipeline.pose import PoseParams, prepare_pose
from depthnav_daemon.pipeline.scan import ScanParams
from drivers.base import Frame, Intrinsics

REBUILD_RESOLUTIONS: dict[str, Intrinsics] = {
    "640x480": Intrinsics(640, 480, 570.3, 570.3, 319.5, 239.5),
    "1280x720": Intrinsics(1280, 720, 640.0, 640.0, 639.5, 359.5),
}
START_MOUNT = Mount(0.55, 15.0, 0.0)
# a pose window that leaves the bench's mounts outside it, so that every change also moves the
# window the pose stage searches (``frame_step.pose_prior``): its table is part of the build
POSE = PoseParams(height_min_m=0.1, height_max_m=0.3)
MAX_CHANGE_FRAMES = 600  # a build that has not served by then is reported as such
AFTER_SWITCH = 3  # frames timed on the new mount right after it serves (first use of its tables)


@dataclass(frozen=True, slots=True)
class RebuildTiming:
    """Large mount changes at one resolution, milliseconds.

    Attributes:
        resolution: image size.
        changes: mount changes timed.
        frame_ms: median per-frame time of the frame path outside a change.
        extra_worst_ms: the worst extra time of a frame during a change (see the module
            docstring), over all changes.
        extra_p90_ms: the 90th percentile of those extra times.
        noise_worst_ms, noise_p90_ms: the same for the frames before each change, against
            their own medians: what the machine's load alone does (a figure above it is the
            change's).
        build_ms: median time to build a new mount's tables (scan, cliff, memory view, pose
            window) on one thread, with no frames running.
        switch_frames: median frames from a change until the new mount served a frame.
        pace_hz: the frame rate the frames were paced at (0: back to back).
        load: busy processes running beside the frames (0: none).
        frames: frames timed during the changes.
        preempted: of those, frames preempted (-1: not known on this system).
        extra_running_worst_ms: the worst extra time of the frames not preempted (None: none,
            or not known).
        noise_frames, noise_preempted: the same counts for the frames before the changes.
    """

    resolution: str
    changes: int
    frame_ms: float
    extra_worst_ms: float
    extra_p90_ms: float
    noise_worst_ms: float
    noise_p90_ms: float
    build_ms: float
    switch_frames: float
    pace_hz: float
    load: int = 0
    frames: int = 0
    preempted: int = -1
    extra_running_worst_ms: float | None = None
    noise_frames: int = 0
    noise_preempted: int = -1


class _FramePath:
    """One frame as ``FrameStep.run`` processes it once the mount is decided (no pose estimate:
    it does not depend on the change), with the tables' worker of the daemon."""

    def __init__(self, params: StageParams) -> None:
        self.params = params
        self.tables = StageTables(
            lambda i, m: prepare(i, m, params), prepare_prior=prepare_pose, defer_start=True
        )

    def run(self, frame: Frame, wanted: Mount) -> Mount:
        """Process ``frame`` for mount ``wanted``; returns the mount that served it."""

        def window() -> PoseParams:
            return pose_prior(POSE, MountTracker(wanted, TrackerParams()))

        used = self.tables.mount_for(frame.intrinsics, wanted, window)
        process(frame, used, self.params, clock=time.perf_counter)
        self.tables.start_queued()
        return used


_THREAD = getattr(resource, "RUSAGE_THREAD", None) if resource is not None else None  # Linux


def _switches() -> int | None:
    """Involuntary context switches of this thread so far (None where RUSAGE_THREAD is
    missing)."""
    return None if _THREAD is None else resource.getrusage(_THREAD).ru_nivcsw


@dataclass
class _Run:
    """What :func:`_paced` saw: per-frame seconds, the mount each used, and whether the frame
    was preempted (None: not known)."""

    times: list[float] = dataclasses.field(default_factory=list)
    used: list[Mount] = dataclasses.field(default_factory=list)
    preempted: list[bool | None] = dataclasses.field(default_factory=list)


def _paced(
    frames: Sequence[Frame],
    n: int,
    pace_s: float,
    step: Callable[[Frame], Mount],
    until: Callable[[list[Mount]], bool] | None = None,
) -> _Run:
    """Run ``step`` on up to ``n`` frames (cycling from the first), one every ``pace_s``
    seconds, stopping early once ``until(mounts used so far)``."""
    out = _Run()
    due = time.perf_counter()
    for i in range(n):
        now = time.perf_counter()
        if due > now:
            time.sleep(due - now)
        s0 = _switches()
        t0 = time.perf_counter()
        out.used.append(step(frames[i % len(frames)]))
        out.times.append(time.perf_counter() - t0)
        s1 = _switches()
        out.preempted.append(None if s0 is None or s1 is None else s1 > s0)
        due = max(due + pace_s, t0)
        if until is not None and until(out.used):
            break
    return out


def _per_frame_median(times: Sequence[float], n_frames: int) -> list[float]:
    return [statistics.median(times[j::n_frames]) for j in range(n_frames)]


def _changed(m: Mount, k: int) -> Mount:
    """A large change from ``m``, never built before (``k`` counts the changes): 10 cm up (so
    the pose window moves too), 10 deg of tilt and 5 of roll back and forth."""
    sign = 1.0 if k % 2 == 0 else -1.0
    return Mount(m.height_m + 0.1, m.tilt_deg - sign * 10.0, m.roll_deg - sign * 5.0)


def build_time_ms(intr: Intrinsics, params: StageParams, mount: Mount, runs: int = 3) -> float:
    """Median milliseconds to build every table of a mount never seen before on this thread."""
    out = []
    for k in range(runs):
        new = dataclasses.replace(mount, height_m=mount.height_m + 1e-5 * (k + 1))
        t0 = time.perf_counter()
        prepare(intr, new, params)
        prepare_pose(intr, pose_prior(POSE, MountTracker(new, TrackerParams())))
        out.append(time.perf_counter() - t0)
    return statistics.median(out) * 1e3


# a busy process spins in laps of ~10 ms and ends once its parent (given as its argument: one
# killed before the child read its own parent would leave it spinning) is gone, so a bench killed
# with SIGKILL leaves nothing spinning for ever
_SPIN = """
import os, sys
parent = int(sys.argv[1])
while os.getppid() == parent:
    for _ in range(200000):
        pass
"""


@contextlib.contextmanager
def busy_processes(n: int) -> Iterator[None]:
    """``n`` processes that spin on the CPU until the block ends (a busy robot computer)."""
    procs: list[subprocess.Popen[bytes]] = []
    try:
        for _ in range(n):
            procs.append(
                subprocess.Popen(
                    [sys.executable, "-c", _SPIN, str(os.getpid())],
                    stdin=subprocess.DEVNULL,
                    stdout=subprocess.DEVNULL,
                    stderr=subprocess.DEVNULL,
                )
            )
        yield
    finally:
        for proc in procs:
            proc.kill()
        for proc in procs:
            proc.wait()


def rebuild_timing(
    name: str,
    intr: Intrinsics,
    changes: int = 5,
    pace_hz: float = 30.0,
    n_frames: int = 6,
    load: int = 0,
) -> RebuildTiming:
    """Time ``changes`` large mount changes at the resolution of ``intr``, with ``load`` busy
    processes beside the frames from the first change on (module docstring)."""
    from depthnav_daemon.commands.bench.stages import synthetic_frames

    frames, mount = synthetic_frames(intr, n=n_frames, mount=START_MOUNT)
    params = StageParams(scan=ScanParams(), cliff=CliffParams())
    path = _FramePath(params)
    pace_s = 1.0 / pace_hz if pace_hz > 0 else 0.0
    build_ms = build_time_ms(intr, params, Mount(1.9, 35.0, 3.0))  # far from the changes
    path.run(frames[0], mount)  # a camera's first frame: builds its tables on the frame
    _paced(frames, 2 * n_frames, pace_s, lambda f: path.run(f, mount))  # warm-up
    extra: list[float] = []
    noise: list[float] = []
    base: list[float] = []
    hit: list[bool | None] = []  # preempted, for each frame of ``extra``
    hit_before: list[bool | None] = []
    switch: list[int] = []
    logger = logging.getLogger("depthnav_daemon")
    level = logger.level
    logger.setLevel(logging.WARNING)  # the tables' info line on a change is not the bench's output
    try:
        with busy_processes(load):
            for k in range(changes):
                new = _changed(mount, k)
                before = _paced(frames, 3 * n_frames, pace_s, lambda f, m=mount: path.run(f, m))
                # until the new mount has served AFTER_SWITCH frames
                during = _paced(
                    frames,
                    MAX_CHANGE_FRAMES,
                    pace_s,
                    lambda f, m=new: path.run(f, m),
                    lambda u, m=new: u.count(m) >= AFTER_SWITCH,
                )
                used = during.used
                switch.append(used.index(new) + 1 if new in used else MAX_CHANGE_FRAMES)
                after = _paced(frames, 3 * n_frames, pace_s, lambda f, m=new: path.run(f, m))
                ref_old = _per_frame_median(before.times, n_frames)
                ref_new = _per_frame_median(after.times, n_frames)
                for i, (ti, ui) in enumerate(zip(during.times, used, strict=True)):
                    ref = ref_new if ui == new else ref_old
                    extra.append(ti - ref[i % n_frames])
                noise += [ti - ref_old[i % n_frames] for i, ti in enumerate(before.times)]
                hit += during.preempted
                hit_before += before.preempted
                base += before.times
                mount = new
    finally:
        path.tables.close()
        logger.setLevel(level)
    ex = np.array(extra) * 1e3
    quiet = np.array(noise) * 1e3
    known = all(h is not None for h in hit + hit_before)
    running = ex[[not h for h in hit]] if known else ex[:0]
    return RebuildTiming(
        resolution=name,
        changes=changes,
        frame_ms=statistics.median(base) * 1e3,
        extra_worst_ms=float(ex.max()),
        extra_p90_ms=float(np.percentile(ex, 90)),
        noise_worst_ms=float(quiet.max()),
        noise_p90_ms=float(np.percentile(quiet, 90)),
        build_ms=build_ms,
        switch_frames=float(statistics.median(switch)),
        pace_hz=pace_hz,
        load=load,
        frames=len(extra),
        preempted=sum(bool(h) for h in hit) if known else -1,
        extra_running_worst_ms=float(running.max()) if running.size else None,
        noise_frames=len(noise),
        noise_preempted=sum(bool(h) for h in hit_before) if known else -1,
    )


LOADED = "640x480"  # the resolution also timed with one busy process per core beside it
# at most this many busy processes (an interpreter each, ~10 MB): enough to keep a robot's
# computer busy, without starting dozens on a big machine
MAX_LOAD = 16


def rebuild_timings(
    changes: int = 5, pace_hz: float = 30.0, loaded: bool = True
) -> list[RebuildTiming]:
    """:func:`rebuild_timing` at every resolution of REBUILD_RESOLUTIONS, then (``loaded``) at
    LOADED with one busy process per core (at most MAX_LOAD) beside the frames."""
    out = [
        rebuild_timing(name, intr, changes, pace_hz) for name, intr in REBUILD_RESOLUTIONS.items()
    ]
    if loaded:
        load = min(os.cpu_count() or 1, MAX_LOAD)
        out.append(rebuild_timing(LOADED, REBUILD_RESOLUTIONS[LOADED], changes, pace_hz, load=load))
    return out


def format_rebuild(timings: Sequence[RebuildTiming]) -> str:
    """The text report's lines (the goal: no frame later than 2 ms because of a rebuild)."""
    out = [
        "large mount change, frames on while the worker builds (goal: no frame > 2 ms late); "
        "extra = a frame's time minus the same frame's without a change:"
    ]
    for t in timings:
        beside = (
            f" with {t.load} busy process{'es' if t.load != 1 else ''} beside" if t.load else ""
        )
        out.append(
            f"  {t.resolution}{beside}: {t.changes} change{'s' if t.changes != 1 else ''}, frames "
            f"{t.frame_ms:.2f} ms at "
            f"{t.pace_hz:g} frames/s; extra worst {t.extra_worst_ms:.2f} ms, p90 "
            f"{t.extra_p90_ms:.2f} ms (without a change: worst {t.noise_worst_ms:.2f}, p90 "
            f"{t.noise_p90_ms:.2f} ms); build {t.build_ms:.0f} ms (one thread, no frames), "
            f"new mount served after {t.switch_frames:g} frames"
        )
        if t.preempted >= 0:
            worst = t.extra_running_worst_ms
            others = "none" if worst is None else f"{worst:.2f} ms"
            out.append(
                f"    preempted: {t.preempted} of {t.frames} frames during the changes "
                f"({t.noise_preempted} of {t.noise_frames} before them); worst extra of the "
                f"frames not preempted {others}"
            )
    return "\n".join(out)
