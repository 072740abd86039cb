"""``stdout``: one JSON object per frame per line on standard output (docs/json_schema.md).

Spec: ``stdout`` (no target, no options). Each line goes to the fd as soon as it is made so a
consumer (or journald) sees every frame at once. A consumer that stops reading (stalled, not
closed) must not freeze the frame loop and with it every other output:

- a regular file or a device such as /dev/null cannot stall: ``write()`` writes it itself;
- a pipe with room for the line (asked with FIONREAD) while the writer thread is idle: also
  written by ``write()``, as such a write cannot block (no thread switch per line);
- otherwise (a full pipe, a socket, a terminal) the line goes to a queue of QUEUE_LINES that a
  writer thread empties, the lines waiting when it comes round in one write. ``write()`` waits
  for the first line (a reader already gone is reported at once), and for room in a full queue at
  most STALL_S; after that, lines are skipped while the queue stays full (counted, logged; the
  consumer sees the gap in ``seq``). ``close()`` writes every queued line while the reader reads.

When stdout is a regular file and the disk fills in the middle of a line, the part written is cut
off again (the file ends with the last whole line; nothing else wrote to it since). Logs must go
to stderr: ``open()`` refuses to run when a logging handler writes to stdout, since that would
corrupt the stream. A closed reader (``depthnav run ... | head -1``) ends the sink with a
SinkError rather than a traceback.
"""

from __future__ import annotations

import array
import contextlib
import fcntl
import io
import logging
import os
import queue
import stat
import sys
import termios
import threading
import time
import weakref
from typing import TYPE_CHECKING, TextIO

from depthnav_daemon.errors import ConfigError, SinkError
from depthnav_daemon.sinks.base import RateLimitedLog, SinkContext, SinkSpec, check_options
from depthnav_daemon.sinks.json import line as json_line

if TYPE_CHECKING:
    from depthnav_daemon.pipeline import Result
    from drivers.base import Frame

log = logging.getLogger(__name__)

GRAMMAR = "stdout"
STALL_S = 1.0  # longest write() waits for room in the queue before going on without its line
QUEUE_LINES = 8  # lines waiting for the writer thread (~100 KB); a pipe holds ~5 more
PAGE_BYTES = 4096
STALLED = "stdout sink: the reader is not reading (stalled?); lines skipped"

# The process's stdout is one pipe however many sinks write to it: when one sees its reader gone
# (and points fd 1 at /dev/null), every other one must stop too, or it writes to /dev/null
# forever (`depthnav run --sink stdout --sink text | head -1` never ended).
_SHARED = {"reader_gone": False, "users": 0}
# Sinks writing to one pipe or terminal (stdout and text both on fd 1) take turns, a write each:
# a pipe write over 4 KiB is not atomic (a JSON line is ~12 kB), so two writer threads writing at
# once cut each other's lines (seen in the soak on a loaded machine). One lock per open file,
# kept while a sink (or its writer thread) uses it.


class _FileLock:
    """The write lock of one open file (weakly listed: a later file on the same inode gets its
    own)."""

    __slots__ = ("__weakref__", "lock")

    def __init__(self) -> None:
        self.lock = threading.Lock()


