"""Writing ``.rrd`` files for the rerun sink: the file is locked while written, a write that failed
is told in words, a file cut short by a full disk is trimmed back to its last whole message (so
everything written before stays readable), and rerun's disconnect is waited for with a bound."""

from __future__ import annotations

import fcntl
import logging
import os
import shutil
import struct
import threading
from typing import Any

from depthnav_daemon.errors import SinkError

log = logging.getLogger(__name__)

RRD_MAGIC = b"RRF2"
RRD_FILE_HEADER = 12  # magic, version, options
RRD_MESSAGE_HEADER = struct.Struct("<QQ")  # message kind, payload length
MAX_MESSAGE_KIND = 255  # a larger "kind" is not a message header
LOW_SPACE_BYTES = 1 << 20


def lock_rrd(path: str) -> int:
    """Open the .rrd and hold an exclusive lock on it while the sink writes it: a second daemon
    given the same file is refused instead of both claiming frames the file lost.

    Returns:
        The open descriptor holding the lock (closing it releases the lock).

    Raises:
        SinkError: the file cannot be written, or another process is writing it.
    """
    try:  # fail with a plain message before rerun does (it also warns about lost data)
        fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_CLOEXEC, 0o644)
    except OSError as exc:
        raise SinkError(f"rerun sink: cannot write {path!r}: {exc.strerror}") from exc
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError:
        os.close(fd)
        raise SinkError(
            f"rerun sink: another process is writing {path!r}",
            hint="give each depthnav its own .rrd file",
        ) from None
    return fd


def file_problem(path: str, exc: BaseException) -> str:
    """Why writing the .rrd failed, in words: a full disk is the usual cause."""
    try:
        if shutil.disk_usage(os.path.dirname(os.path.abspath(path))).free < LOW_SPACE_BYTES:
            return "no space left on the disk"
    except OSError:
        pass
    return str(exc).splitlines()[0] if str(exc) else type(exc).__name__


def trim_partial_message(path: str) -> int | None:
    """Cut an ``.rrd`` whose writing stopped mid-message (disk full) back to its last whole message.

    rerun's reader refuses a file whose last message is cut short, which would make every frame
    written before the disk filled unreadable. The result has no footer, which rerun reads
    (``RrdReader.stream()``, the viewer). Nothing is changed unless the file walks cleanly.

    Returns:
        The new size in bytes, or None when the file was left as it was.
    """
    try:
        with open(path, "r+b") as fh:
            size = os.fstat(fh.fileno()).st_size
            if fh.read(4) != RRD_MAGIC:
                return None
            pos = RRD_FILE_HEADER
            while pos + RRD_MESSAGE_HEADER.size <= size:
                fh.seek(pos)
                kind, length = RRD_MESSAGE_HEADER.unpack(fh.read(RRD_MESSAGE_HEADER.size))
                if (
                    kind > MAX_MESSAGE_KIND
                ):  # not a message header: an unknown layout, leave the file alone
                    return None
                if pos + RRD_MESSAGE_HEADER.size + length > size:
                    break
                pos += RRD_MESSAGE_HEADER.size + length
            if pos == size:
                return None
            fh.truncate(pos)
            return pos
    except OSError as exc:
        log.warning("rerun sink: could not trim %s: %s", path, exc.strerror or exc)
        return None


def disconnect(rec: Any, what: str, wait_s: float | None) -> bool:
    """``rec.disconnect()`` (which writes a file's footer), waited for at most ``wait_s`` (None:
    until it returns); whether it returned (rerun.DISCONNECT_S says why)."""

    def run() -> None:
        try:
            rec.disconnect()
        except Exception as exc:
            log.warning("rerun sink: disconnecting %s failed: %s", what, exc)
            log.debug("disconnect failure", exc_info=True)

    thread = threading.Thread(target=run, name=f"rerun disconnect {what}", daemon=True)
    thread.start()
    thread.join(wait_s)
    return not thread.is_alive()
