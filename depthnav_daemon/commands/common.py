"""What several subcommands share: exit codes, stop handlers, config from the arguments, a
progress bar, the figure outputs' guarded path and bounded usage errors. Light on purpose:
commands import numpy and the stages only after their stop handlers are installed.
"""

from __future__ import annotations

import argparse
import logging
import os
import signal
import stat
import sys
import threading
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Any

from depthnav_daemon.errors import ConfigError, DepthnavError

if TYPE_CHECKING:
    from matplotlib.figure import Figure

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


def _usage(option: str) -> Callable[..., Exception]:
    """drivers.files' error factory for a figure path that is a usage error (exit 2)."""
    return lambda message, hint=None: ConfigError(f"{option} {message}", hint=hint)


def figure_output(path: str | os.PathLike[str], option: str) -> tuple[Path, str]:
    """Where a figure goes and its format (``plots.check_output``), after the guarded path's own
    checks: a name over NAME_MAX bytes or a path over PATH_MAX, and an existing FIFO, device or
    socket (writing would block or go nowhere) are refused by name before any work.

    Raises:
        ConfigError: as above, or check_output's (extension, folder, directory).
        DepthnavError: matplotlib is not installed.
    """
    from depthnav_daemon.plots import check_output
    from drivers import files  # here: the drivers package imports numpy

    text = files.check_path_length(path, _usage(option))
    try:
        mode: int | None = os.stat(text).st_mode
    except (OSError, ValueError):  # missing (a new file) or unreadable: check_output says
        mode = None
    if mode is not None and not (stat.S_ISREG(mode) or stat.S_ISDIR(mode)):
        files.open_output(text, what="figure", error=_usage(option))  # says what it is
    return check_output(text, option)


def save_figure(fig: Figure, path: str | os.PathLike[str], option: str) -> Path:
    """Write ``fig`` to ``path`` (PNG or SVG by extension) through the guarded path
    (``drivers.files.open_output``: a regular or new file, opened without blocking); a
    half-written file is removed.

    Raises:
        ConfigError: see figure_output.
        DepthnavError: it cannot be written (a read-only place, a full disk, a FIFO or device
            swapped in after the check).
    """
    from depthnav_daemon.plots import render
    from drivers import files

    p, fmt = figure_output(path, option)
    data = render(fig, fmt)

    def failed(message: str, hint: str | None = None) -> DepthnavError:
        return DepthnavError(
            f"cannot write {option} {message}", hint=hint or "choose a writable place"
        )

    with files.open_output(p, what="figure", error=failed) as fh:
        try:
            fh.write(data)
            fh.flush()
        except OSError as exc:
            _remove(p)
            raise DepthnavError(
                f"cannot write {option} {str(p)!r}: {exc.strerror or type(exc).__name__}",
                hint="choose a writable place with free space",
            ) from None
    return p


def _remove(p: Path) -> None:
    """Remove a half-written figure (best effort)."""
    try:
        os.unlink(p)
    except OSError:
        pass


def bound_message(message: str, limit: int = 300) -> str:
    """A usage error as argparse words it (cli's parser shows it through here), bounded: each
    quoted value ('...') as ``short_repr`` shows it (cut to about 60 characters, escaped; argparse
    echoed a 5000-digit --frame in full), control characters escaped elsewhere, on one line of
    at most about ``limit`` characters."""
    from drivers.values import short_repr  # here: the drivers package imports numpy

    parts = message.split("'")
    text = "".join(
        short_repr(part) if i % 2 and i < len(parts) - 1 else part for i, part in enumerate(parts)
    )
    text = "".join(c if c.isprintable() else repr(c)[1:-1] for c in text)
    return text if len(text) <= limit + 3 else text[:limit] + "..."
