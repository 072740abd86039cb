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

from depthnav_daemon.commands.bench.stages import FIXTURE, Work
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
        # a socket nobody reads (its buffer fills, then the kernel drops what comes): the same
        # send, with no process woken by it (LOOP_SINKS, "not read")
        self.unread = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.unread.bind(("127.0.0.1", 0))
        self.unread_port = self.unread.getsockname()[1]
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
        self.unread.close()


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


# The sets of sinks the whole loop is timed with. "not read" sends the same datagrams to a socket
# nobody reads: beside "stdout + udp" it shows what the reader's wake-up and work cost the loop (on
# a 2-vCPU VM the reader's work on the other vCPU slows this one: docs/benchmarks.md).
LOOP_SINKS = {
    "null": ("null",),
    "stdout + udp": ("stdout", "udp"),
    "stdout + udp, datagrams not read": ("stdout", "udp-unread"),
    "stdout to a pipe + udp": ("pipe", "udp"),
}


def loop_cost(
    spec: str, n_frames: int = 600, rounds: int = 5, reference: Work | None = None
) -> tuple[
    dict[str, float],
    dict[str, float],
    dict[str, tuple[float, float]],
    dict[str, dict[str, float]],
]:
    """Per-frame wall time of the daemon's whole frame loop (read, stages, sinks), in-process.

    For each sink set of LOOP_SINKS the loop runs ``n_frames`` frames of ``spec`` at full speed
    (stdout goes to /dev/null, or to a pipe that another process reads; UDP to that process, or
    to a socket nobody reads),
    timed from one frame's output to the next (start-up and the end are left out), in blocks of
    ``reference.frames_per_call`` frames. ``reference`` (the in-process pipeline) runs inside the
    same run, one call (as many frames, one pose estimate, as a block) after every block, timed
    apart (see _Clock): on a busy machine, where either time alone moves by half from one second
    to the next, a block and its reference call see the same load.

    Returns:
        (ms per frame: median block of the ``rounds`` runs; loop / reference: median over the
        blocks of block / its reference call; those ratios' quartiles, how far one run's median
        may move; the parts of a frame inside the loop, median ms: "stages" (the stages' own
        timings of the frame) and each sink's write, by its LOOP_SINKS name), each keyed by the
        set's name; the ratios are empty without ``reference``.
    """
    import logging

    from depthnav_daemon.config.loader import Config, DaemonParams
    from depthnav_daemon.daemon.loop import run
    from depthnav_daemon.sinks import create_sink
    from depthnav_daemon.sinks.json.stdout import StdoutSink

    consumer = _Consumer()
    quiet = logging.getLogger("depthnav_daemon")
    level = quiet.level
    quiet.setLevel(logging.WARNING)
    ms: dict[str, float] = {}
    ratio: dict[str, float] = {}
    spread: dict[str, tuple[float, float]] = {}
    parts: dict[str, dict[str, float]] = {}
    try:
        with open(os.devnull, "w") as devnull:

            def make(name: str) -> Any:
                if name == "stdout":
                    return StdoutSink("stdout", stream=devnull)
                if name == "pipe":
                    return StdoutSink("stdout", stream=consumer.pipe)
                if name == "udp":
                    return create_sink(f"udp://127.0.0.1:{consumer.port}")
                if name == "udp-unread":
                    return create_sink(f"udp://127.0.0.1:{consumer.unread_port}")
                return create_sink(name)

            for label, sinks in LOOP_SINKS.items():
                cfg = Config(device=spec, sinks=sinks, daemon=DaemonParams(tilt_source="floor"))
                blocks: list[float] = []
                ratios: list[float] = []
                inside: dict[str, list[float]] = {}
                for i in range(rounds + 1):  # the first run builds the tables: not counted
                    clock = _Clock(reference)

                    def timed(name: str, clock: _Clock = clock) -> Any:
                        return clock.wrap(make(name), name)

                    run(cfg, threading.Event(), n_frames, sink_factory=timed)
                    if i:
                        clock.finish()
                        blocks += [b / clock.block for b in clock.blocks]
                        ratios += clock.ratios()
                        for part, times in clock.parts.items():
                            inside.setdefault(part, []).extend(times)
                ms[label] = float(np.median(blocks)) * 1e3
                parts[label] = {k: float(np.median(v)) * 1e3 for k, v in inside.items() if v}
                if ratios:
                    ratio[label] = float(np.median(ratios))
                    q1, q3 = np.percentile(ratios, [25, 75])
                    spread[label] = (float(q1), float(q3))
    finally:
        consumer.close()
        quiet.setLevel(level)
    return ms, ratio, spread, parts


