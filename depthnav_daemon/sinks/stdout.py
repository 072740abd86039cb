"""``stdout``: one JSON object per frame per line on standard output (docs/json_schema.md).

Spec: ``stdout`` (no target, no options). Each line is flushed as soon as it is written so a
consumer (or journald) sees every frame at once. A consumer that stops reading (stalled, not
closed) must not freeze the frame loop and with it every other output: lines are written by a
writer thread, ``write()`` waits for each at most STALL_S, and while one is still stuck the next
ones are skipped (counted, logged; the consumer sees the gap in ``seq``). When stdout is a regular
file and the disk fills in the middle of a line, the part written is cut off again (the file ends
with the last whole line; nothing else wrote to it since). Logs must go to stderr:
``open()`` refuses to run when a logging handler writes to stdout, since that would corrupt the
stream. A closed reader (``depthnav run ... | head -1``) ends the sink with a SinkError rather than
a traceback.
"""

from __future__ import annotations

import contextlib
import fcntl
import io
import logging
import os
import queue
import stat
import sys
import threading
import time
from typing import TYPE_CHECKING, TextIO

from depthnav_daemon.errors import ConfigError, SinkError
from depthnav_daemon.sinks import jsonmsg
from depthnav_daemon.sinks.base import RateLimitedLog, SinkContext, SinkSpec, check_options

if TYPE_CHECKING:
    from depthnav_daemon.pipeline import Result
    from drivers.base import Frame

log = logging.getLogger(__name__)

GRAMMAR = "stdout"
STALL_S = 1.0  # longest write() waits for a line to reach the pipe before going on without it

# The process's stdout is one pipe however many sinks write to it: when one sees its reader gone
# (and points fd 1 at /dev/null), every other one must stop too, or it writes to /dev/null
# forever (`depthnav run --sink stdout --sink text | head -1` never ended).
_SHARED = {"reader_gone": False, "users": 0}


