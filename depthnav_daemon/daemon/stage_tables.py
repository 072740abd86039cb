"""Which mount the stages use for a frame, so that a mount change never stalls the frame loop.

The scan and cliff stages precompute tables per camera and mount (tens of ms at 640x480, a few
hundred at 1280x720 on a loaded 2-core machine: exact bearings for every pixel). When the mount
tracker moves the mount (the smoothed floor estimate drifting, the first floor estimate after
the configured mount, a confirmed jump, a new tilt source), the tables for the new mount are
built on a worker thread while the frames go on with the nearest mount of the same camera whose
tables exist; the new mount is used from the first frame after they are ready (one to a few
frames later). Only a camera's first frame, with no tables at all to go on with, builds them on
the frame itself.

The table of the robot's body (``with_body``: the pixels that can see it, per camera and mount)
is built with the stages' tables, in the same job.

The floor pose stage's table for its prior window (``pose.prepare_pose``, 4-14 ms) is built the
same way: the job of a new mount also builds the window the pose stage will search around it,
and an estimate whose window has no table yet searches the window of the camera's last
estimate while the worker builds it. Only a camera's first estimate builds its window's table
on the frame.

The frame loop must not wait for the worker: one worker thread (started with the tables, at the
frame loop's own priority: see _serve) gets each build after the frame that decided it;
while it builds, the interpreter's switch interval is 0.1 ms, so the frame loop waits at most
about that long for the interpreter lock whenever the worker runs Python code between its
compiled kernels.
"""

from __future__ import annotations

import logging
import queue
import sys
import threading
import weakref
from collections.abc import Callable, Hashable
from dataclasses import dataclass
from typing import TypeVar, cast

from depthnav_daemon.pipeline.footprint import Footprint, body_table
from depthnav_daemon.pipeline.geometry import Mount
from drivers.base import Intrinsics

log = logging.getLogger(__name__)

# the stages keep the tables of their 16 latest mounts (functools.lru_cache); remembering fewer
# keeps "ready" true, and the memory of a long run with a drifting mount bounded
KEEP_READY = 8
# the interpreter's switch interval while a build runs (seconds; Python's default is 5 ms). A
# thread that wants the interpreter lock while another runs Python code waits this long before
# asking for it: the frame loop, reacquiring the lock after each compiled stage, waited up to
# 5 ms each time the worker was between two of its kernels (at 1280x720 a frame took 13 ms
# instead of 2.5 against a worker running Python code; 2.4-2.6 ms with 0.5 ms). A frame gives the
# lock up at every compiled stage, so it may wait once per stage: over 8 large changes at
# 1280x720 the 90th percentile of a frame's extra time was 0.9-1.5 ms with 0.5 ms, 0.6-0.8 ms with
# 0.1 ms (four runs each, interleaved); 0.05 ms gained nothing more
BUILD_SWITCH_S = 0.0001

Key = tuple[Intrinsics, Mount]
PriorKey = tuple[Intrinsics, Hashable]  # (camera, the pose stage's prior window)
P = TypeVar("P", bound=Hashable)  # the pose stage's prior window (PoseParams)
_Job = tuple[Key | None, PriorKey | None, threading.Event]  # what to build; set when built


@dataclass(frozen=True, slots=True)
class SmallChange:
    """A mount change at most this large is small (metres, degrees): the unit of the distance
    between mounts, and what the log calls a large change."""

    height_m: float = 0.01
    angle_deg: float = 0.5

    def holds(self, a: Mount, b: Mount) -> bool:
        """True if ``a`` and ``b`` differ by no more than this."""
        return (
            abs(a.height_m - b.height_m) <= self.height_m
            and abs(a.tilt_deg - b.tilt_deg) <= self.angle_deg
            and abs(a.roll_deg - b.roll_deg) <= self.angle_deg
        )

    def distance(self, a: Mount, b: Mount) -> float:
        """How far apart two mounts are, in units of this change."""
        return (
            abs(a.height_m - b.height_m) / self.height_m
            + abs(a.tilt_deg - b.tilt_deg) / self.angle_deg
            + abs(a.roll_deg - b.roll_deg) / self.angle_deg
        )


