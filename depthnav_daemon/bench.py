"""``depthnav bench``: time every stage and the whole per-frame pipeline against np.copy of a frame.

Method (../shared/reference/performance.md §8): frames from a recording (the bundled
``fixtures/corridor_step`` by default) or synthetic scenes, a warm-up (which also loads the compiled
kernels), then interleaved rounds: each round times np.copy of a frame and then every stage, each
sample auto-batched to at least 2 ms, gc off while sampling. Reported per stage: median and p90 of
all samples, best sample, frames per second (1 / median), and the median over rounds of the ratio to
the same round's np.copy (the distance from the memory limit; it does not remove noise).

Also, on request: the frame-read-to-UDP-sent latency of the real frame loop (p50, p99), the CPU
the daemon uses at 30 frames/s with the UDP sink, and the start-up time of ``depthnav run``.
"""

from __future__ import annotations

import gc
import itertools
import json
import math
import os
import platform
import signal
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from depthnav_daemon.errors import DepthnavError
from depthnav_daemon.pipeline import process
from depthnav_daemon.pipeline.cliff import CliffParams, detect_cliffs
from depthnav_daemon.pipeline.geometry import Mount
from depthnav_daemon.pipeline.pose import (
    PoseParams,
    estimate_pose,
    floor_candidates,
    ransac_plane,
    refine_plane,
)
from depthnav_daemon.pipeline.scan import ScanParams, depth_to_scan, scan_layout
from depthnav_daemon.synthetic import Box, KinectNoise, Scene, render, step_down
from drivers.base import KINECT_V1, Frame, Intrinsics

FIXTURE = Path(__file__).resolve().parent.parent / "fixtures" / "corridor_step"
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


@dataclass
class BenchReport:
    """Everything one ``depthnav bench`` run measured (the --json output)."""

    machine: dict[str, Any]
    source: str
    frames: int
    resolution: str
    mount: dict[str, float]
    timings: list[Timing]
    latency: dict[str, float] | None = None
    cpu_30fps: dict[str, float] | None = None
    startup: dict[str, float] | None = None
    resolutions: dict[str, list[Timing]] = field(default_factory=dict)


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


# --- what is timed ---------------------------------------------------------------------------------


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
    """The mount the daemon would settle on: a floor estimate on the first frame, else ``fallback``."""
    est = estimate_pose(
        frames[0].depth_mm, frames[0].intrinsics, PoseParams(), np.random.default_rng(0)
    )
    if not est.ok:
        return fallback
    return Mount(round(est.height_m, 3), round(est.tilt_deg, 2), round(est.roll_deg, 2))


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
    if pipeline:
        work.append(
            Work(
                f"pipeline per frame (scan + cliff, pose every {POSE_EVERY})",
                _pipeline_fn(frames, mount, exact, cliff, pose, rng),
                POSE_EVERY,
            )
        )
    return work


def _pipeline_fn(
    frames: Sequence[Frame],
    mount: Mount,
    scan: ScanParams,
    cliff: CliffParams,
    pose: PoseParams,
    rng: np.random.Generator,
) -> Callable[[], None]:
    """POSE_EVERY frames through ``process`` as the daemon calls it, the first with a pose estimate."""
    nxt = itertools.cycle(frames).__next__

    def run() -> None:
        process(nxt(), mount, scan, cliff, pose, rng, "config", time.perf_counter)
        for _ in range(POSE_EVERY - 1):
            process(nxt(), mount, scan, cliff, None, rng, "config", time.perf_counter)

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


# --- whole-process figures ---------------------------------------------------------------------------


class _TimedDriver:
    """A driver that notes when each frame was read (perf_counter), by frame identity."""

    def __init__(self, inner: Any, marks: dict[int, float]) -> None:
        self._inner = inner
        self._marks = marks

    def read_frame(self, timeout_s: float) -> Frame | None:
        frame = self._inner.read_frame(timeout_s=timeout_s)
        if frame is not None:
            self._marks[id(frame)] = time.perf_counter()
        return frame

    def __getattr__(self, name: str) -> Any:
        return getattr(self._inner, name)


class _TimedSink:
    """A sink that notes, after its inner sink's write returned, how long ago its frame was read."""

    def __init__(self, inner: Any, marks: dict[int, float], latencies: list[float]) -> None:
        self._inner = inner
        self._marks = marks
        self._lat = latencies
        self.name = inner.name

    def write(self, frame: Frame, result: Any) -> None:
        self._inner.write(frame, result)
        t = time.perf_counter()
        t0 = self._marks.pop(id(frame), None)
        if t0 is not None:
            self._lat.append(t - t0)

    def __getattr__(self, name: str) -> Any:
        return getattr(self._inner, name)