_FILE_LOCKS: weakref.WeakValueDictionary[tuple[int, int], _FileLock] = weakref.WeakValueDictionary()
_FILE_LOCKS_LOCK = threading.Lock()


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
        self._direct = False  # the fd never waits (a file, /dev/null): written in write()
        self._regular = False
        self._queue: queue.Queue[bytes | None] | None = None
        self._thread: threading.Thread | None = None
        self._first = threading.Event()  # the writer thread has written (or failed) a batch
        self._stalled = False  # the queue stayed full for STALL_S: lines are being skipped
        self._handed = 0  # lines queued for the writer thread
        self._served = 0  # of those, the ones it has written (all: it is idle)
        self._pipe_size = 0  # stdout is a pipe of this many bytes (0: a socket, a terminal)
        self._error: BaseException | None = None
        self._skipped = RateLimitedLog(log)
        self._file_lock = _FileLock()  # its own until open() finds the file's (see _FILE_LOCKS)
        # the JSON line (this class's format), not a subclass's: checked once, not per frame
        self._json = type(self).format is StdoutSink.format

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
        stream.flush()  # what was printed before goes first; from now on the fd is written
        self._fd = fd
        self._file_lock = _lock_of(fd)
        if _never_waits(fd):
            # a file or /dev/null: no reader can stall it, so the frame loop writes it itself
            # (no thread hand-off per line; an error shows on the line that met it)
            self._direct = True
            self._regular = _is_regular(fd)
            return
        self._queue = queue.Queue(maxsize=QUEUE_LINES)
        # the thread gets the queue and fd it serves: a close() right after open() (a stop
        # signal at once) may clear the attributes before the thread has run a line
        self._thread = threading.Thread(
            target=self._writer,
            args=(self._queue, fd, self._file_lock),
            name=f"sink {self.name}",
            daemon=True,
        )
        self._thread.start()
        if stat.S_ISFIFO(os.fstat(fd).st_mode):
            with contextlib.suppress(OSError):
                self._pipe_size = fcntl.fcntl(fd, fcntl.F_GETPIPE_SZ)

    def _writer(self, lines: queue.Queue[bytes | None], fd: int, lock: _FileLock) -> None:
        """Write the queued lines to the fd, those waiting together in one write (taking turns
        with the other sinks on the same file); a stalled reader blocks this thread, not the frame
        loop. Ends at None or at the first error."""
        regular = _is_regular(fd)
        while True:
            data = lines.get()
            if data is None:
                return
            batch, last = [data], False
            while len(batch) < QUEUE_LINES:
                try:
                    more = lines.get_nowait()
                except queue.Empty:
                    break
                if more is None:
                    last = True
                    break
                batch.append(more)
            try:
                with lock.lock:
                    _write_whole_lines(fd, b"".join(batch), regular)
            except BaseException as exc:
                self._error = exc
                self._first.set()
                return  # the frame loop raises it on its next write and drops the sink
            self.lines += len(batch)
            self._served += len(batch)
            self._first.set()
            if last:
                return

    def write(self, frame: Frame, result: Result) -> None:
        """Write one line (flushed: a reader sees it at once).

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
        data = (
            # the frame's JSON is made once and shared with the udp sink (json_line.frame_line)
            json_line.frame_line(frame, result, self._version, time.time())
            if self._json
            else self._line(frame, result)
        )
        if data is None:
            return
        if self._direct:
            assert self._fd is not None
            try:
                with self._file_lock.lock:  # a file or device: never waits, so held briefly
                    _write_whole_lines(self._fd, data, self._regular)
            except OSError as exc:
                self._error = exc
                self._raise_error()
            self.lines += 1
            return
        if self._queue is not None:
            self._write_threaded(data)
            return
        try:
            print(data.decode("utf-8"), end="", file=self._stream, flush=True)
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

    def _write_threaded(self, data: bytes) -> None:
        """Queue the line for the writer thread. The first line is waited for (a reader that is
        already gone is reported at once); later ones wait only when QUEUE_LINES are queued."""
        assert self._queue is not None and self._fd is not None
        self._raise_error()
        if (
            self._served == self._handed
            and len(data) <= self._pipe_room()
            and self._file_lock.lock.acquire(blocking=False)
        ):
            # the writer thread is idle, the pipe has room and no other sink is writing to it:
            # this write cannot block, so the frame loop makes it (waking the thread costs the
            # loop a thread switch a line); the lock taken, else another sink's writer thread,
            # perhaps stuck on a full pipe, holds it: then the line goes to the queue
            try:
                _write_whole_lines(self._fd, data, False)
            except OSError as exc:
                self._error = exc
                self._raise_error()
            finally:
                self._file_lock.lock.release()
            self._stalled = False
            self.lines += 1
            return
        self._handed += 1
        try:
            self._queue.put_nowait(data)
        except queue.Full:
            if self._stalled:  # still stuck: skip without waiting again
                self._handed -= 1
                self._skipped.failed(STALLED)
                return
            try:
                self._queue.put(data, timeout=STALL_S)
            except queue.Full:
                self._handed -= 1
                self._stalled = True
                self._skipped.failed(STALLED)
                return
        self._stalled = False
        if not self._first.is_set() and self._first.wait(STALL_S):
            self._raise_error()

    def _pipe_room(self) -> int:
        """Bytes a write to the pipe takes without blocking (a lower bound); 0 for a socket or
        terminal, or when it cannot be told."""
        if not self._pipe_size:
            return 0
        unread = array.array("i", [0])
        try:
            fcntl.ioctl(self._fd, termios.FIONREAD, unread, True)
        except OSError:
            return 0
        # a pipe holds pages, and a write may leave the last one part empty (so lines of 3.1
        # pages take 4): unread bytes may use up to twice their pages, plus the page being read
        # and the one being filled; our write may need one page more than its bytes. Counting
        # the bytes only, a pipe made larger than 64 KiB (by the reader, before we start) took a
        # write it then blocked in, for good when the reader had stalled.
        pages = -(-unread[0] // PAGE_BYTES)
        return self._pipe_size - PAGE_BYTES * (2 * pages + 3)

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
        if q is not None:
            with contextlib.suppress(queue.Full):  # full: it is writing, and ends at its error
                q.put_nowait(None)

    def _line(self, frame: Frame, result: Result) -> bytes | None:
        """The bytes to write for one frame of a subclass's :meth:`format`, newline included
        (None: nothing for it)."""
        line = self.format(frame, result)
        return None if line is None else (line + "\n").encode("utf-8")

    def format(self, frame: Frame, result: Result) -> str | None:
        """The line to write for one frame (None: write nothing for it)."""
        return json_line.frame_json(frame, result, self._version, time.time()).decode()

    def close(self) -> None:
        """Write what is queued and stop. Safe to call twice; a broken pipe now is ignored."""
        if getattr(self, "_counted", False):
            self._counted = False
            _SHARED["users"] -= 1
        stream, self._stream = self._stream, None
        if stream is None:
            return
        if self._queue is not None:
            self._drain()
            with contextlib.suppress(SinkError):
                self._raise_error()
            self._stop_thread()
            if self._skipped.count:
                log.warning(
                    "stdout sink: %d lines skipped while the reader was not reading",
                    self._skipped.count,
                )
            return
        if self._direct:
            return  # nothing is buffered: every line went to the fd as it came
        try:
            stream.flush()
        except BrokenPipeError:
            self._detach_broken_stdout(stream)
        except (OSError, ValueError):
            log.debug("flushing stdout at close failed", exc_info=True)

    def _drain(self) -> None:
        """Let the writer thread write every queued line, waiting as long as the reader reads
        (no line is lost at shutdown), but at most STALL_S for one that has stopped reading."""
        q, thread = self._queue, self._thread
        if q is None or thread is None:
            return
        self._queue = None
        while thread.is_alive():
            before = self.lines
            try:
                q.put(None, timeout=STALL_S)
                break
            except queue.Full:
                if self.lines == before:
                    return  # the reader is stalled: the daemon thread is left in its write
        while thread.is_alive():
            before = self.lines
            thread.join(STALL_S)
            if self.lines == before:
                return

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


def _lock_of(fd: int) -> _FileLock:
    """The write lock of the file ``fd`` is open on (its device and inode: two fds, one pipe)."""
    try:
        st = os.fstat(fd)
        key = (st.st_dev, st.st_ino)
    except OSError:
        key = (-1, fd)
    with _FILE_LOCKS_LOCK:
        found = _FILE_LOCKS.get(key)
        if found is None:
            found = _FILE_LOCKS[key] = _FileLock()
        return found


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


def _never_waits(fd: int) -> bool:
    """Whether writing ``fd`` can never wait for a reader: a regular file, or a device that is
    not a terminal (/dev/null, /dev/full). Pipes, sockets and terminals can stall."""
    try:
        mode = os.fstat(fd).st_mode
    except OSError:
        return False
    return stat.S_ISREG(mode) or (stat.S_ISCHR(mode) and not os.isatty(fd))


def _write_whole_lines(fd: int, data: bytes, regular: bool) -> None:
    """Write ``data`` (whole lines) to ``fd``. When a regular file fills up in the middle, the
    part of a line that made it is cut off again, so the file ends with a whole line.

    Raises:
        OSError (BrokenPipeError, ENOSPC, ...): what the write met.
    """
    start = _end_of(fd) if regular else None
    written = 0
    try:
        view = memoryview(data)
        while view:
            n = os.write(fd, view)
            written += n
            view = view[n:]
    except BaseException:
        if written and start is not None:
            _cut_back(fd, start, written, data.rfind(b"\n", 0, written) + 1)
        raise


def _cut_back(fd: int, start: int, written: int, whole: int) -> None:
    """Remove the part of a line a full disk cut short: keep the ``whole`` bytes of the
    ``written`` ones that end with a newline.

    Only when the file ends exactly where the write did (nobody else wrote to it since)."""
    try:
        if whole < written and os.fstat(fd).st_size == start + written:
            os.ftruncate(fd, start + whole)
            if not fcntl.fcntl(fd, fcntl.F_GETFL) & os.O_APPEND:
                os.lseek(fd, start + whole, os.SEEK_SET)
    except OSError:
        log.debug("could not remove a half-written line from stdout", exc_info=True)


def _all_handlers() -> list[logging.Handler]:
    """Every handler attached to the root logger or any existing logger."""
    handlers = list(logging.getLogger().handlers)
    for logger in logging.Logger.manager.loggerDict.values():
        if isinstance(logger, logging.Logger):
            handlers.extend(logger.handlers)
    return handlers
