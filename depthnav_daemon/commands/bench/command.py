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

import argparse
import json
import os
import platform
import sys
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from depthnav_daemon.commands.bench.process import (
    cpu_at_30fps,
    loop_cost,
    startup_time,
    udp_latency,
)
from depthnav_daemon.commands.bench.rebuild import RebuildTiming, format_rebuild, rebuild_timings
from depthnav_daemon.commands.bench.sinks import BUDGETS_MS, sink_work
from depthnav_daemon.commands.bench.stages import (
    FIXTURE,
    RESOLUTIONS,
    SCAN_TARGET,
    Timing,
    floor_mount,
    format_timings,
    load_frames,
    scan_across_mounts,
    stage_work,
    synthetic_frames,
    time_work,
)
from depthnav_daemon.commands.bench.table_memory import (
    SIZES,
    TableMemory,
    format_table_memory,
    table_memory,
)
from depthnav_daemon.errors import ConfigError, DepthnavError
from depthnav_daemon.pipeline.geometry import Mount
from depthnav_daemon.pipeline.scan_table import TABLE_BUDGET_B_PER_PX
from drivers.base import Intrinsics

MOUNT_FIELDS = ("height_m", "tilt_deg", "roll_deg")  # --mount H,TILT,ROLL


@dataclass
class BenchReport:
    """Everything one ``depthnav bench`` run measured (the --json output)."""

    machine: dict[str, Any]
    source: str
    frames: int
    resolution: str
    mount: dict[str, float]
    timings: list[Timing]
    sinks: list[Timing] = field(default_factory=list)  # the outputs' per-frame work
    latency: dict[str, float] | None = None
    loop_ms: dict[str, float] | None = None  # the whole loop per frame, by sink set
    # the whole loop / the in-process pipeline interleaved with it, by sink set (median ratio)
    loop_vs_pipeline: dict[str, float] | None = None
    # the quartiles of those ratios over the blocks (this machine moves them from run to run)
    loop_vs_pipeline_iqr: dict[str, tuple[float, float]] | None = None
    # inside the loop, median ms a frame: the stages' own timings, and each sink's write
    loop_parts: dict[str, dict[str, float]] | None = None
    cpu_30fps: dict[str, float] | None = None
    startup: dict[str, float] | None = None
    resolutions: dict[str, list[Timing]] = field(default_factory=dict)
    scan_mounts: list[Timing] = field(default_factory=list)  # the exact scan at SCAN_MOUNTS
    rebuild: list[RebuildTiming] = field(default_factory=list)  # large mount changes (frames on)
    # the exact scan's and the cliff's tables: bytes per pixel at peak while building
    table_memory: list[TableMemory] = field(default_factory=list)


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
    quick = rounds == 1
    report.scan_mounts = scan_across_mounts(
        rounds, samples, min_batch_s, n_frames=1 if quick else 4, n_buffers=1 if quick else 12
    )
    with sink_work(frames, floor) as work:
        report.sinks = time_work(work, [f.depth_mm for f in frames], rounds, samples, min_batch_s)[
            1:
        ]  # np.copy is in the stages' table already
    loop_spec = spec if device else f"replay:{FIXTURE}?rate=max&loop=1"
    if latency_frames:
        report.latency = udp_latency(loop_spec, latency_frames)
        pipeline = stage_work(frames, floor)[-1]  # "pipeline per frame", the reference
        (
            report.loop_ms,
            report.loop_vs_pipeline,
            report.loop_vs_pipeline_iqr,
            report.loop_parts,
        ) = loop_cost(loop_spec, latency_frames, reference=pipeline)
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
    report.rebuild = rebuild_timings(changes=1 if quick else 5, loaded=not quick)
    report.table_memory = table_memory(SIZES[:1] if quick else SIZES)
    if cpu_seconds:
        report.cpu_30fps = cpu_at_30fps(cpu_seconds)
    if startup:
        report.startup = startup_time()
    return report


def _quartiles(r: BenchReport, key: str) -> str:
    q = (r.loop_vs_pipeline_iqr or {}).get(key)
    return "" if q is None else f" ({q[0]:.2f}-{q[1]:.2f})"