class _UdpDrain:
    """A local UDP receiver that reads and counts datagrams in a thread."""

    def __init__(self) -> None:
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind(("127.0.0.1", 0))
        self.sock.settimeout(0.2)
        self.port = self.sock.getsockname()[1]
        self.count = 0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.is_set():
            try:
                self.sock.recv(65536)
                self.count += 1
            except (TimeoutError, OSError):
                continue

    def close(self) -> None:
        self._stop.set()
        self._thread.join(1.0)
        self.sock.close()


def udp_latency(spec: str, n_frames: int = 600) -> dict[str, float]:
    """Frame read to UDP datagram sent, through the daemon's own frame loop at full speed.

    Args:
        spec: a device spec that delivers at least ``n_frames`` frames (e.g. replay with loop=1).
        n_frames: frames to run.

    Returns:
        p50_ms, p99_ms, max_ms of the latency, frames, and fps of the loop (frames / wall time).
    """
    import logging

    from depthnav_daemon.config import Config, DaemonParams
    from depthnav_daemon.daemon import run
    from depthnav_daemon.sinks import create_sink
    from drivers import create_driver

    drain = _UdpDrain()
    marks: dict[int, float] = {}
    lat: list[float] = []
    quiet = logging.getLogger("depthnav_daemon")
    level = quiet.level
    quiet.setLevel(logging.WARNING)  # the loop's info lines are not the bench's output
    cfg = Config(
        device=spec,
        sinks=(f"udp://127.0.0.1:{drain.port}",),
        daemon=DaemonParams(tilt_source="floor"),
    )
    try:
        t0 = time.perf_counter()
        report = run(
            cfg,
            threading.Event(),
            n_frames,
            driver_factory=lambda s: _TimedDriver(create_driver(s), marks),
            sink_factory=lambda s: _TimedSink(create_sink(s), marks, lat),
        )
        wall = time.perf_counter() - t0
    finally:
        drain.close()
        quiet.setLevel(level)
    ms = np.array(lat[1:] if len(lat) > 1 else lat) * 1e3  # the first frame also builds tables
    if ms.size == 0:
        raise DepthnavError(f"{spec} delivered no frame to time the UDP latency on")
    return {
        "p50_ms": float(np.percentile(ms, 50)),
        "p99_ms": float(np.percentile(ms, 99)),
        "max_ms": float(ms.max()),
        "frames": float(report.frames),
        "loop_fps": report.frames / wall,
    }


