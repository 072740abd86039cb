"""The compiled kernels' cache, made ready before the first frame so that start-up never compiles
in the daemon's own process (docs/startup.md).

numba compiles a kernel the first time it meets an argument type, holding the interpreter for
seconds at a time; a SIGTERM then waited for the whole compile (~90 s measured, issue 33). So
when the cache is cold the daemon runs ``depthnav warmup`` in a child process that fills it
(``tools/warmup.py`` runs every kernel with every kind of array the stages pass), waits for it
without holding anything (a stop kills the child at once) and tells systemd it is still starting
(``EXTEND_TIMEOUT_USEC``). A cache is warm when the warm-up finished into it for this depthnav,
Python, numba, CPU and these kernel sources: it leaves ``depthnav-warm.json`` saying so, last.
"""

from __future__ import annotations

import json
import logging
import os
import re
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import IO, Any

from depthnav_daemon import __version__
from depthnav_daemon.daemon.notify import ServiceNotifier
from depthnav_daemon.errors import DepthnavError

log = logging.getLogger(__name__)

MARKER = "depthnav-warm.json"
PIPELINE = Path(__file__).resolve().parents[1] / "pipeline"  # where every kernel is defined
# the whole warm-up with an empty cache: 94 s on 2 idle cores (docs/startup.md); a Raspberry Pi
# 4 is some 3x slower, so systemd is asked to wait up to this long, no more
COMPILE_BUDGET_S = 1200.0
POLL_S = 0.1  # how often the wait for the child looks at the stop flag
# the child's log lines, and the CLI's own "error:" / "hint:" lines when it fails
_LINE = re.compile(
    r"depthnav: (DEBUG|INFO|WARNING|ERROR|CRITICAL|error|internal error|hint): (.*)$"
)
_PROGRESS = re.compile(r"compiling kernels: (\d+)/(\d+)")


def cache_dir() -> Path:
    """The folder numba caches the kernels in: ``NUMBA_CACHE_DIR``, else
    ``$XDG_CACHE_HOME/depthnav/numba`` (``~/.cache``): what pipeline/_jit.py sets, computed
    without importing numba or the stages (a test keeps the two equal)."""
    given = os.environ.get("NUMBA_CACHE_DIR")
    if given:
        return Path(given)
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(base) / "depthnav" / "numba"


def check_writable(folder: Path) -> None:
    """Make sure numba can write ``folder`` (it creates it); a folder it cannot write makes
    every kernel import fail with "no locator available", so say it in one line instead.

    Raises:
        DepthnavError: the folder cannot be created or written.
    """
    try:
        folder.mkdir(parents=True, exist_ok=True)
        tempfile.TemporaryFile(dir=folder).close()
    except OSError as exc:
        raise DepthnavError(
            f"cannot write the kernel cache {folder}: {exc.strerror or exc}",
            hint=f"give it to this user (sudo chown -R {_user()} {folder}), or run "
            f"sudo depthnav warmup --cache-dir {folder} --owner {_user()}",
        ) from exc


def _user() -> str:
    import pwd

    try:
        return pwd.getpwuid(os.getuid()).pw_name
    except KeyError:
        return str(os.getuid())


def fingerprint() -> dict[str, Any]:
    """What the cached machine code depends on: versions, the CPU numba compiles for (its own
    key, with NUMBA_CPU_NAME honoured) and every kernel source's size and time."""
    import numba
    import numpy
    from numba.core.registry import cpu_target

    sources = [
        [p.name, p.stat().st_mtime_ns, p.stat().st_size] for p in sorted(PIPELINE.glob("*.py"))
    ]
    return {
        "depthnav": __version__,
        "python": sys.version,
        "numba": numba.__version__,
        "numpy": numpy.__version__,
        "cpu": list(cpu_target.target_context.codegen().magic_tuple()),
        "sources": sources,
    }