class StdoutSink:
    """Writes one strict-JSON line per frame to stdout (or to ``stream``, for tests and embedding).

    Args:
        name: the spec, for messages.
        stream: a text stream to write to instead of ``sys.stdout`` (looked up at ``open()``).
    """

    def __init__(self, name: str = "stdout", stream: TextIO | None = None) -> None:
        self.name = name
        self._given_stream = stream
        self._stream: TextIO | None = None
        self._version = "unknown"
        self.lines = 0
        self._fd: int | None = None
        self._queue: queue.Queue[bytes | None] | None = None
        self._thread: threading.Thread | None = None
        self._done = threading.Event()
        self._done.set()
        self._error: BaseException | None = None
        self._skipped = RateLimitedLog(log)

    @classmethod
    def from_spec(cls, spec: SinkSpec) -> StdoutSink:
        """Build from a parsed spec (no I/O). Raises ConfigError for a target or any option."""
        check_options(spec, (), GRAMMAR)
        if spec.target:
            raise ConfigError(
                f"the stdout sink takes no target, got {spec.text!r}", hint=f"write {GRAMMAR}"
            )
        return cls(spec.text)

    def open(self, context: SinkContext) -> None:
        """Pick the stream and check that no log handler shares it."""
        stream = self._given_stream if self._given_stream is not None else sys.stdout
        if stream is None:
            raise SinkError(
                "stdout is closed",
                hint="run depthnav with a standard output, or drop --sink stdout",
            )
        for handler in _all_handlers():
            if isinstance(handler, logging.StreamHandler) and handler.stream is stream:
                raise SinkError(
                    "a log handler writes to stdout, which would corrupt the JSON lines",
                    hint="send logs to stderr (logging.StreamHandler(sys.stderr))",
                )
        self._stream = stream
        self._version = context.version
        if stream is sys.stdout:
            if _SHARED["users"]:
                log.warning(
                    "%s and another sink both write to stdout: their lines interleave "
                    "(a program reading JSON lines should get stdout to itself)",
                    self.name,
                )
            _SHARED["users"] += 1
            self._counted = True
        try:
            fd = stream.fileno()
        except (AttributeError, OSError, ValueError, io.UnsupportedOperation):
            return  # an in-memory stream: written directly, it cannot stall
        stream.flush()  # what was printed before goes first; from now on the thread writes the fd
        self._fd = fd
        self._queue = queue.Queue(maxsize=1)
        # the thread gets the queue and fd it serves: a close() right after open() (a stop
        # signal at once) may clear the attributes before the thread has run a line
        self._thread = threading.Thread(
            target=self._writer, args=(self._queue, fd), name=f"sink {self.name}", daemon=True
        )
        self._thread.start()

    def _writer(self, lines: queue.Queue[bytes | None], fd: int) -> None:
        """Write whole lines to the fd; a stalled reader blocks this thread, not the frame loop."""
        regular = _is_regular(fd)
        while True:
            data = lines.get()
            if data is None:
                return
            start = _end_of(fd) if regular else None
            written = 0
            try:
                view = memoryview(data)
                while view:
                    n = os.write(fd, view)
                    written += n
                    view = view[n:]
            except BaseException as exc:
                self._error = exc
                if written and start is not None:
                    _cut_back(fd, start, written)
            self._done.set()

    def write(self, frame: Frame, result: Result) -> None:
        """Write and flush one line.

        Raises:
            SinkError: the reader went away (broken pipe) or the stream failed.
        """
        if self._stream is None:
            raise SinkError(f"sink {self.name!r} is not open")
        if self._stream is sys.stdout and _SHARED["reader_gone"]:
            self._stop_thread()
            self._stream = None
            raise SinkError(
                "stdout was closed by the reader (broken pipe)",
                hint="keep the consumer of depthnav's stdout running, or drop the stdout sinks",
            )
        line = self.format(frame, result)
        if line is None:
            return
        if self._queue is not None:
            self._write_threaded(line)
            return
        try:
            print(line, file=self._stream, flush=True)
        except BrokenPipeError:
            self._detach_broken_stdout()
            raise SinkError(
                "stdout was closed by the reader (broken pipe)",
                hint="keep the consumer of depthnav's stdout running, or drop --sink stdout",
            ) from None
        except (OSError, ValueError) as exc:  # ValueError: write to a closed file object
            self._stream = None
            raise SinkError(f"writing to stdout failed: {exc}") from exc
        self.lines += 1

    def _write_threaded(self, line: str) -> None:
        assert self._queue is not None
        if not self._done.is_set():  # the last line is still stuck in a pipe nobody reads
            self._skipped.failed("stdout sink: the reader is not reading (stalled?); lines skipped")
            return
        self._raise_error()
        self._done.clear()
        self._queue.put_nowait((line + "\n").encode("utf-8"))
        if self._done.wait(STALL_S):
            self._raise_error()
            self.lines += 1

    def _raise_error(self) -> None:
        exc, self._error = self._error, None
        if exc is None:
            return
        if isinstance(exc, BrokenPipeError):
            self._stop_thread()
            self._detach_broken_stdout()
            raise SinkError(
                "stdout was closed by the reader (broken pipe)",
                hint="keep the consumer of depthnav's stdout running, or drop --sink stdout",
            ) from None
        self._stop_thread()
        self._stream = None
        raise SinkError(f"writing to stdout failed: {exc}") from exc

    def _stop_thread(self) -> None:
        """Let the writer thread end (it is a daemon thread: one stuck in a write is left)."""
        q, self._queue = self._queue, None
        if q is not None and self._done.is_set():
            q.put_nowait(None)

    def format(self, frame: Frame, result: Result) -> str | None:
        """The line to write for one frame (None: write nothing for it)."""
        return jsonmsg.dumps(jsonmsg.frame_message(frame, result, self._version, time.time()))

    def close(self) -> None:
        """Flush what is buffered. Safe to call twice; a broken pipe at this point is ignored."""
        if getattr(self, "_counted", False):
            self._counted = False
            _SHARED["users"] -= 1
        stream, self._stream = self._stream, None
        if stream is None:
            return
        if self._queue is not None:
            if self._done.wait(STALL_S):  # the last line gets its chance; a stalled reader not
                with contextlib.suppress(SinkError):
                    self._raise_error()
            self._stop_thread()
            if self._skipped.count:
                log.warning(
                    "stdout sink: %d lines skipped while the reader was not reading",
                    self._skipped.count,
                )
            return
        try:
            stream.flush()
        except BrokenPipeError:
            self._detach_broken_stdout(stream)
        except (OSError, ValueError):
            log.debug("flushing stdout at close failed", exc_info=True)

    def _detach_broken_stdout(self, stream: TextIO | None = None) -> None:
        """After a broken pipe, point fd 1 at /dev/null so Python's exit-time flush cannot raise."""
        stream = stream or self._stream
        self._stream = None
        if stream is sys.stdout:
            _SHARED["reader_gone"] = True  # every sink sharing stdout stops (see _SHARED)
            # the Python docs' recipe (signal module, "Note on SIGPIPE")
            try:
                devnull = os.open(os.devnull, os.O_WRONLY)
                os.dup2(devnull, sys.stdout.fileno())
                os.close(devnull)
            except (OSError, ValueError):
                log.debug("could not redirect stdout to /dev/null", exc_info=True)


def _is_regular(fd: int) -> bool:
    try:
        return stat.S_ISREG(os.fstat(fd).st_mode)
    except OSError:
        return False


def _end_of(fd: int) -> int | None:
    """Where the next write to a regular file lands: its end (O_APPEND) or the fd's offset."""
    try:
        if fcntl.fcntl(fd, fcntl.F_GETFL) & os.O_APPEND:
            return os.fstat(fd).st_size
        return os.lseek(fd, 0, os.SEEK_CUR)
    except OSError:
        return None


def _cut_back(fd: int, start: int, written: int) -> None:
    """Remove the part of a line a full disk cut short, so the file ends with a whole line.

    Only when the file ends exactly where that part does (nobody else wrote to it since)."""
    try:
        if os.fstat(fd).st_size == start + written:
            os.ftruncate(fd, start)
            if not fcntl.fcntl(fd, fcntl.F_GETFL) & os.O_APPEND:
                os.lseek(fd, start, os.SEEK_SET)
    except OSError:
        log.debug("could not remove a half-written line from stdout", exc_info=True)


def _all_handlers() -> list[logging.Handler]:
    """Every handler attached to the root logger or any existing logger."""
    handlers = list(logging.getLogger().handlers)
    for logger in logging.Logger.manager.loggerDict.values():
        if isinstance(logger, logging.Logger):
            handlers.extend(logger.handlers)
    return handlers