def _cpu_s(pid: int) -> float:
    """utime + stime of a process, seconds (/proc/PID/stat fields 14 and 15)."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def _daemon_cmd(device: str, *args: str) -> list[str]:
    return [sys.executable, "-m", "depthnav_daemon", "-q", "run", "--device", device, *args]


def cpu_at_30fps(seconds: float = 20.0, settle_s: float = 3.0) -> dict[str, float]:
    """CPU share of one core used by ``depthnav run`` replaying the fixture at 30 frames/s to UDP.

    The first ``settle_s`` (start-up, imports, table builds) are left out of the share.
    """
    drain = _UdpDrain()
    cmd = _daemon_cmd(
        f"replay:{FIXTURE}?rate=realtime&loop=1", "--sink", f"udp://127.0.0.1:{drain.port}"
    )
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    try:
        time.sleep(settle_s)
        if proc.poll() is not None:
            raise DepthnavError(
                f"depthnav run ended early: {proc.stderr.read().decode(errors='replace')[-300:]}"
            )
        c0, n0, t0 = _cpu_s(proc.pid), drain.count, time.perf_counter()
        time.sleep(seconds)
        c1, n1, t1 = _cpu_s(proc.pid), drain.count, time.perf_counter()
    finally:
        proc.send_signal(signal.SIGTERM)
        try:
            proc.wait(5)
        except subprocess.TimeoutExpired:
            proc.kill()
        drain.close()
    wall = t1 - t0
    return {
        "cpu_percent_of_one_core": 100.0 * (c1 - c0) / wall,
        "seconds": wall,
        "datagrams_per_s": (n1 - n0) / wall,
        "startup_cpu_s": c0,
    }


def startup_time(repeats: int = 5) -> dict[str, float]:
    """Wall time of ``depthnav run --device replay:fixture --sink stdout --max-frames 1`` (warm cache)."""
    cmd = _daemon_cmd(f"replay:{FIXTURE}", "--sink", "stdout", "--max-frames", "1")
    walls = []
    for i in range(repeats + 1):
        t0 = time.perf_counter()
        subprocess.run(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, check=True)
        if i:  # the first run may fill the kernel cache
            walls.append(time.perf_counter() - t0)
    return {"median_s": float(np.median(walls)), "best_s": min(walls), "runs": float(repeats)}


# --- the command ---------------------------------------------------------------------------------


def machine() -> dict[str, Any]:
    """The machine and software the figures belong to."""
    import numba

    model = platform.processor() or platform.machine()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                model = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    return {
        "cpu": model,
        "cores": os.cpu_count(),
        "loadavg": list(os.getloadavg()),
        "python": platform.python_version(),
        "numpy": np.__version__,
        "numba": numba.__version__,
    }


def run_bench(
    device: str | None = None,
    rounds: int = 7,
    samples: int = 5,
    latency_frames: int = 600,
    resolutions: bool = False,
    cpu_seconds: float = 0.0,
    startup: bool = False,
    min_batch_s: float = 0.002,
    mount: Mount | None = None,
) -> BenchReport:
    """Measure; see the module docstring. ``device`` None = the bundled fixture.

    ``mount``: also time synthetic corridor frames at the recording's resolution seen from this
    mount (the exact scan's cost grows with tilt and roll).
    """
    spec = device or f"replay:{FIXTURE}"
    frames = load_frames(spec)
    if not frames:
        raise DepthnavError(f"{spec} delivered no frames")
    intr = frames[0].intrinsics
    floor = floor_mount(frames, Mount())
    timings = time_work(
        stage_work(frames, floor), [f.depth_mm for f in frames], rounds, samples, min_batch_s
    )
    report = BenchReport(
        machine(), spec, len(frames), f"{intr.width}x{intr.height}", asdict(floor), timings
    )
    loop_spec = spec if device else f"replay:{FIXTURE}?rate=max&loop=1"
    if latency_frames:
        report.latency = udp_latency(loop_spec, latency_frames)
    views: list[tuple[str, Intrinsics, Mount | None]] = []  # synthetic frames to time as well
    if mount is not None:
        views.append(
            (
                f"{intr.width}x{intr.height} from {mount.height_m:g} m, {mount.tilt_deg:g} deg "
                f"tilt, {mount.roll_deg:g} deg roll",
                intr,
                mount,
            )
        )
    if resolutions:
        views += [(name, res_intr, None) for name, res_intr in RESOLUTIONS.items()]
    for name, view_intr, view_mount in views:
        view_frames, used = synthetic_frames(view_intr, mount=view_mount)
        report.resolutions[name] = time_work(
            stage_work(view_frames, used),
            [f.depth_mm for f in view_frames],
            rounds,
            samples,
            min_batch_s,
        )
    if cpu_seconds:
        report.cpu_30fps = cpu_at_30fps(cpu_seconds)
    if startup:
        report.startup = startup_time()
    return report


def format_report(r: BenchReport) -> str:
    """The report as text."""
    m = r.machine
    out = [
        f"depthnav bench: {r.source}, {r.frames} frames {r.resolution}, mount {r.mount}",
        f"machine: {m['cpu']}, {m['cores']} cores, loadavg {', '.join(f'{x:.2f}' for x in m['loadavg'])}; "
        f"Python {m['python']}, numpy {m['numpy']}, numba {m['numba']}",
        format_timings(r.timings, "per frame, one core (median of interleaved rounds):"),
    ]
    if r.latency:
        lt = r.latency
        out.append(
            f"frame read -> UDP datagram sent (daemon loop, full speed, {lt['frames']:.0f} frames): "
            f"p50 {lt['p50_ms']:.3f} ms, p99 {lt['p99_ms']:.3f} ms, max {lt['max_ms']:.3f} ms; "
            f"loop {lt['loop_fps']:.0f} frames/s"
        )
    for name, ts in r.resolutions.items():
        out.append(format_timings(ts, f"synthetic corridor, {name}:"))
    if r.cpu_30fps:
        c = r.cpu_30fps
        out.append(
            f"depthnav run at 30 frames/s to UDP: {c['cpu_percent_of_one_core']:.1f} % of one core "
            f"over {c['seconds']:.0f} s ({c['datagrams_per_s']:.1f} datagrams/s; start-up "
            f"{c['startup_cpu_s']:.2f} s CPU not counted)"
        )
    if r.startup:
        s = r.startup
        out.append(
            f"start-up to first output (depthnav run --max-frames 1, warm cache): median "
            f"{s['median_s']:.2f} s, best {s['best_s']:.2f} s over {s['runs']:.0f} runs"
        )
    return "\n".join(out)


def main(
    device: str | None = None,
    as_json: bool = False,
    resolutions: bool = False,
    cpu_seconds: float = 0.0,
    startup: bool = False,
    rounds: int = 7,
    quick: bool = False,
    mount: Mount | None = None,
) -> int:
    """``depthnav bench``: measure and print; returns the exit code (0)."""
    kwargs: dict[str, Any] = {}
    if quick:  # a smoke run (tests): one short round, few frames through the loop
        kwargs = {"rounds": 1, "samples": 1, "latency_frames": 40, "min_batch_s": 0.0002}
    else:
        kwargs["rounds"] = rounds
    report = run_bench(
        device,
        resolutions=resolutions,
        cpu_seconds=cpu_seconds,
        startup=startup,
        mount=mount,
        **kwargs,
    )
    if as_json:
        print(json.dumps(asdict(report), indent=1))  # noqa: T201
    else:
        print(format_report(report))  # noqa: T201
    return 0


if __name__ == "__main__":
    sys.exit(main())
