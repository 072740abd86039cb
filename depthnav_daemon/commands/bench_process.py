"""What ``depthnav bench`` times as whole processes: frame-read-to-UDP latency of the real loop,
the CPU the daemon uses at 30 frames/s and the start-up time of ``depthnav run``."""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np

from depthnav_daemon.commands.bench_stages import FIXTURE, Work
from depthnav_daemon.errors import DepthnavError
from drivers.base import Frame


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


_CONSUMER = """
import os, selectors, socket, sys
udp = socket.socket(fileno=int(sys.argv[1]))
sel = selectors.DefaultSelector()
sel.register(udp, selectors.EVENT_READ)
sel.register(0, selectors.EVENT_READ)
while True:
    for key, _ in sel.select():
        if key.fileobj is udp:
            udp.recv(65536)
        elif not os.read(0, 1 << 20):
            sys.exit(0)
"""


class _Consumer:
    """Another process that reads and drops the loop's UDP datagrams and the lines on ``pipe``,
    as a robot's programs would. (A receiver thread in the bench's own process took the GIL from
    the frame loop at every datagram: a cost the daemon does not have.)"""

    def __init__(self) -> None:
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind(("127.0.0.1", 0))
        self.port = self.sock.getsockname()[1]
        r, w = os.pipe()
        fd = self.sock.fileno()
        self.proc = subprocess.Popen(
            [sys.executable, "-c", _CONSUMER, str(fd)], stdin=r, pass_fds=(fd,)
        )
        os.close(r)
        self.pipe = os.fdopen(w, "w")

    def close(self) -> None:
        self.pipe.close()  # the consumer ends at the end of its input
        try:
            self.proc.wait(5)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait()
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

    from depthnav_daemon.config.loader import Config, DaemonParams
    from depthnav_daemon.daemon.loop import run
    from depthnav_daemon.sinks import create_sink
    from drivers import create_driver

    drain = _Consumer()
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


LOOP_SINKS = {
    "null": ("null",),
    "stdout + udp": ("stdout", "udp"),
    "stdout to a pipe + udp": ("pipe", "udp"),
}


def loop_cost(
    spec: str, n_frames: int = 600, rounds: int = 5, reference: Work | None = None
) -> tuple[dict[str, float], dict[str, float]]:
    """Per-frame wall time of the daemon's whole frame loop (read, stages, sinks), in-process.

    For each sink set of LOOP_SINKS the loop runs ``n_frames`` frames of ``spec`` at full speed
    (stdout goes to /dev/null, or to a pipe that another process reads; UDP to that process),
    timed from the first frame's output to the last one's (start-up is timed on its own).
    Right before each run, ``reference`` (the in-process pipeline) runs as many frames: on a busy
    machine the two then see the same load, and their ratio holds where either time alone moves.

    Returns:
        (ms per frame, median over ``rounds`` runs; loop / reference, median over the runs'
        ratios), each keyed by the set's name; the ratios are empty without ``reference``.
    """
    import logging

    from depthnav_daemon.config.loader import Config, DaemonParams
    from depthnav_daemon.daemon.loop import run
    from depthnav_daemon.sinks import create_sink
    from depthnav_daemon.sinks.stdout import StdoutSink

    consumer = _Consumer()
    quiet = logging.getLogger("depthnav_daemon")
    level = quiet.level
    quiet.setLevel(logging.WARNING)
    ms: dict[str, float] = {}
    ratio: dict[str, float] = {}
    try:
        with open(os.devnull, "w") as devnull:

            def make(name: str) -> Any:
                if name == "stdout":
                    return StdoutSink("stdout", stream=devnull)
                if name == "pipe":
                    return StdoutSink("stdout", stream=consumer.pipe)
                if name == "udp":
                    return create_sink(f"udp://127.0.0.1:{consumer.port}")
                return create_sink(name)

            for label, sinks in LOOP_SINKS.items():
                cfg = Config(device=spec, sinks=sinks, daemon=DaemonParams(tilt_source="floor"))
                per_frame, ratios = [], []
                for i in range(rounds + 1):  # the first run builds the tables: not counted
                    ref = _per_frame(reference, n_frames) if reference is not None else None
                    clock = _Clock()

                    def timed(name: str, clock: _Clock = clock) -> Any:
                        sink = make(name)
                        return clock.wrap(sink) if not clock.wrapped else sink

                    run(cfg, threading.Event(), n_frames, sink_factory=timed)
                    loop = clock.per_frame_s()
                    if i:
                        per_frame.append(loop)
                        if ref is not None:
                            ratios.append(loop / ref)
                ms[label] = float(np.median(per_frame)) * 1e3
                if ratios:
                    ratio[label] = float(np.median(ratios))
    finally:
        consumer.close()
        quiet.setLevel(level)
    return ms, ratio


class _Clock:
    """Notes the time of every write to the loop's first sink: from one frame's write to the
    next one's is a whole cycle of the loop (its other sinks, the next read and stages), so the
    run's start (opening the recording, the first frame's tables) and end stay out."""

    def __init__(self) -> None:
        self.times: list[float] = []
        self.wrapped = False

    def wrap(self, inner: Any) -> Any:
        self.wrapped = True
        clock = self

        class Timed:
            name = inner.name

            def write(self, frame: Frame, result: Any) -> None:
                clock.times.append(time.perf_counter())
                inner.write(frame, result)

            def __getattr__(self, attr: str) -> Any:
                return getattr(inner, attr)

        return Timed()

    def per_frame_s(self) -> float:
        if len(self.times) < 2:  # noqa: PLR2004 - two writes make one interval
            raise DepthnavError("the loop delivered fewer than 2 frames to time")
        return (self.times[-1] - self.times[0]) / (len(self.times) - 1)


def _per_frame(work: Work, n_frames: int) -> float:
    """Seconds per frame of ``work`` over about ``n_frames`` frames."""
    calls = max(1, n_frames // work.frames_per_call)
    t0 = time.perf_counter()
    for _ in range(calls):
        work.fn()
    return (time.perf_counter() - t0) / (calls * work.frames_per_call)


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
    """Wall time of ``depthnav run --device replay:fixture --sink stdout --max-frames 1`` (warm
    cache)."""
    cmd = _daemon_cmd(f"replay:{FIXTURE}", "--sink", "stdout", "--max-frames", "1")
    walls = []
    for i in range(repeats + 1):
        t0 = time.perf_counter()
        subprocess.run(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, check=True)
        if i:  # the first run may fill the kernel cache
            walls.append(time.perf_counter() - t0)
    return {"median_s": float(np.median(walls)), "best_s": min(walls), "runs": float(repeats)}
