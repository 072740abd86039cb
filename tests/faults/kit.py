"""Helpers of the fault suite: the real CLI in a child process, signals, readiness, small files."""

from __future__ import annotations

import contextlib
import io
import json
import logging
import os
import resource
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
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


# --- the CLI in this process, a child's peak memory, a signal at a chosen import ----------------
STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)


def run_cli(*argv: str) -> tuple[int, str, str]:
    """``cli.main(argv)`` in this process: (exit code, stdout, stderr).

    For the many cases that only need the exit code and the one error line (a child process
    costs a second of imports each). Logging and the signal handlers are restored afterwards.
    """
    from depthnav_daemon import cli

    root = logging.getLogger()
    saved = (root.handlers[:], root.level, {s: signal.getsignal(s) for s in STOP_SIGNALS})
    out, err = io.StringIO(), io.StringIO()
    try:
        with contextlib.redirect_stderr(err), contextlib.redirect_stdout(out):
            try:
                code = cli.main(list(argv))
            except SystemExit as exc:  # argparse: usage errors
                code = exc.code if isinstance(exc.code, int) else 2
    finally:
        root.handlers[:], root.level = saved[0], saved[1]
        for sig, handler in saved[2].items():
            signal.signal(sig, handler)
        for name in ("depthnav_daemon", "drivers"):
            logging.getLogger(name).setLevel(logging.NOTSET)
    return code, out.getvalue(), err.getvalue()


@dataclass(frozen=True)
class Finished:
    """A child process that ran to its end."""

    returncode: int
    stdout: str
    stderr: str
    peak_mb: float  # its peak resident memory (the kernel's hiwater mark, VmHWM at exit)


def run_measured(
    args: Sequence[str],
    *,
    env: dict[str, str] | None = None,
    timeout: float = 120,
    cwd: Path = ROOT,
) -> Finished:
    """Run a child to its end and return its output and peak memory.

    The peak is the child's VmHWM, taken from the kernel when the child is reaped (wait4's
    ru_maxrss, the same counter /proc/PID/status shows as VmHWM while it runs). A child still
    running after ``timeout`` is killed and fails the test.
    """
    with tempfile.TemporaryFile("w+") as out, tempfile.TemporaryFile("w+") as err:
        proc = subprocess.Popen(list(args), stdout=out, stderr=err, text=True, cwd=cwd, env=env)
        timer = threading.Timer(timeout, proc.kill)
        timer.start()
        try:
            _, status, usage = os.wait4(proc.pid, 0)
        finally:
            timer.cancel()
        proc.returncode = os.waitstatus_to_exitcode(status)
        out.seek(0)
        err.seek(0)
        text_out, text_err = out.read(), err.read()
    assert proc.returncode != -signal.SIGKILL, f"still running after {timeout} s: {text_err}"
    return Finished(proc.returncode, text_out, text_err, usage.ru_maxrss / 1024)


def depthnav_measured(*argv: str, env: dict[str, str] | None = None) -> Finished:
    """The CLI in a child, with its peak memory."""
    return run_measured([sys.executable, "-m", "depthnav_daemon", *argv], env=env)


INJECT = Path(__file__).with_name("inject")


def signal_at_import(module: str, sig: int, *, in_callback: bool = False) -> dict[str, str]:
    """Environment for a child that sends itself ``sig`` while it imports ``module``.

    tests/faults/inject/sitecustomize.py does it from an import hook, so the signal lands at a
    known point of start-up every run; with ``in_callback`` it comes from inside a weakref
    callback run by the import, where an exception is printed as 'Exception ignored' and lost
    (as in importlib's own module-lock callback).
    """
    return {
        **os.environ,
        "PYTHONPATH": os.pathsep.join([str(INJECT), str(ROOT)]),
        "DEPTHNAV_TEST_SIGNAL_AT": module,
        "DEPTHNAV_TEST_SIGNAL": str(int(sig)),
        "DEPTHNAV_TEST_SIGNAL_IN_CALLBACK": "1" if in_callback else "",
    }


# --- a disk that fills ------------------------------------------------------------------------
@contextlib.contextmanager
def small_disk(tmp_path: Path, size: str) -> Iterator[tuple[Path, Callable[[], None] | None]]:
    """A tmpfs of ``size`` (e.g. "1m"), or, where mounting is not allowed, a file-size limit.

    Yields (folder, preexec_fn for the child): with the fallback, writes past the limit fail
    with EFBIG (SIGXFSZ ignored) the way a full disk fails with ENOSPC.
    """
    folder = tmp_path / "disk"
    folder.mkdir()
    mounted = (
        subprocess.run(
            ["mount", "-t", "tmpfs", "-o", f"size={size}", "tmpfs", str(folder)],
            capture_output=True,
            check=False,
        ).returncode
        == 0
    )
    if mounted:
        try:
            yield folder, None
        finally:
            subprocess.run(["umount", "-l", str(folder)], capture_output=True, check=False)
        return
    limit = int(size[:-1]) * (1 << 20)

    def preexec() -> None:
        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
        resource.setrlimit(resource.RLIMIT_FSIZE, (limit, limit))

    yield folder, preexec
