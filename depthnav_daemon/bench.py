"""Stage benchmarks: median time per frame of each stage, and its ratio to np.copy of the frame.

Timing follows ../shared/reference/performance.md §8: warm-up first, interleaved rounds, each round
times np.copy of the same frame and every stage, auto-batched samples, gc off while sampling.
"""

from __future__ import annotations

import gc
import math
import platform
import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from depthnav_daemon.pipeline.geometry import Mount
from depthnav_daemon.pipeline.scan import ScanParams, depth_to_scan
from depthnav_daemon.synthetic import Box, KinectNoise, Scene, render, step_down
from drivers.base import KINECT_V1, Intrinsics


@dataclass(frozen=True, slots=True)
class Timing:
    """Per-call statistics of one benchmarked function, seconds."""

    name: str
    median_s: float
    p90_s: float
    best_s: float
    ratio_to_copy: float


def bench_scene(intr: Intrinsics = KINECT_V1, mount: Mount | None = None, seed: int = 1) -> tuple[np.ndarray, Mount]:
    """A noisy corridor-like frame: boxes, a wall and a step down, as uint16 mm."""
    mount = mount or Mount(0.55, 15.0, 0.0)
    scene = Scene(
        boxes=(Box(1.5, 0.4, 0.3, 0.3, 0.3), Box(2.2, -0.5, 0.4, 0.4, 0.6, yaw_deg=20), Box(4.0, 0.0, 0.1, 6.0, 2.5)),
        holes=(step_down(3.0, 0.18),),
    )
    view = render(scene, intr, mount, KinectNoise(), np.random.default_rng(seed))
    return view.depth_mm, mount


def _sample(fn: Callable[[], object], min_batch_s: float = 0.002) -> float:
    """Seconds per call of ``fn``, batched so one sample lasts at least ``min_batch_s``."""
    n = 1
    while True:
        t0 = time.perf_counter()
        for _ in range(n):
            fn()
        dt = time.perf_counter() - t0
        if dt >= min_batch_s or n >= 1 << 16:
            return dt / n
        n *= 2 if dt <= 0 else max(2, math.ceil(min_batch_s / dt))


def time_functions(
    funcs: dict[str, Callable[[], object]], frame: np.ndarray, rounds: int = 7, samples: int = 5
) -> list[Timing]:
    """Interleaved rounds: np.copy(frame) then every function; medians over all samples."""
    for fn in funcs.values():
        fn()  # warm-up (caches, compiled kernels)
    copies: list[float] = []
    got: dict[str, list[float]] = {name: [] for name in funcs}
    gc_was = gc.isenabled()
    gc.disable()
    try:
        for _ in range(rounds):
            for _ in range(samples):
                copies.append(_sample(lambda: np.copy(frame)))
            for name, fn in funcs.items():
                got[name].extend(_sample(fn) for _ in range(samples))
    finally:
        if gc_was:
            gc.enable()
    copy_med = float(np.median(copies))
    out = [Timing("np.copy(frame)", copy_med, float(np.percentile(copies, 90)), min(copies), 1.0)]
    for name, xs in got.items():
        med = float(np.median(xs))
        out.append(Timing(name, med, float(np.percentile(xs, 90)), min(xs), med / copy_med))
    return out


def format_timings(timings: list[Timing], title: str) -> str:
    lines = [title, f"{'work':<44} {'median ms':>10} {'p90 ms':>8} {'best ms':>8} {'x np.copy':>9}"]
    for t in timings:
        lines.append(
            f"{t.name:<44} {t.median_s * 1e3:>10.3f} {t.p90_s * 1e3:>8.3f} {t.best_s * 1e3:>8.3f} {t.ratio_to_copy:>9.1f}"
        )
    return "\n".join(lines)


def scan_benchmark(intr: Intrinsics = KINECT_V1) -> list[Timing]:
    """Both scan methods over the whole image on one noisy frame."""
    depth, mount = bench_scene(intr)
    h = intr.height
    band = 2 * int(min(intr.cy, h - intr.cy))
    funcs = {
        "scan exact, whole image": lambda: depth_to_scan(depth, intr, mount, ScanParams()),
        "scan paper, whole band, ground + tilt on": lambda: depth_to_scan(
            depth, intr, mount, ScanParams(method="paper", scan_height=band)
        ),
        "scan paper, params.yaml (400 rows)": lambda: depth_to_scan(
            depth, intr, mount, ScanParams(method="paper", scan_height=min(400, band))
        ),
    }
    return time_functions(funcs, depth)


def machine() -> str:
    return f"{platform.processor() or platform.machine()}, Python {platform.python_version()}, numpy {np.__version__}"


def main() -> None:
    print(format_timings(scan_benchmark(), f"640x480 uint16, one core; {machine()}"))  # noqa: T201


if __name__ == "__main__":
    main()
