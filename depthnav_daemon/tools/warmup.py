"""Compile and cache every numeric kernel now: ``depthnav warmup`` (commands/warmup.py) runs it,
and so does the daemon in a child process when its cache is cold (daemon/kernel_cache.py).

Afterwards ``depthnav run`` compiles nothing: numba keeps the machine code on disk (see
pipeline/_jit.py), keyed to this CPU. numba compiles one version per argument type, and a read-only
array, a writable one and a strided view are different types, so every kernel is run here with each
kind of array the stages can hand it; then the daemon's own loop runs on a rendered scene with
what only it reaches: a mount placed on the robot (placement), the robot's body (footprint), the
obstacle memory with its expiry, a lens with distortion and several sensors merged.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable
from typing import Any

import numpy as np

from depthnav_daemon.pipeline import StageParams, process
from depthnav_daemon.pipeline.cliff import CliffParams, detect_cliffs
from depthnav_daemon.pipeline.geometry import Mount
from depthnav_daemon.pipeline.lens import undistort
from depthnav_daemon.pipeline.pose import PoseParams, estimate_pose
from depthnav_daemon.pipeline.scan import ScanParams, depth_to_scan, scan_layout
from depthnav_daemon.sim.synthetic import Box, Scene, render, step_down
from drivers.base import DeviceInfo, Frame, Intrinsics

# every scan / cliff configuration that gives its kernel a differently typed array:
# contiguous frame vs column-strided view (col_step > 1) vs gathered samples (uneven columns)
SCAN_VARIANTS = (ScanParams(), ScanParams(col_step=2), ScanParams(method="paper", scan_height=100))
CLIFF_VARIANTS = (
    CliffParams(used_depth_height=100),  # step 8: view
    CliffParams(
        used_depth_height=100, block_size=8, row_step=1, col_step=1, block_points_thresh=10
    ),
    CliffParams(used_depth_height=100, block_size=8, row_step=2, col_step=3, block_points_thresh=4),
)
SCENE = Scene(boxes=(Box(1.5, 0.0, 0.3, 0.3, 0.3),), holes=(step_down(2.0, 0.2),))
# the daemon's runs (a 640x480 camera: the defaults' row bands fit it); a mount placed on the
# robot, so the outputs go through the base frame, and memory expiry on
PLACED = {"height_m": 0.5, "tilt_deg": 15.0, "x_m": 0.2, "y_m": 0.1, "yaw_deg": 10.0}
# a robot body the placed sensor sees (the floor in front of it, under the polygon), so that
# its table and per-frame kernels run (pipeline/footprint.py)
ROBOT = {"footprint_m": [[0.9, 0.3], [-0.3, 0.3], [-0.3, -0.3], [0.9, -0.3]], "height_m": 0.3}
DAEMON_RUNS: tuple[dict[str, Any], ...] = (
    {"mount": PLACED, "memory": {"max_age_s": 5.0}, "robot": ROBOT},
    {"mount": PLACED, "scan": {"method": "paper"}},
    {
        "sensor": [
            {"name": "left", "device": "warmup:", "mount": PLACED},
            {"name": "right", "device": "warmup:", "mount": {**PLACED, "y_m": -0.1}},
        ],
        "robot": ROBOT,
    },
)
DAEMON_FRAMES = 4


def warm_up() -> float:
    """Run every stage kernel on small frames, read-only (as the daemon's) and writable, then the
    daemon's loop on a rendered scene (``DAEMON_RUNS``).

    Returns:
        Seconds it took (a few with a warm cache, tens to hundreds without).
    """
    t0 = time.perf_counter()
    intr = Intrinsics(160, 120, 145.0, 145.0, 79.5, 59.5)
    mount = Mount(0.5, 15.0, 0.0)
    view = render(SCENE, intr, mount)
    frame = Frame(0, 0.0, view.depth_mm.copy(), intr)  # Frame makes its depth read-only
    writable = view.depth_mm.copy()
    rng = np.random.default_rng(0)
    pose = PoseParams(used_depth_height=100)
    for depth in (frame.depth_mm, writable):
        for scan in SCAN_VARIANTS:
            depth_to_scan(depth, intr, mount, scan)
        layout = scan_layout(intr, mount, ScanParams())
        for cliff in CLIFF_VARIANTS:
            detect_cliffs(depth, intr, mount, cliff, *layout)
        estimate_pose(depth, intr, pose, rng)
    # the lens model's inverse (tables of a camera with distortion coefficients)
    undistort(np.zeros(4), np.zeros(4), Intrinsics(160, 120, 145.0, 145.0, 79.5, 59.5, -0.1))
    # and the whole per-frame path once, as the daemon calls it
    estimate_pose(frame.depth_mm, intr, pose, rng)
    process(frame, mount, StageParams(scan=ScanParams(), cliff=CliffParams(used_depth_height=100)))
    warm_daemon_paths()
    return time.perf_counter() - t0


class SceneDriver:
    """A device that delivers a few rendered frames as a camera does (read-only depth), with the
    robot's odometry in each (so the memory is on), then ends."""

    INTRINSICS = Intrinsics(640, 480, 570.0, 570.0, 319.5, 239.5, k1=-0.05)
    _depth: np.ndarray | None = None

    def __init__(self, spec: str) -> None:
        self.spec = spec
        self._seq = 0

    @classmethod
    def depth(cls) -> np.ndarray:
        if cls._depth is None:
            cls._depth = render(SCENE, cls.INTRINSICS, Mount(0.5, 15.0, 0.0)).depth_mm
        return cls._depth

    def open(self) -> DeviceInfo:
        return DeviceInfo("warm-up scene", None, self.spec, self.INTRINSICS)

    def read_frame(self, timeout_s: float = 1.0) -> Frame | None:
        if self._seq >= DAEMON_FRAMES:
            return None
        s, self._seq = self._seq, self._seq + 1
        return Frame(s, s / 30.0, self.depth().copy(), self.INTRINSICS, odom=(0.02 * s, 0.0, 0.0))

    def close(self) -> None:
        pass


def warm_daemon_paths() -> None:
    """The daemon's frame loop (daemon/loop.py, daemon/multi.py) over ``DAEMON_RUNS``, on
    ``SceneDriver`` frames, into the null sink."""
    from depthnav_daemon.config.loader import build_config
    from depthnav_daemon.daemon.loop import run
    from depthnav_daemon.daemon.notify import ServiceNotifier

    quiet = logging.getLogger("depthnav_daemon.daemon")  # its mount and end-of-run lines
    level = quiet.level
    quiet.setLevel(logging.WARNING)
    try:
        for extra in DAEMON_RUNS:
            device = {} if "sensor" in extra else {"device": "warmup:"}
            cfg = build_config([], [], {"sinks": ["null"], **device, **extra})
            # never systemd's: a warm-up is no service start, even inside one
            run(cfg, threading.Event(), driver_factory=SceneDriver, notifier=ServiceNotifier({}))
    finally:
        quiet.setLevel(level)


def watch_compiles(progress: Callable[[int, int], None]) -> None:
    """Report numba compiling one of depthnav's kernels: ``progress(done, total)`` per kernel.

    A warm cache loads every kernel from disk and reports nothing; a cold one (a fresh install,
    another CPU, a new depthnav) compiles them, tens of seconds in all, and the caller says so
    instead of looking hung. Uses numba's event API; call it once per process.
    """
    from numba.core import event

    from depthnav_daemon.pipeline._jit import KERNELS

    done: set[int] = set()
    started = [False]

    def ours(ev: event.Event) -> bool:
        disp = ev.data.get("dispatcher") if isinstance(ev.data, dict) else None
        # KERNELS as it is now: a kernel module imported later counts too
        return disp is not None and any(k is disp for k in KERNELS)

    class _Listener(event.Listener):
        def on_start(self, ev: event.Event) -> None:
            if not started[0] and ours(ev):
                started[0] = True
                progress(0, len(KERNELS))  # the first compile: say it before the wait

        def on_end(self, ev: event.Event) -> None:
            disp = ev.data.get("dispatcher") if isinstance(ev.data, dict) else None
            if ours(ev) and id(disp) not in done:
                done.add(id(disp))
                progress(len(done), len(KERNELS))

    event.register("numba:compile", _Listener())


def main() -> None:
    """``python -m depthnav_daemon.tools.warmup``: the kernels into this user's cache (the older
    spelling of ``depthnav warmup``)."""
    from depthnav_daemon.daemon.kernel_cache import mark_warm

    def show(done: int, total: int) -> None:
        if done:  # each kernel takes seconds: show the install moves
            print(f"depthnav: compiling kernels {done}/{total}", flush=True)  # noqa: T201

    watch_compiles(show)
    seconds = warm_up()
    mark_warm()
    print(f"depthnav kernels ready in {seconds:.1f} s")  # noqa: T201


if __name__ == "__main__":
    main()
