"""What several subcommands share: exit codes, stop handlers, config from the arguments and a
progress bar. Light on purpose: commands import numpy and the stages only after their stop
handlers are installed.
"""

from __future__ import annotations

import argparse
import logging
import os
import signal
import sys
import threading
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

from depthnav_daemon.errors import ConfigError

if TYPE_CHECKING:
    from depthnav_daemon.config.loader import Config

log = logging.getLogger(__name__)

EXIT_OK, EXIT_FAIL, EXIT_USAGE, EXIT_INTERRUPTED = 0, 1, 2, 130
# measured with an empty NUMBA_CACHE_DIR on a 2-core machine: 10.6 s idle, 30 s at load average 5
FIRST_COMPILE_S = (20, 70)  # measured: 23.5 s idle, 67 s at load average 3-4 (README)


def overrides(args: argparse.Namespace, device: str | None = None) -> dict[str, Any]:
    """The config keys the dedicated flags set (they win over files and ``--set``)."""
    out: dict[str, Any] = {}
    mount = {
        k: v
        for k, v in (
            ("height_m", args.height_m),
            ("tilt_deg", args.tilt_deg),
            ("roll_deg", args.roll_deg),
        )
        if v is not None
    }
    if mount:
        out["mount"] = mount
        typed = (s.split("=", 1)[0].strip() for s in getattr(args, "set", []) or [])
        if "daemon.tilt_source" not in typed:
            # a mount the user typed wins: the accelerometer and the floor do not replace it
            out["daemon"] = {"tilt_source": "config"}
    if args.method:
        out["scan"] = {"method": args.method}
    if device:
        out["device"] = device
    if getattr(args, "sink", None):
        out["sinks"] = args.sink
    odometry = getattr(args, "odometry", None)
    if odometry is not None:
        if not odometry.strip():  # "" in a config file means none; typed, it is a mistake
            raise ConfigError(
                "--odometry needs a spec", hint="e.g. --odometry odom+udp://127.0.0.1:5700"
            )
        out["odometry"] = {"source": odometry}
    return out


def load_config(args: argparse.Namespace, device: str | None) -> Config:
    """The effective configuration: files, ``--set``, then the dedicated flags."""
    from depthnav_daemon.config.loader import build_config

    return build_config(args.config, args.set, overrides(args, device))


# SIGHUP (the terminal closed, a service manager) stops as cleanly as SIGTERM
STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)
_received: dict[str, int] = {}  # the first stop signal of this process, whoever caught it


def note_stop_signal(signum: int) -> None:
    """Remember that a stop signal came (the first one counts for the exit code)."""
    _received.setdefault("signal", signum)


def stop_signal_received() -> int | None:
    """The first stop signal this process got, or None."""
    return _received.get("signal")


def install_stop_handlers(stop: threading.Event) -> dict[str, int]:
    """SIGINT, SIGTERM and SIGHUP set ``stop``; returns a dict that records which signal came.

    Commands install these before their heavy imports (numpy, numba, the kernels): a
    KeyboardInterrupt raised inside an import ended the process with -SIGINT instead of 130 in
    ~1 of 30 runs signalled 0.1-0.3 s into start-up; a stop flag set during the imports is seen
    by the command as soon as they finish. A stop signal that came earlier, while the CLI was
    starting (cli.entry_point notes it), sets ``stop`` at once.
    """
    got: dict[str, int] = {}

    def handler(signum: int, _frame: object) -> None:
        note_stop_signal(signum)
        got["signal"] = signum
        stop.set()

    for sig in STOP_SIGNALS:
        signal.signal(sig, handler)
    early = stop_signal_received()
    if early is not None:
        got["signal"] = early
        stop.set()
    return got


def progress_bar(label: str, unit: str = "frames") -> Callable[[int, int], None]:
    """A one-line progress bar on stderr when it is a terminal; log lines otherwise.

    The log lines come at the first unit, at every quarter of ``total`` crossed and at the end,
    also for callers that skip values (compression reports every few MiB).
    """
    tty = sys.stderr.isatty()
    last = [0]

    def show(done: int, total: int) -> None:
        step = max(total // 4, 1)
        if tty:
            width = 30
            filled = int(width * done / max(total, 1))
            end = "\n" if done >= total else ""
            sys.stderr.write(
                f"\r{label} [{'#' * filled}{'.' * (width - filled)}] {done}/{total} {unit}{end}"
            )
            sys.stderr.flush()
        elif done in (1, total) or done // step > last[0] // step:  # the first: it started
            log.info("%s: %d/%d %s", label, done, total, unit)
        last[0] = done

    return show


def stopped_code(got: dict[str, int]) -> int:
    """The exit code of a command stopped by the signal in ``got``: 130 for SIGINT, else 0."""
    return EXIT_INTERRUPTED if got.get("signal") == signal.SIGINT else EXIT_OK


def mib(n_bytes: int) -> int:
    """Bytes in whole MiB, rounded up (so a finished count equals its total)."""
    return -(-n_bytes // (1 << 20))


def announce_compiles() -> None:
    """On a cold kernel cache, say "compiling kernels (first run only)" and show the progress.

    Call after the stage imports; with a warm cache (scripts/install.sh fills it) it says nothing.
    """
    from depthnav_daemon.tools.warmup import watch_compiles

    # a bar at a terminal; elsewhere a line per kernel (each takes seconds: show it moves)
    bar = progress_bar("compiling kernels", unit="kernels") if sys.stderr.isatty() else None

    def progress(done: int, total: int) -> None:
        if done == 0:
            log.warning(
                "compiling kernels (first run only, %d-%d s on 2 cores; later runs load them "
                "from %s)",
                *FIRST_COMPILE_S,
                os.environ.get("NUMBA_CACHE_DIR", "the cache"),
            )
        if bar is not None:
            bar(done, total)
        elif done:
            log.info("compiling kernels: %d/%d", done, total)

    watch_compiles(progress)
