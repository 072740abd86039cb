"""Compile and cache every numeric kernel now (``python -m depthnav_daemon.warmup``).

scripts/install.sh runs it, so ``depthnav run`` compiles nothing at its first frame: numba keeps
the machine code on disk (see pipeline/_jit.py), keyed to this CPU.
"""

from __future__ import annotations

import time

import numpy as np

from depthnav_daemon.pipeline import process
from depthnav_daemon.pipeline.cliff import CliffParams
from depthnav_daemon.pipeline.geometry import Mount
from depthnav_daemon.pipeline.pose import PoseParams
from depthnav_daemon.pipeline.scan import ScanParams
from depthnav_daemon.synthetic import Box, Scene, render, step_down
from drivers.base import Frame, Intrinsics


def warm_up() -> float:
    """Run the whole pipeline once per scan method on a small read-only frame, as the daemon does.

    Returns:
        Seconds it took (about a second with a warm cache, several without).
    """
    t0 = time.perf_counter()
    intr = Intrinsics(160, 120, 145.0, 145.0, 79.5, 59.5)
    mount = Mount(0.5, 15.0, 0.0)
    view = render(Scene(boxes=(Box(1.5, 0.0, 0.3, 0.3, 0.3),), holes=(step_down(2.0, 0.2),)), intr, mount)
    frame = Frame(0, 0.0, view.depth_mm, intr)
    rng = np.random.default_rng(0)
    for method in ("exact", "paper"):
        process(frame, mount, ScanParams(method=method, scan_height=100), CliffParams(used_depth_height=100),
                PoseParams(used_depth_height=100), rng)
    return time.perf_counter() - t0


def main() -> None:
    print(f"depthnav kernels ready in {warm_up():.1f} s")  # noqa: T201


if __name__ == "__main__":
    main()
