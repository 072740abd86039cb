"""Soak: replay many frames at full speed through every sink and watch memory and drops.

The daemon runs as a child process (``depthnav run``), exactly as on a robot. This process is its
far end: it reads the JSON lines on stdout, receives the UDP datagrams and the MAVLink stream on
loopback, and samples the child's resident memory (VmRSS in /proc/PID/status) as frames go by.

Figures reported: frames read by the daemon, lines and datagrams received (every seq 0..N-1 must
arrive once), duration, frame rate, RSS after warm-up and at the end, and the growth between them.
"""

from __future__ import annotations

import json
import logging
import socket
import subprocess
import sys
import tempfile
import threading
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

log = logging.getLogger(__name__)

ROOT = Path(__file__).resolve().parents[2]
FIXTURE = ROOT / "fixtures" / "corridor_step"
RSS_LIMIT_MB = 5.0
UDP_BUFFER = 64 << 20  # a receiver that keeps up on loopback; the bitmap shows any loss anyway


@dataclass
class SoakReport:
    """What a soak run measured."""

    frames_requested: int
    frames_processed: int = 0  # from the daemon's own summary line
    stdout_lines: int = 0  # JSON lines, seq 0..N-1 in order
    stdout_out_of_order: int = 0
    udp_received: int = 0  # distinct seqs received over UDP
    udp_missing: int = 0  # seqs 0..N-1 never received
    mavlink_bytes: int = 0
    rrd_bytes: int = 0
    duration_s: float = 0.0
    fps: float = 0.0
    warmup_frames: int = 0
    rss_warm_mb: float = 0.0  # VmRSS once warm-up frames were done
    rss_end_mb: float = 0.0  # VmRSS at the last sample before the daemon exited
    rss_max_mb: float = 0.0
    rss_growth_mb: float = 0.0  # the lowest RSS of the last third less that of the first
    exit_code: int | None = None
    sinks: list[str] = field(default_factory=list)
    samples: list[tuple[int, float]] = field(default_factory=list)  # (frames, VmRSS MB)

    @property
    def ok(self) -> bool:
        """No frame dropped anywhere and memory flat."""
        n = self.frames_requested
        return (
            self.exit_code == 0
            and self.frames_processed == n
            and self.stdout_lines == n
            and self.stdout_out_of_order == 0
            and self.udp_received == n
            and self.udp_missing == 0
            and self.rss_growth_mb < RSS_LIMIT_MB
        )

    def text(self) -> str:
        """The figures, one per line."""
        lines = [
            f"frames requested      {self.frames_requested}",
            f"frames processed      {self.frames_processed}",
            f"stdout JSON lines     {self.stdout_lines} (out of order: {self.stdout_out_of_order})",
            f"UDP datagrams         {self.udp_received} distinct seqs "
            f"(missing: {self.udp_missing})",
            f"MAVLink bytes         {self.mavlink_bytes}",
            f".rrd bytes            {self.rrd_bytes}",
            f"duration              {self.duration_s:.1f} s ({self.fps:.0f} frames/s)",
            f"RSS after warm-up     {self.rss_warm_mb:.1f} MB (at frame {self.warmup_frames})",
            f"RSS at the end        {self.rss_end_mb:.1f} MB (max {self.rss_max_mb:.1f} MB)",
            f"RSS growth            {self.rss_growth_mb:+.2f} MB (limit {RSS_LIMIT_MB:g} MB)",
            f"exit code             {self.exit_code}",
            f"result                {'PASS' if self.ok else 'FAIL'}",
        ]
        return "\n".join(lines)


def vm_rss_mb(pid: int) -> float | None:
    """Resident set size of ``pid`` in MB, or None once it has gone."""
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024.0
    except (FileNotFoundError, ProcessLookupError):
        return None
    return None


