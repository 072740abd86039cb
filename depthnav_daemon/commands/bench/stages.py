"""What ``depthnav bench`` times inside the process: each stage and the per-frame pipeline against
np.copy of the same frame, in interleaved rounds (method in ``bench``'s docstring)."""

from __future__ import annotations

import dataclasses
import gc
import itertools
import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from depthnav_daemon.pipeline import MountState, StageParams, process
from depthnav_daemon.pipeline.cliff import CliffParams, detect_cliffs
from depthnav_daemon.pipeline.geometry import MAX_MOUNT_HEIGHT_M, Mount
from depthnav_daemon.pipeline.pose import (
    PoseParams,
    estimate_pose,
    floor_candidates,
    ransac_plane,
    refine_plane,
)
from depthnav_daemon.pipeline.scan import ScanParams, depth_to_scan, scan_layout
from depthnav_daemon.sim.synthetic import Box, KinectNoise, Scene, render, step_down
from drivers.base import KINECT_V1, Frame, Intrinsics

FIXTURE = Path(__file__).resolve().parents[3] / "fixtures" / "corridor_step"
MAX_FRAMES = 64
POSE_EVERY = 30  # the daemon's default pose_every_frames
# the resolutions of the table; intrinsics of the typical sensor at each (approximate)
RESOLUTIONS: dict[str, Intrinsics] = {
    "640x480 (Kinect v1)": KINECT_V1,
    "512x424 (Kinect v2)": Intrinsics(512, 424, 365.5, 365.5, 255.5, 211.5),
    "848x480 (RealSense D435)": Intrinsics(848, 480, 425.0, 425.0, 423.5, 239.5),
    "1280x720 (RealSense D435)": Intrinsics(1280, 720, 640.0, 640.0, 639.5, 359.5),
}
DENSE_CLIFF = CliffParams(
    block_size=8, row_step=1, col_step=1, block_points_thresh=10, used_depth_height=8192
)
RANSAC_TARGET = PoseParams(row_step=2, col_step=2, max_points=5000, ransac_iterations=200)


@dataclass(frozen=True, slots=True)
class Timing:
    """Per-frame statistics of one benchmarked piece of work, seconds.

    Attributes:
        name: what was timed.
        median_s, p90_s, best_s: over all samples.
        ratio_to_copy: median over rounds of (this round's median / this round's np.copy median).
        best_ratio: best sample / np.copy's best sample (a low-noise estimate on a loaded machine).
        fps: frames per second at the median (1 / median_s).
    """

    name: str
    median_s: float
    p90_s: float
    best_s: float
    ratio_to_copy: float
    fps: float = 0.0
    best_ratio: float = 0.0


