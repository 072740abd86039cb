"""Compile and cache every numeric kernel now (``python -m depthnav_daemon.tools.warmup``).

scripts/install.sh runs it, so ``depthnav run`` compiles nothing at its first frame: numba keeps
the machine code on disk (see pipeline/_jit.py), keyed to this CPU. numba compiles one version per
argument type, and a read-only array, a writable one and a strided view are different types, so
every kernel is run here with each kind of array the stages can hand it.
"""

from __future__ import annotations

import time
from collections.abc import Callable

import numpy as np

from depthnav_daemon.pipeline import StageParams, process
from depthnav_daemon.pipeline.cliff import CliffParams, detect_cliffs
from depthnav_daemon.pipeline.geometry import Mount
from depthnav_daemon.pipeline.lens import undistort
from depthnav_daemon.pipeline.pose import PoseParams, estimate_pose
from depthnav_daemon.pipeline.scan import ScanParams, depth_to_scan, scan_layout
from depthnav_daemon.sim.synthetic import Box, Scene, render, step_down
from drivers.base import Frame, Intrinsics

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


def warm_up() -> float:
    """Run every stage kernel on small frames, read-only (as the daemon's) and writable.

    Returns:
        Seconds it took (well under a second with a warm cache, tens of seconds without).
    """
    t0 = time.perf_counter()
    intr = Intrinsics(160, 120, 145.0, 145.0, 79.5, 59.5)
    mount = Mount(0.5, 15.0, 0.0)
    view = render(
        Scene(boxes=(Box(1.5, 0.0, 0.3, 0.3, 0.3),), holes=(step_down(2.0, 0.2),)), intr, mount
    )
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
    return time.perf_counter() - t0


def watch_compiles(progress: Callable[[int, int], None]) -> None:
    """Report numba compiling one of depthnav's kernels: ``progress(done, total)`` per kernel.

    A warm cache loads every kernel from disk and reports nothing; a cold one (a fresh install,
    another CPU, a new depthnav) compiles them at the first frame, tens of seconds in all, and the
    caller says so instead of looking hung. Uses numba's event API; call it once per process.
    """
    from numba.core import event

    from depthnav_daemon.pipeline._jit import KERNELS

    ours = {id(k) for k in KERNELS}
    done: set[int] = set()

    class _Listener(event.Listener):
        def on_start(self, ev: event.Event) -> None:
            disp = ev.data.get("dispatcher") if isinstance(ev.data, dict) else None
            if disp is not None and id(disp) in ours and not done:
                progress(0, len(ours))  # the first compile: say it before the wait

        def on_end(self, ev: event.Event) -> None:
            disp = ev.data.get("dispatcher") if isinstance(ev.data, dict) else None
            if disp is not None and id(disp) in ours and id(disp) not in done:
                done.add(id(disp))
                progress(len(done), len(ours))

    event.register("numba:compile", _Listener())


def main() -> None:
    def show(done: int, total: int) -> None:
        if done:  # each kernel takes seconds: show the install moves
            print(f"depthnav: compiling kernels {done}/{total}", flush=True)  # noqa: T201

    watch_compiles(show)
    print(f"depthnav kernels ready in {warm_up():.1f} s")  # noqa: T201


if __name__ == "__main__":
    main()
