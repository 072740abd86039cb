"""The CLI's standard streams: fds closed at start, log lines on stderr, lines that never fail.

Standard library only: the ``depthnav`` console script imports this (through cli.py) before
the start-up stop handlers are in place.
"""

from __future__ import annotations

import logging
import os
import sys

__all__ = ["configure_logging", "guard_standard_fds", "say"]


def guard_standard_fds() -> None:
    """Put /dev/null on fd 0, 1 or 2 when it was closed at start (``2>&-``).

    A closed fd is the lowest free one: the next file depthnav opened (an ``.rrd``, a bag, a
    socket) would become "stderr", and log lines or a native library's messages would be written
    into it. With stderr closed, ``sys.stderr`` is None (Python's doing) and the CLI's own lines
    went nowhere before failing: it now writes them to /dev/null and runs on. ``sys.stdout``
    stays None, so ``--sink stdout`` still says "stdout is closed".
    """
    for fd in (0, 1, 2):
        try:
            os.fstat(fd)
        except OSError:
            null = os.open(os.devnull, os.O_RDWR)  # the lowest free fd: this one
            if null != fd:
                os.dup2(null, fd)
                os.close(null)
    if sys.stderr is None:
        sys.stderr = open(2, "w", errors="backslashreplace", closefd=False)


def say(text: str) -> None:
    """Write to stderr, if there is one (a closed stderr is no reason to fail)."""
    try:
        sys.stderr.write(text)
    except (OSError, ValueError, AttributeError):
        pass


# syslog priorities (sd-daemon(3)): journald reads a "<N>" prefix as the line's priority
_PRIORITY = {logging.DEBUG: 7, logging.INFO: 6, logging.WARNING: 4, logging.ERROR: 3}


class _JournalFormatter(logging.Formatter):
    """``<priority>depthnav: LEVEL: message``: journald adds the time itself."""

    def format(self, record: logging.LogRecord) -> str:
        prio = _PRIORITY.get(record.levelno, 2 if record.levelno > logging.ERROR else 7)
        return f"<{prio}>{super().format(record)}"


def _stderr_is_journal() -> bool:
    """True when stderr is systemd's journal stream (JOURNAL_STREAM names its device:inode)."""
    want = os.environ.get("JOURNAL_STREAM", "")
    try:
        st = os.fstat(sys.stderr.fileno())
    except (OSError, ValueError, AttributeError):  # AttributeError: sys.stderr is None (2>&-)
        return False
    return bool(want) and want == f"{st.st_dev}:{st.st_ino}"


def _stderr_is_tty() -> bool:
    try:
        return bool(sys.stderr.isatty())
    except (OSError, ValueError, AttributeError):
        return False


def _log_formatter() -> logging.Formatter:
    """Plain lines at a terminal, journald priorities under systemd, timestamps elsewhere."""
    fmt = "depthnav: %(levelname)s: %(message)s"
    if _stderr_is_journal():
        return _JournalFormatter(fmt)
    if _stderr_is_tty():
        return logging.Formatter(fmt)
    return logging.Formatter("%(asctime)s.%(msecs)03d " + fmt, datefmt="%Y-%m-%dT%H:%M:%S")


def configure_logging(verbose: int, quiet: bool) -> None:
    """Log lines to stderr at the level the flags ask for (-v debug, -q warnings)."""
    level = logging.WARNING if quiet else (logging.DEBUG if verbose else logging.INFO)
    handler = logging.StreamHandler(sys.stderr)
    handler.setFormatter(_log_formatter())
    root = logging.getLogger()
    root.handlers[:] = [handler]
    root.setLevel(logging.WARNING)
    for name in ("depthnav_daemon", "drivers"):
        logging.getLogger(name).setLevel(level)