def bench_scene(
    intr: Intrinsics = KINECT_V1, mount: Mount | None = None, seed: int = 1
) -> tuple[np.ndarray, Mount]:
    """A noisy corridor-like frame: boxes, a wall and a step down, as uint16 mm."""
    mount = mount or Mount(0.55, 15.0, 0.0)
    scene = Scene(
        boxes=(
            Box(1.5, 0.4, 0.3, 0.3, 0.3),
            Box(2.2, -0.5, 0.4, 0.4, 0.6, yaw_deg=20),
            Box(4.0, 0.0, 0.1, 6.0, 2.5),
        ),
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


@dataclass(frozen=True, slots=True)
class Work:
    """One thing to time: ``fn`` processes ``frames_per_call`` frames per call."""

    name: str
    fn: Callable[[], object]
    frames_per_call: int = 1


def time_work(
    work: Sequence[Work],
    frames: Sequence[np.ndarray],
    rounds: int = 7,
    samples: int = 5,
    min_batch_s: float = 0.002,
) -> list[Timing]:
    """Interleaved rounds: np.copy of a frame, then every piece of work; per-frame statistics.

    Args:
        work: what to time (each already warmed up by one call here).
        frames: the frames the work goes through in turn; np.copy goes through them the same way,
            so that the reference reads its frame from the same level of the memory hierarchy.
        rounds, samples: rounds, and samples per piece of work in each round.
        min_batch_s: shortest sample, seconds.
    """
    nxt = itertools.cycle(frames).__next__
    for w in work:
        w.fn()  # warm-up: tables, caches, compiled kernels
    copies: list[list[float]] = []
    got: dict[str, list[list[float]]] = {w.name: [] for w in work}
    gc_was = gc.isenabled()
    gc.disable()
    try:
        for _ in range(rounds):
            copies.append([_sample(lambda: np.copy(nxt()), min_batch_s) for _ in range(samples)])
            for w in work:
                got[w.name].append(
                    [_sample(w.fn, min_batch_s) / w.frames_per_call for _ in range(samples)]
                )
            gc.collect()  # between rounds, never inside a sample
    finally:
        if gc_was:
            gc.enable()
    return [_stats("np.copy(frame)", copies, copies)] + [
        _stats(name, xs, copies) for name, xs in got.items()
    ]


def _stats(name: str, per_round: list[list[float]], copies: list[list[float]]) -> Timing:
    xs = np.concatenate(per_round)
    ratios = [
        float(np.median(r)) / float(np.median(c)) for r, c in zip(per_round, copies, strict=True)
    ]
    med = float(np.median(xs))
    return Timing(
        name,
        med,
        float(np.percentile(xs, 90)),
        float(xs.min()),
        float(np.median(ratios)),
        1.0 / med,
        float(xs.min()) / float(np.concatenate(copies).min()),
    )


def format_timings(timings: list[Timing], title: str) -> str:
    """A text table of timings, ms per frame."""
    lines = [
        title,
        f"  {'work':<58} {'median ms':>9} {'p90 ms':>8} {'best ms':>8} {'frames/s':>9} "
        f"{'x np.copy':>9} {'best x':>6}",
    ]
    for t in timings:
        lines.append(
            f"  {t.name:<58} {t.median_s * 1e3:>9.3f} {t.p90_s * 1e3:>8.3f} {t.best_s * 1e3:>8.3f} "
            f"{t.fps:>9.0f} {t.ratio_to_copy:>9.1f} {t.best_ratio:>6.1f}"
        )
    return "\n".join(lines)


# --- what is timed --------------------------------------------------------------------------------


def load_frames(spec: str, limit: int = MAX_FRAMES) -> list[Frame]:
    """Up to ``limit`` frames of a device or recording (drivers' spec grammar)."""
    from drivers import create_driver

    driver = create_driver(spec)
    driver.open()
    frames: list[Frame] = []
    try:
        while len(frames) < limit:
            frame = driver.read_frame(timeout_s=5.0)
            if frame is None:
                break
            frames.append(frame)
    finally:
        driver.close()
    return frames


def floor_mount(frames: Sequence[Frame], fallback: Mount) -> Mount:
    """The mount the daemon would settle on: a floor estimate on the first frame, else
    ``fallback``."""
    est = estimate_pose(
        frames[0].depth_mm, frames[0].intrinsics, PoseParams(), np.random.default_rng(0)
    )
    if not est.ok:
        return fallback
    return Mount(round(est.height_m, 3), round(est.tilt_deg, 2), round(est.roll_deg, 2))


# the exact scan's cost grows with tilt and roll: the mounts and resolutions its target (at most
# 6x np.copy) holds at, timed by every bench run
SCAN_MOUNTS = (Mount(0.55, 15.0, 0.0), Mount(0.8, 40.0, 5.0), Mount(1.2, 50.0, -8.0))
SCAN_RESOLUTIONS = ("640x480 (Kinect v1)", "1280x720 (RealSense D435)")
SCAN_TARGET = 6.0  # x np.copy of the same frame


def scan_across_mounts(
    rounds: int, samples: int, min_batch_s: float, n_frames: int = 4, n_buffers: int = 12
) -> list[Timing]:
    """The exact scan over synthetic corridor frames from each of SCAN_MOUNTS at each of
    SCAN_RESOLUTIONS, each against np.copy of its own frames (interleaved rounds as time_work).

    ``n_frames`` are rendered (rendering 1280x720 takes about a second a frame) and cycled through
    ``n_buffers`` separate arrays, as the other synthetic views cycle through 12 frames: a new
    frame is not in the cache, for np.copy as for the scan.
    """
    out: list[Timing] = []
    params = ScanParams()
    for res in SCAN_RESOLUTIONS:
        intr = RESOLUTIONS[res]
        for mount in SCAN_MOUNTS:
            frames, used = synthetic_frames(intr, n=n_frames, mount=mount)
            depths = [frames[k % len(frames)].depth_mm.copy() for k in range(n_buffers)]
            nxt = itertools.cycle(depths).__next__
            name = (
                f"scan exact, {intr.width}x{intr.height}, {used.height_m:g} m, "
                f"{used.tilt_deg:g} deg tilt, {used.roll_deg:g} deg roll"
            )
            work = [Work(name, lambda n=nxt, i=intr, m=used: depth_to_scan(n(), i, m, params))]
            out.append(time_work(work, depths, rounds, samples, min_batch_s)[1])
    return out


def stage_work(frames: Sequence[Frame], mount: Mount, pipeline: bool = True) -> list[Work]:
    """Every stage (and the whole per-frame pipeline) over the frames in turn."""
    intr = frames[0].intrinsics
    depths = [f.depth_mm for f in frames]
    nxt = itertools.cycle(depths).__next__
    band = 2 * int(min(intr.cy, intr.height - intr.cy))
    exact, paper = ScanParams(), ScanParams(method="paper", scan_height=band)
    yaml_paper = ScanParams(method="paper", scan_height=min(400, band))
    layout = scan_layout(intr, mount, exact)
    cliff, pose = CliffParams(), PoseParams()
    rng = np.random.default_rng(0)

    def ransac_target() -> None:
        pts = floor_candidates(nxt(), intr, RANSAC_TARGET)
        plane, _ = ransac_plane(
            pts, RANSAC_TARGET.ransac_iterations, RANSAC_TARGET.inlier_dist_m, rng, adaptive=False
        )
        refine_plane(pts, plane, RANSAC_TARGET.inlier_dist_m)

    work = [
        Work("scan exact, whole image", lambda: depth_to_scan(nxt(), intr, mount, exact)),
        Work(
            f"scan paper, whole band ({band} rows), ground + tilt on",
            lambda: depth_to_scan(nxt(), intr, mount, paper),
        ),
        Work(
            f"scan paper, params.yaml ({yaml_paper.scan_height} rows)",
            lambda: depth_to_scan(nxt(), intr, mount, yaml_paper),
        ),
        Work(
            "cliff, params.yaml (16 px blocks, 8x8 step, 400 rows)",
            lambda: detect_cliffs(nxt(), intr, mount, cliff, *layout),
        ),
        Work(
            "cliff, 8 px blocks over every pixel (step 1)",
            lambda: detect_cliffs(nxt(), intr, mount, DENSE_CLIFF, *layout),
        ),
        Work(
            "pose, daemon defaults (3000 pts, <= 500 hyps, adaptive)",
            lambda: estimate_pose(nxt(), intr, pose, rng),
        ),
        Work("pose: candidates + RANSAC 200 x 5000 (no early stop) + refine", ransac_target),
    ]
    work += robot_work(frames, mount, cliff)
    work.append(mount_change_work(intr, mount, StageParams(scan=exact, cliff=cliff), pose))
    if pipeline:
        work.append(
            Work(
                f"pipeline per frame (scan + cliff, pose every {POSE_EVERY})",
                _pipeline_fn(frames, mount, exact, cliff, pose, rng),
                POSE_EVERY,
            )
        )
    return work


def mount_change_work(
    intr: Intrinsics, mount: Mount, params: StageParams, pose: PoseParams
) -> Work:
    """A large mount change: every table of a mount never seen before (the scan's, the cliff
    detector's, the memory's view, and the pose stage's prior window around it), as the worker
    of daemon.stage_tables builds them (the frame loop goes on meanwhile)."""
    from depthnav_daemon.pipeline import prepare
    from depthnav_daemon.pipeline.pose_fit import _pose_table

    count = itertools.count(1)
    # 10 cm, 10 deg of tilt and 5 of roll away (toward the middle of the accepted ranges)
    tilt = mount.tilt_deg + (10.0 if mount.tilt_deg < 0 else -10.0)
    roll = mount.roll_deg + (5.0 if mount.roll_deg < 0 else -5.0)
    height = mount.height_m + (0.1 if mount.height_m <= MAX_MOUNT_HEIGHT_M / 2 else -0.1)

    def change() -> None:
        k = next(count)  # a little further at every call: the tables are cached
        new = Mount(height + 1e-6 * k, tilt, roll)
        prepare(intr, new, params)
        prior = dataclasses.replace(pose, height_min_m=pose.height_min_m + 1e-6 * k)
        _pose_table(intr, prior)

    return Work("large mount change: all tables of a new mount (scan, cliff, pose)", change)


def robot_work(frames: Sequence[Frame], mount: Mount, cliff: CliffParams) -> list[Work]:
    """The robot's view: the base-frame conversion of an off-origin sensor, the memory update and
    read-back, and the merge of two sensors (their inputs made once, up front)."""
    from depthnav_daemon.pipeline import to_base_frame
    from depthnav_daemon.pipeline.memory import (
        MemoryParams,
        SensorView,
        new_state,
        read_scan,
        update,
    )
    from depthnav_daemon.pipeline.merge import merge_scans

    params = StageParams(scan=ScanParams(), cliff=cliff)
    placed = dataclasses.replace(mount, x_m=0.2, y_m=-0.1, yaw_deg=30.0)
    left = dataclasses.replace(mount, x_m=0.3, y_m=0.12, yaw_deg=40.0)
    right = dataclasses.replace(mount, x_m=0.1, y_m=-0.2, yaw_deg=-40.0)
    level = [process(f, mount, params) for f in frames]
    pairs = [(process(f, left, params).scan, process(f, right, params).scan) for f in frames]
    views = [
        SensorView(
            mount, f.intrinsics, r.scan, r.cliff.scan if r.cliff else None, (0, -1, 1), 1, 17
        )
        for f, r in zip(frames, level, strict=True)
    ]
    state = new_state(MemoryParams())
    step = itertools.count()
    for i, v in enumerate(views):  # a memory that holds what these frames show
        update(state, (0.01 * i, 0.0, 0.0), i / 30.0, [v])
    nv = itertools.cycle(views).__next__
    nl = itertools.cycle(zip(frames, level, strict=True)).__next__
    npair = itertools.cycle(pairs).__next__

    def memory_update() -> None:
        k = next(step) + len(views)  # the robot drives on at 1 cm a frame (0.3 m/s at 30 Hz)
        update(state, (0.01 * k, 0.0, 0.0), k / 30.0, [nv()])

    def base_frame() -> None:
        f, r = nl()
        to_base_frame(r.scan, r.cliff, placed, params, r.intrinsics, f.depth_mm)

    return [
        Work("placement: scan + cliff to the base frame (0.2, -0.1 m, 30 deg)", base_frame),
        Work("memory update, one view (8 x 8 m grid at 5 cm)", memory_update),
        Work(
            "memory read-back: 360 deg memory scan",
            lambda: read_scan(state, (0.01 * len(views), 0.0, 0.0)),
        ),
        Work("merge two sensors' base-frame scans (+-40 deg)", lambda: merge_scans(npair())),
    ]


def _pipeline_fn(
    frames: Sequence[Frame],
    mount: Mount,
    scan: ScanParams,
    cliff: CliffParams,
    pose: PoseParams,
    rng: np.random.Generator,
) -> Callable[[], None]:
    """POSE_EVERY frames through ``process`` as the daemon calls it, the first with a pose
    estimate."""
    nxt = itertools.cycle(frames).__next__

    params = StageParams(scan=scan, cliff=cliff)

    def run() -> None:
        frame = nxt()
        t0 = time.perf_counter()
        est = estimate_pose(frame.depth_mm, frame.intrinsics, pose, rng)
        state = MountState(mount=mount, pose=est, pose_s=time.perf_counter() - t0)
        process(frame, state, params, time.perf_counter)
        for _ in range(POSE_EVERY - 1):
            process(nxt(), mount, params, time.perf_counter)

    return run


def synthetic_frames(
    intr: Intrinsics, n: int = 12, mount: Mount | None = None
) -> tuple[list[Frame], Mount]:
    """``n`` noisy corridor frames (bench_scene) at the resolution of ``intr``, seen from ``mount``
    (default 0.55 m, 15 deg down, no roll)."""
    frames = []
    mount = mount or Mount(0.55, 15.0, 0.0)
    for seed in range(n):
        depth, mount = bench_scene(intr, mount, seed=seed + 1)
        frames.append(Frame(seed, seed / 30.0, depth, intr))
    return frames, mount
