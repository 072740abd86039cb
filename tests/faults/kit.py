"""Helpers of the fault suite: the real CLI in a child process, signals, readiness, small files."""

from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Sequence
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
FIXTURE = ROOT / "fixtures" / "corridor_step"
ENDLESS = f"replay:{FIXTURE}?rate=realtime&loop=1"
FAST = f"replay:{FIXTURE}?rate=max"
WAIT_S = 30.0  # generous bound for a slow, noisy 2-core machine; tests return as soon as ready


def depthnav(*args: str, timeout: float = 120, **kw: object) -> subprocess.CompletedProcess[str]:
    """Run the CLI to the end, as a user does."""
    return subprocess.run(
        [sys.executable, "-m", "depthnav_daemon", *args],
        capture_output=True,
        text=True,
        timeout=timeout,
        cwd=ROOT,
        **kw,  # type: ignore[arg-type]
    )


def start(*args: str, stderr_path: Path | None = None) -> subprocess.Popen[str]:
    """Start the CLI with stdout piped and stderr to a file.

    stderr never shares a pipe with stdout: communicate() on two pipes reads the raw fds and
    would lose what readline() already buffered; a file also never fills and blocks the daemon.
    """
    if stderr_path is None:
        fd, name = tempfile.mkstemp(prefix="depthnav-stderr-", suffix=".txt")
        os.close(fd)
        stderr_path = Path(name)
    with open(stderr_path, "w") as err:
        proc = subprocess.Popen(
            [sys.executable, "-m", "depthnav_daemon", *args],
            stdout=subprocess.PIPE,
            stderr=err,
            text=True,
            cwd=ROOT,
        )
    proc.stderr_path = stderr_path  # type: ignore[attr-defined]
    return proc


def catches(pid: int, sig: int) -> bool:
    """True once process ``pid`` has a handler for ``sig`` (SigCgt in /proc/PID/status)."""
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("SigCgt:"):
                return bool(int(line.split()[1], 16) >> (sig - 1) & 1)
    except FileNotFoundError:
        return False
    return False


def wait_until_ours(proc: subprocess.Popen[str]) -> None:
    """Wait until depthnav's own code runs (its SIGTERM handler is installed)."""
    deadline = time.monotonic() + WAIT_S
    while not catches(proc.pid, signal.SIGTERM):
        assert proc.poll() is None, "depthnav exited during start-up"
        assert time.monotonic() < deadline, "depthnav did not start within the bound"
        time.sleep(0.005)


def read_lines(proc: subprocess.Popen[str], n: int) -> list[str]:
    """Read ``n`` stdout lines (each must be a complete JSON object)."""
    assert proc.stdout is not None
    out = []
    for _ in range(n):
        line = proc.stdout.readline()
        assert line, "stdout ended early"
        json.loads(line)
        out.append(line)
    return out


def finish(
    proc: subprocess.Popen[str], sig: int | None = signal.SIGTERM, timeout: float = WAIT_S
) -> tuple[int, str, str]:
    """Signal the process, and return (exit code, rest of stdout, stderr) once it has exited.

    The rest of stdout is read through the same text buffer readline() used (communicate() with a
    timeout reads the raw fd and would lose the bytes already buffered).
    """
    assert proc.stdout is not None
    rest: list[str] = []
    reader = threading.Thread(target=lambda: rest.append(proc.stdout.read()), daemon=True)
    reader.start()
    if sig is not None:
        proc.send_signal(sig)
    try:
        proc.wait(timeout=timeout)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait()
        raise AssertionError(f"did not exit within {timeout} s after the signal") from None
    reader.join(timeout=timeout)
    assert not reader.is_alive(), "stdout stayed open after the process exited"
    err = Path(proc.stderr_path).read_text()  # type: ignore[attr-defined]
    return proc.returncode, "".join(rest), err


def json_lines(text: str) -> list[dict]:
    """Every line parsed strictly (a half-written line fails)."""
    return [json.loads(line) for line in text.splitlines() if line.strip()]


def one_error_line(stderr: str) -> str:
    """The one ``error:`` line of a failed command (and no traceback)."""
    assert "Traceback" not in stderr, stderr
    errors = [line for line in stderr.splitlines() if "error:" in line]
    assert len(errors) == 1, stderr
    return errors[0]


def free_udp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def free_tcp_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def env_with(paths: Sequence[Path]) -> dict[str, str]:
    """os.environ with PYTHONPATH extended (for child-process snippets)."""
    return {**os.environ, "PYTHONPATH": os.pathsep.join([str(ROOT), *map(str, paths)])}