def _udp_receiver(bufsize: int) -> socket.socket:
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    for opt in (getattr(socket, "SO_RCVBUFFORCE", None), socket.SO_RCVBUF):
        if opt is None:
            continue
        try:
            sock.setsockopt(socket.SOL_SOCKET, opt, bufsize)
            break
        except OSError:  # SO_RCVBUFFORCE needs CAP_NET_ADMIN; SO_RCVBUF is capped by rmem_max
            continue
    sock.bind(("127.0.0.1", 0))
    sock.settimeout(0.5)
    return sock


class _Receivers:
    """The UDP and MAVLink receivers of a soak: which seqs arrived, how many bytes, in threads."""

    def __init__(self, frames: int) -> None:
        self.frames = frames
        self.udp, self.mav = _udp_receiver(UDP_BUFFER), _udp_receiver(1 << 20)
        self.seen = bytearray(frames)
        self.counts = {"lines": 0, "order": 0, "mav": 0}
        self._done = threading.Event()
        self._threads = [
            threading.Thread(target=self._receive_udp, daemon=True),
            threading.Thread(target=self._receive_mavlink, daemon=True),
        ]

    def start(self) -> None:
        for t in self._threads:
            t.start()

    def stop(self) -> None:
        self._done.set()
        for t in self._threads:
            t.join(timeout=5)
        self.udp.close()
        self.mav.close()

    def _receive_udp(self) -> None:
        while not self._done.is_set():
            try:
                data = self.udp.recv(65535)
            except TimeoutError:
                continue
            seq = json.loads(data)["seq"]
            if 0 <= seq < self.frames:
                self.seen[seq] = 1

    def _receive_mavlink(self) -> None:
        while not self._done.is_set():
            try:
                self.counts["mav"] += len(self.mav.recv(65535))
            except TimeoutError:
                continue


def _sample_rss(
    proc: subprocess.Popen[str], rx: _Receivers, report: SoakReport, sample_s: float
) -> None:
    """(lines so far, VmRSS MB) every ``sample_s`` while the daemon runs."""
    next_at = time.monotonic()
    while proc.poll() is None:
        rss = vm_rss_mb(proc.pid)
        if rss is not None:
            report.samples.append((rx.counts["lines"], rss))
        next_at += sample_s
        time.sleep(max(0.0, next_at - time.monotonic()))


def _read_json_lines(
    proc: subprocess.Popen[str], rx: _Receivers, t0: float, timeout_s: float
) -> None:
    """Count the daemon's JSON lines and those out of order; kill it after ``timeout_s``."""
    assert proc.stdout is not None
    expected = 0
    for line in proc.stdout:
        if not line.startswith("{"):
            continue  # the text sink's summary lines
        seq = json.loads(line)["seq"]
        if seq != expected:
            rx.counts["order"] += 1
        expected = seq + 1
        rx.counts["lines"] += 1
        if time.monotonic() - t0 > timeout_s:
            proc.kill()
            break