def is_warm(folder: Path | None = None) -> bool:
    """True when the warm-up finished into ``folder`` (default: cache_dir()) for this machine
    and these sources."""
    marker = (folder or cache_dir()) / MARKER
    try:
        return bool(json.loads(marker.read_text()) == fingerprint())
    except (OSError, ValueError):
        return False


def mark_warm(folder: Path | None = None) -> Path:
    """Record that the warm-up finished into ``folder`` (written whole, or not at all)."""
    marker = (folder or cache_dir()) / MARKER
    tmp = marker.with_suffix(f".tmp.{os.getpid()}")
    tmp.write_text(json.dumps(fingerprint()))
    os.replace(tmp, marker)
    return marker


def warm_kernels(stop: threading.Event, notifier: ServiceNotifier) -> bool:
    """Fill a cold kernel cache in a child process (``depthnav warmup``) before the first frame.

    Says so (a warning: it is the first run only), relays the child's progress to the log and
    to systemd (STATUS, EXTEND_TIMEOUT_USEC), and kills the child when ``stop`` is set.

    Returns:
        False when stopped meanwhile; True otherwise (a warm cache, a finished warm-up, or a
        failed one: said, and the kernels then compile at the first frame as before).
    """
    if stop.is_set():
        return False
    folder = cache_dir()
    if is_warm(folder):
        return True
    log.warning(
        "compiling kernels into %s (first run only, about 1.5 min on 2 cores; "
        "depthnav warmup does it ahead, scripts/install.sh too)",
        folder,
    )
    notifier.starting("compiling kernels (first run only)", COMPILE_BUDGET_S)
    t0 = time.monotonic()
    child = subprocess.Popen(
        [sys.executable, "-m", "depthnav_daemon", "warmup"],  # into NUMBA_CACHE_DIR, below
        stdin=subprocess.DEVNULL,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
        text=True,
        env=_child_env(folder),
    )
    last: list[str] = []
    relay = threading.Thread(
        target=_relay, args=(child.stderr, notifier, last), name="warm-up log", daemon=True
    )
    relay.start()
    try:
        while child.poll() is None:
            if stop.wait(POLL_S):
                log.info("stopping: kernel warm-up interrupted (the next start goes on with it)")
                return False
    finally:
        if child.poll() is None:
            child.kill()
            child.wait()
        relay.join(timeout=1.0)
    if stop.is_set():  # Ctrl-C reaches the child too, which may end first
        return False
    if child.returncode != 0:
        log.warning(
            "kernel warm-up failed (exit %d%s); the kernels compile at the first frame instead",
            child.returncode,
            f": {last[-1]}" if last else "",
        )
        return True
    log.info("kernels compiled in %.1f s", time.monotonic() - t0)
    return True


def _child_env(folder: Path) -> dict[str, str]:
    """The warm-up's environment: ours, with the cache named, and nothing of systemd's (the
    service's notify socket and watchdog are the daemon's alone)."""
    env = {k: v for k, v in os.environ.items() if not k.startswith(("NOTIFY_", "WATCHDOG_"))}
    env["NUMBA_CACHE_DIR"] = str(folder)
    return env


def _relay(stream: IO[str] | None, notifier: ServiceNotifier, last: list[str]) -> None:
    """The child's log lines into ours (``warm-up: ...`` at their own level), its progress into
    systemd's STATUS."""
    if stream is None:
        return
    for line in stream:
        m = _LINE.search(line.rstrip("\n"))
        if m is None:
            continue  # nothing else is expected; a traceback's lines are not for the journal
        level, text = m.groups()
        if level.islower():  # the CLI's lines: what went wrong, said as a warning here
            level, text = "WARNING", f"{level}: {text}"
        last[:] = [text]
        progress = _PROGRESS.search(text)
        if progress:
            notifier.status(f"compiling kernels {progress[1]}/{progress[2]} (first run only)")
        log.log(logging.getLevelName(level), "warm-up: %s", text)