def format_report(r: BenchReport) -> str:
    """The report as text."""
    m = r.machine
    out = [
        f"depthnav bench: {r.source}, {r.frames} frames {r.resolution}, mount {r.mount}",
        f"machine: {m['cpu']}, {m['cores']} cores, loadavg "
        f"{', '.join(f'{x:.2f}' for x in m['loadavg'])}; "
        f"Python {m['python']}, numpy {m['numpy']}, numba {m['numba']}",
        format_timings(r.timings, "per frame, one core (median of interleaved rounds):"),
    ]
    if r.scan_mounts:
        out.append(
            format_timings(
                r.scan_mounts,
                f"exact scan, synthetic corridor from the mounts its target holds at "
                f"(<= {SCAN_TARGET:g}x np.copy of the same frames):",
            )
        )
    if r.sinks:
        budgets = ", ".join(f"{k} {v:g} ms" for k, v in BUDGETS_MS.items())
        out.append(format_timings(r.sinks, f"outputs per frame, as each sink does it ({budgets}):"))
    if r.latency:
        lt = r.latency
        out.append(
            "frame read -> UDP datagram sent "
            f"(daemon loop, full speed, {lt['frames']:.0f} frames): "
            f"p50 {lt['p50_ms']:.3f} ms, p99 {lt['p99_ms']:.3f} ms, max {lt['max_ms']:.3f} ms; "
            f"loop {lt['loop_fps']:.0f} frames/s"
        )
    if r.loop_ms and r.loop_vs_pipeline:
        out.append(
            "whole loop per frame (read, stages, sinks) / in-process pipeline (interleaved: "
            "one call after every 30 frames of the loop, median of the pairs (quartiles); "
            'targets: null <= 1.2x, stdout + udp <= 1.5x; "datagrams not read": the same '
            "sends, nobody woken by them): "
            + ", ".join(
                f"{k} {v:.3f} ms = {r.loop_vs_pipeline[k]:.2f}x{_quartiles(r, k)}"
                for k, v in r.loop_ms.items()
            )
        )
    if r.loop_parts:
        out.append(
            "  inside the loop, median per frame: "
            + "; ".join(
                f"{k}: " + ", ".join(f"{part} {v:.3f} ms" for part, v in p.items())
                for k, p in r.loop_parts.items()
            )
        )
    for name, ts in r.resolutions.items():
        out.append(format_timings(ts, f"synthetic corridor, {name}:"))
    if r.rebuild:
        out.append(format_rebuild(r.rebuild))
    if r.table_memory:
        out.append(format_table_memory(r.table_memory, TABLE_BUDGET_B_PER_PX))
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


def cmd_bench(args: argparse.Namespace) -> int:
    from depthnav_daemon.commands.bench.command import main as bench_main

    if args.rounds < 1:
        raise ConfigError(f"--rounds={args.rounds} is out of range (accepted: 1 or more)")
    if args.cpu_30fps < 0:
        raise ConfigError(f"--cpu-30fps={args.cpu_30fps} is out of range (accepted: seconds > 0)")
    mount = _parse_mount(args.mount) if args.mount is not None else None
    return bench_main(
        device=args.device,
        as_json=args.json,
        resolutions=args.resolutions,
        cpu_seconds=args.cpu_30fps,
        startup=args.startup,
        rounds=args.rounds,
        quick=args.quick,
        mount=mount,
    )


def _parse_mount(text: str) -> Mount:
    """``H,TILT,ROLL`` (metres, degrees, degrees) as a Mount; a bad value is a ConfigError."""
    from depthnav_daemon.pipeline.geometry import Mount

    parts = text.split(",")
    try:
        if len(parts) != len(MOUNT_FIELDS):
            raise ValueError
        height_m, tilt_deg, roll_deg = (float(x) for x in parts)
    except ValueError:
        raise ConfigError(
            f"--mount={text!r} is not H,TILT,ROLL", hint="e.g. --mount 0.55,30,5"
        ) from None
    return Mount(height_m, tilt_deg, roll_deg)