def _summarise(report: SoakReport, rx: _Receivers, rrd: Path, stderr: str) -> None:
    """Fill the report's counts, rate and memory figures from what was received and logged."""
    report.stdout_lines = rx.counts["lines"]
    report.stdout_out_of_order = rx.counts["order"]
    report.mavlink_bytes = rx.counts["mav"]
    report.udp_received = sum(rx.seen)
    report.udp_missing = report.frames_requested - report.udp_received
    report.fps = report.stdout_lines / report.duration_s if report.duration_s else 0.0
    report.rrd_bytes = rrd.stat().st_size if rrd.exists() else 0
    for text in stderr.splitlines():
        if text.endswith("frames processed") or "frames processed;" in text:
            report.frames_processed = int(text.split("INFO:")[1].split()[0])
    warm = [rss for n, rss in report.samples if n >= report.warmup_frames]
    if warm:
        report.rss_warm_mb, report.rss_end_mb = warm[0], warm[-1]
        report.rss_max_mb = max(warm)
        # the floor RSS returns to, first third against last: rerun's batcher holds chunks
        # between flushes (a saw tooth up to ~150 MB over 100,000 frames with the drop-off
        # areas drawn), so two single samples could land on a tooth; a leak lifts the floor
        third = max(1, len(warm) // 3)
        report.rss_growth_mb = min(warm[-third:]) - min(warm[:third])
    if report.exit_code != 0:
        log.error("the daemon exited with %s: %s", report.exit_code, stderr[-2000:])


def run_soak(
    frames: int,
    *,
    device: str | None = None,
    workdir: Path | None = None,
    warmup: int | None = None,
    rrd_every: int = 10,
    sample_s: float = 0.5,
    timeout_s: float = 3600.0,
) -> SoakReport:
    """Replay ``frames`` frames at max rate through stdout, text, udp, null, rerun file and
    mavlink+udp sinks, and measure drops and memory.

    Args:
        frames: frames to process (the recording loops).
        device: device spec; default the bundled fixture at 640x480, looping at max rate.
        workdir: where the .rrd goes; a temporary folder by default (removed afterwards).
        warmup: frames before the memory baseline; default 1,000 or a tenth of ``frames``.
        rrd_every: the rerun file sink logs every Nth frame, without the depth image (a 640x480
            image per frame would be 60 GB over 100,000 frames).
        sample_s: how often VmRSS is read.
        timeout_s: give up (and fail) after this long.
    """
    device = device or f"replay:{FIXTURE}?rate=max&loop=1"
    warmup = warmup if warmup is not None else max(1000, frames // 10)
    report = SoakReport(frames, warmup_frames=min(warmup, frames))
    own_dir = workdir is None
    work = Path(tempfile.mkdtemp(prefix="depthnav-soak-")) if own_dir else Path(workdir)
    rx = _Receivers(frames)
    rrd = work / "soak.rrd"
    report.sinks = [
        "stdout",
        "text?every=1000",
        f"udp://127.0.0.1:{rx.udp.getsockname()[1]}",
        "null",
        f"rerun:{rrd}?every={rrd_every}&image=0",
        f"mavlink+udp://127.0.0.1:{rx.mav.getsockname()[1]}",
    ]
    cmd = [sys.executable, "-m", "depthnav_daemon", "run", "--device", device]
    cmd += ["--max-frames", str(frames), "--set", "daemon.pose_every_frames=30"]
    for spec in report.sinks:
        cmd += ["--sink", spec]
    err_path = work / "daemon.stderr"
    rx.start()
    t0 = time.monotonic()
    with open(err_path, "w") as err:
        proc = subprocess.Popen(
            cmd, stdout=subprocess.PIPE, stderr=err, text=True, cwd=ROOT, bufsize=1 << 16
        )
    sampler = threading.Thread(target=_sample_rss, args=(proc, rx, report, sample_s), daemon=True)
    sampler.start()
    _read_json_lines(proc, rx, t0, timeout_s)
    report.exit_code = proc.wait()
    report.duration_s = time.monotonic() - t0
    sampler.join(timeout=5)
    time.sleep(1.0)  # the last datagrams are on their way
    rx.stop()
    _summarise(report, rx, rrd, err_path.read_text())
    if own_dir:
        for path in work.iterdir():
            path.unlink()
        work.rmdir()
    return report


def main(argv: list[str] | None = None) -> int:
    """``python scripts/soak.py [FRAMES] [--json]``: run the soak and print the figures."""
    import argparse

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "frames", type=int, nargs="?", default=100_000, help="frames (default 100000)"
    )
    parser.add_argument(
        "--device", help="device spec (default: the bundled fixture, looping at max rate)"
    )
    parser.add_argument("--json", action="store_true", help="print the report as JSON")
    args = parser.parse_args(argv)
    if args.frames < 1:
        parser.error("FRAMES must be 1 or more")
    logging.basicConfig(level=logging.INFO, format="soak: %(message)s")
    report = run_soak(args.frames, device=args.device)
    out = asdict(report)
    out["ok"] = report.ok
    print(json.dumps(out) if args.json else report.text())  # noqa: T201 - the script's output
    return 0 if report.ok else 1