class _SwitchWhileBuilding:
    """Lowers the interpreter's switch interval to BUILD_SWITCH_S while any build of any
    StageTables runs (several sensors build at once), and restores it after the last."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._builds = 0
        self._saved = 0.0

    def enter(self) -> None:
        with self._lock:
            if self._builds == 0:
                self._saved = sys.getswitchinterval()
                sys.setswitchinterval(min(self._saved, BUILD_SWITCH_S))
            self._builds += 1

    def exit(self) -> None:
        with self._lock:
            self._builds -= 1
            if self._builds == 0:
                sys.setswitchinterval(self._saved)


_SWITCH = _SwitchWhileBuilding()


def _serve(tables: weakref.ref[StageTables], jobs: queue.SimpleQueue[_Job | None]) -> None:
    """The worker: builds the queued jobs until told to stop (None)."""
    # The worker keeps the frame loop's priority. A lower one looks kind to the frame loop but
    # inverts it through the interpreter lock: on a busy machine a niced worker is preempted while
    # it holds the lock (between two of its compiled kernels) and waits for its next turn, tens
    # of ms away, while the frame loop waits for the lock. With two busy processes beside it, the
    # worst extra time of a frame that was not preempted during large changes was up to 77 ms
    # with the worker at nice +10 (39-43 ms in every run at 1280x720; up to 7.6 ms at +3) and
    # 0.1-1.7 ms at the same priority in most runs (9 ms in two of about ten: a worker at the same
    # priority can still be preempted holding the lock, for one turn of a busy process), and a
    # new mount served after 22-62 frames instead of 5-10 (docs/benchmarks.md, 2026-12-02).
    while (job := jobs.get()) is not None:
        key, pkey, done = job
        owner = tables()
        try:
            if owner is not None:
                owner._build(key, pkey)
        finally:
            _SWITCH.exit()  # entered by the frame loop when it queued the job
            done.set()
        if owner is None:
            return
        del owner


def with_body(
    prepare: Callable[[Intrinsics, Mount], None], body: Footprint | None
) -> Callable[[Intrinsics, Mount], None]:
    """``prepare``, then the table of the robot's body (``pipeline.footprint.body_table``, 3-4
    ms at 640x480, compiled and releasing the interpreter) for the same camera and mount, so
    that a new mount's first frame finds it built too; ``prepare`` itself when the robot has no
    footprint."""
    if body is None:
        return prepare

    def both(intr: Intrinsics, mount: Mount) -> None:
        prepare(intr, mount)
        body_table(intr, mount, body)

    return both


def _same_placement(a: Mount, b: Mount) -> bool:
    return a.x_m == b.x_m and a.y_m == b.y_m and a.yaw_deg == b.yaw_deg


class StageTables:
    """Picks the mount for each frame and builds the tables of new mounts off the frame loop.

    Args:
        prepare: builds (and caches) the stages' tables for (intrinsics, mount); may raise.
        small: the unit of mount distance (and what counts as a large change in the log).
        prepare_prior: builds (and caches) the pose stage's table for (intrinsics, prior
            window); may raise. None: :meth:`prior_for` gives the wanted window.
        defer_start: a build decided on a frame starts when the frame loop calls
            :meth:`start_queued` after the frame's stages (woken mid-frame, the worker made
            that frame 4-5 ms slower in ``depthnav bench`` on a loaded machine).
    """

    def __init__(
        self,
        prepare: Callable[[Intrinsics, Mount], None],
        small: SmallChange | None = None,
        prepare_prior: Callable[[Intrinsics, Hashable], None] | None = None,
        defer_start: bool = False,
    ) -> None:
        self._prepare = prepare
        self._defer_start = defer_start
        self._queued: _Job | None = None  # decided, not yet handed to the worker
        self._prepare_prior = prepare_prior
        self._small = small or SmallChange()
        self._ready: list[Key] = []  # latest last
        self._priors: list[PriorKey] = []  # prior windows whose tables exist, latest last
        # the running build: the mount (or None) and the prior (or None) it builds, and its end
        self._job: tuple[Key | None, PriorKey | None, threading.Event] | None = None
        # one worker thread, started here: Thread.start() waits until the new thread runs,
        # which on a loaded machine took milliseconds of the frame that started a build
        self._jobs: queue.SimpleQueue[_Job | None]
        self._worker: threading.Thread | None = None
        self._failed: set[Key] = set()  # a worker's build raised
        self._failed_priors: set[PriorKey] = set()
        self._said = False  # the log has told once how a large change is applied
        self._lock = threading.Lock()
        self._run_worker()

    def mount_for(
        self, intr: Intrinsics, wanted: Mount, prior: Callable[[], Hashable | None] | None = None
    ) -> Mount:
        """The mount to process a frame of camera ``intr`` with, given the tracker's ``wanted``:
        ``wanted`` if its tables exist (or nothing else can serve), else the nearest mount of
        this camera and placement whose tables exist, while ``wanted``'s are built.

        ``prior``: gives the pose stage's prior window around ``wanted`` (called on this thread
        when a build starts; None: no pose stage); the build makes its table too, so the next
        estimate finds it ready.
        """
        ready = self._ready
        if self._job is None and ready and ready[-1][0] is intr and ready[-1][1] is wanted:
            return wanted  # the last frame's mount, nothing being built: the common case
        self._collect()
        key = (intr, wanted)
        if key in ready or key in self._failed:  # failed: the frame loop meets the error
            self._mark_ready(key)
            return wanted
        usable = [k for k in self._ready if k[0] == intr and _same_placement(k[1], wanted)]
        if not usable:  # a camera's first frame: the stages build its tables on this frame
            self._mark_ready(key)
            return wanted
        # the latest of equally near mounts (min keeps the first: search latest first)
        nearest = min(reversed(usable), key=lambda k: self._small.distance(k[1], wanted))
        if self._job is None:
            window = prior() if prior is not None and self._prepare_prior is not None else None
            pkey = None if window is None or (intr, window) in self._priors else (intr, window)
            self._start(key, pkey)
        if not self._small.holds(nearest[1], wanted) and not self._said:
            self._said = True
            log.info(
                "mount change to %s: its tables are built on a worker while frames go on with "
                "%s (a few frames); later changes are applied the same way",
                _short(wanted),
                _short(nearest[1]),
            )
        self._mark_ready(nearest)
        return nearest[1]

    def prior_for(self, intr: Intrinsics, wanted: P) -> P:
        """The prior window the pose stage searches on this frame of camera ``intr``, given the
        one it wants: ``wanted`` if its table exists (or a build of it failed: the estimate
        meets the error) or this camera has none yet (its first estimate builds it on the
        frame); else the window this camera searched last, while ``wanted``'s table is built on
        the worker."""
        if self._prepare_prior is None:
            return wanted
        self._collect()
        key = (intr, wanted)
        if key in self._priors or key in self._failed_priors:
            self._mark_prior(key)
            return wanted
        mine = [k for k in self._priors if k[0] == intr]
        if not mine:
            self._mark_prior(key)
            return wanted
        if self._job is None:
            self._start(None, key)
        return cast(P, mine[-1][1])  # the windows of one FrameStep are of one type

    def close(self, timeout_s: float = 5.0) -> None:
        """Wait for a running build and stop the worker (a later build starts it again)."""
        self.start_queued()
        if self._job is not None:
            self._job[2].wait(timeout_s)
        if self._worker is not None:
            self._jobs.put(None)
            self._worker.join(timeout_s)
            self._worker = None

    def _run_worker(self) -> None:
        jobs: queue.SimpleQueue[_Job | None] = queue.SimpleQueue()
        self._jobs = jobs
        # the worker holds only a weak reference: tables nobody closed stop it when collected
        self._worker = threading.Thread(
            target=_serve, args=(weakref.ref(self), jobs), name="depthnav-tables", daemon=True
        )
        weakref.finalize(self, jobs.put, None)
        self._worker.start()

    def _build(self, key: Key | None, pkey: PriorKey | None) -> None:
        if key is not None:
            try:
                self._prepare(*key)
            except Exception as exc:
                log.debug("building the tables for %s failed: %s", key[1], exc)
                with self._lock:
                    self._failed.add(key)
        if pkey is not None and self._prepare_prior is not None:
            try:
                self._prepare_prior(*pkey)
            except Exception as exc:
                log.debug("building the pose table for %s failed: %s", pkey[1], exc)
                with self._lock:
                    self._failed_priors.add(pkey)

    def start_queued(self) -> None:
        """Hand the build decided on this frame to the worker (with ``defer_start``: the frame
        loop calls this once the frame's stages are done)."""
        if self._queued is None:
            return
        job, self._queued = self._queued, None
        if self._worker is None:  # stopped by close()
            self._run_worker()
        # from now on: the worker's first steps are Python code too
        _SWITCH.enter()
        self._jobs.put(job)

    def _start(self, key: Key | None, pkey: PriorKey | None) -> None:
        done = threading.Event()
        self._job = (key, pkey, done)
        self._queued = self._job
        if not self._defer_start:
            self.start_queued()

    def _collect(self) -> None:
        """Note a finished build."""
        if self._job is None or not self._job[2].is_set():
            return
        key, pkey, _ = self._job
        self._job = None
        with self._lock:
            if key is not None and key not in self._failed:
                self._mark_ready(key)
            if pkey is not None and pkey not in self._failed_priors:
                self._mark_prior(pkey)

    def _mark_ready(self, key: Key) -> None:
        if key in self._ready:
            self._ready.remove(key)
        self._ready.append(key)
        del self._ready[:-KEEP_READY]

    def _mark_prior(self, key: PriorKey) -> None:
        if key in self._priors:
            self._priors.remove(key)
        self._priors.append(key)
        del self._priors[:-KEEP_READY]


def _short(m: Mount) -> str:
    return f"{m.height_m:.3f} m, tilt {m.tilt_deg:.2f} deg, roll {m.roll_deg:.2f} deg"