class _Clock:
    """Times the loop at every write to its first sink: from one frame's write to the next one's
    is a whole cycle of the loop (its other sinks, the next read and stages), so the run's start
    (opening the recording, the first frame's tables) and end stay out.

    Cycles are summed in blocks of ``reference.frames_per_call`` (as many pose estimates as one
    call of the reference); after each block, at the start of a write, one call of ``reference``
    runs, timed apart (the next cycle is timed from its end). A block and the call after it are
    a pair measured within tens of milliseconds: their ratio holds where a busy machine moves
    either alone by half, and the median over pairs leaves out the blocks another process
    preempted (the stages' bench takes medians of samples likewise).
    """

    def __init__(self, reference: Work | None = None, block: int = 30) -> None:
        self.reference = reference
        self.block = reference.frames_per_call if reference is not None else block
        self.wrapped = False
        self.blocks: list[float] = []  # seconds of each block of cycles
        self.references: list[float] = []  # seconds of each reference call, after its block
        self._cycles = 0
        self._block_s = 0.0
        self._last: float | None = None
        self.parts: dict[str, list[float]] = {"stages": []}  # seconds, by part

    def wrap(self, inner: Any, part: str) -> Any:
        """``inner`` with its writes timed as ``part``; the first sink wrapped also ticks the
        clock and notes the stages' time of each frame."""
        first = not self.wrapped
        self.wrapped = True
        clock = self
        times = self.parts.setdefault(part, [])
        stages = self.parts["stages"]

        class Timed:
            name = inner.name

            def write(self, frame: Frame, result: Any) -> None:
                if first:
                    clock.tick()
                    stages.append(sum(result.timings_s.values()))
                t0 = time.perf_counter()
                inner.write(frame, result)
                times.append(time.perf_counter() - t0)

            def __getattr__(self, attr: str) -> Any:
                return getattr(inner, attr)

        return Timed()

    def tick(self) -> None:
        now = time.perf_counter()
        if self._last is not None:
            self._block_s += now - self._last
            self._cycles += 1
            if self._cycles % self.block == 0:
                self.blocks.append(self._block_s)
                self._block_s = 0.0
                if self.reference is not None:
                    self.reference.fn()
                    done = time.perf_counter()
                    self.references.append(done - now)
                    now = done
        self._last = now

    def finish(self) -> None:
        """After a run too short for one block: its cycles as one (scaled), and a reference
        call after it.

        Raises:
            DepthnavError: the loop delivered fewer than 2 frames.
        """
        if self.blocks:
            return
        if not self._cycles:
            raise DepthnavError("the loop delivered fewer than 2 frames to time")
        self.blocks.append(self._block_s * self.block / self._cycles)
        if self.reference is not None:
            t0 = time.perf_counter()
            self.reference.fn()
            self.references.append(time.perf_counter() - t0)

    def per_frame_s(self) -> float:
        """Median block / its cycles."""
        self.finish()
        return float(np.median(self.blocks)) / self.block

    def ratios(self) -> list[float]:
        """Each block / the reference call after it (the same number of frames)."""
        return [b / r for b, r in zip(self.blocks, self.references, strict=False)]


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
    # a bound on its frames (30 a second, 10 s to spare): a bench that is killed leaves no
    # replay looping for ever; the bench stops it with SIGTERM long before
    frames = int((settle_s + seconds + 10.0) * 30)
    cmd = _daemon_cmd(
        f"replay:{FIXTURE}?rate=realtime&loop=1",
        "--sink",
        f"udp://127.0.0.1:{drain.port}",
        "--max-frames",
        str(frames),
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
