"""The one way depthnav opens a file it reads (and a figure it writes, ``open_output``): a regular
file, size-checked, never blocking.

Every reader (recordings, PNG folders, fakenect folders, ``.oni`` files, config and parameter
files) opens its inputs here, so each refusal is one line and the same everywhere:

- only regular files are opened: a FIFO (``open()`` would block, and a signal could not end it),
  a device (``/dev/zero`` reads forever), a socket or a folder, directly or through a symlink, is
  refused from ``stat()`` before anything is opened, and the opened file is checked again
  (``fstat``) in case it was swapped in between; the open itself uses ``O_NONBLOCK``;
- a name longer than NAME_MAX bytes (or a path longer than PATH_MAX) is refused by name, not
  with ``OSError: [Errno 36]``;
- the size is checked before reading (``max_bytes``), and reading stops one byte past it in case
  the file grows;
- text must be UTF-8 (a UTF-8 byte-order mark is dropped); UTF-16 and other encodings are refused
  naming the byte and its offset;
- TOML nested deeper than Python's recursion allows, or holding an integer over Python's
  4300-digit limit, is refused as such (tomllib raises RecursionError and ValueError for them).

Errors are raised as ``error(message, hint=...)``: each caller passes its own type (drivers'
RecordingError, the daemon's ConfigError), so this module imports nothing of either layer.
"""

from __future__ import annotations

import codecs
import errno
import os
import stat
import tomllib
from collections.abc import Callable
from pathlib import Path
from typing import Any, BinaryIO

from drivers.errors import RecordingError
from drivers.values import short_repr, short_text

NAME_MAX = 255  # bytes of one path component (Linux)
PATH_MAX = 4095  # bytes of a whole path (Linux, without the NUL)
TEXT_MAX_BYTES = 1 << 20  # config files, recording.toml, camera.toml, parameter files
INDEX_MAX_BYTES = 64 << 20  # depth.txt, INDEX.txt: about a million lines
_SHOWN_PATH = 200  # characters of a path shown in a message about its length

ErrorFactory = Callable[..., Exception]  # error(message, hint=...) -> the caller's error type


def _kind(mode: int) -> str:
    if stat.S_ISDIR(mode):
        return "a folder"
    if stat.S_ISFIFO(mode):
        return "a FIFO (named pipe)"
    if stat.S_ISCHR(mode):
        return "a character device"
    if stat.S_ISBLK(mode):
        return "a block device"
    if stat.S_ISSOCK(mode):
        return "a socket"
    return "not a regular file"


def _os_error(path: str, exc: OSError, error: ErrorFactory) -> Exception:
    """One line for what open() or stat() said."""
    if exc.errno == errno.ENOENT:
        return error(f"{path}: no such file", hint="check the path")
    if exc.errno == errno.ENOTDIR:
        return error(f"{path}: a part of the path is not a folder", hint="check the path")
    if exc.errno == errno.ENAMETOOLONG:
        return error(f"{path[:_SHOWN_PATH]}...: the path is too long for the system")
    if exc.errno == errno.ELOOP:
        return error(f"{path}: too many levels of symbolic links (a symlink loop?)")
    if exc.errno in (errno.EACCES, errno.EPERM):
        return error(f"{path}: permission denied", hint="check the file's permissions")
    return error(f"{path}: cannot read it ({exc.strerror or type(exc).__name__})")


def check_path_length(path: str | os.PathLike[str], error: ErrorFactory = RecordingError) -> str:
    """The path as text, refused when a name in it is over NAME_MAX bytes or it is over PATH_MAX.

    Raises:
        error: naming the first long name (cut) and its length in bytes.
    """
    text = os.fspath(path)
    raw = os.fsencode(text)
    if len(raw) > PATH_MAX:
        raise error(
            f"{short_repr(text, _SHOWN_PATH)}: the path is {len(raw)} bytes long, "
            f"longer than the {PATH_MAX} the system allows",
            hint="check the path",
        )
    parts = raw.split(b"/")
    for i, part in enumerate(parts):
        if len(part) > NAME_MAX:
            shown = os.fsdecode(b"/".join([*parts[:i], part[:40]]))
            raise error(
                f"{shown}...: a name of {len(part)} bytes, longer than the {NAME_MAX} a file "
                "name may have",
                hint="check the path",
            )
    return text


def _regular_stat(path: str, error: ErrorFactory) -> os.stat_result:
    check_path_length(path, error)
    try:
        st = os.stat(path)
    except OSError as exc:
        raise _os_error(path, exc, error) from None
    except ValueError:  # an embedded NUL
        raise error(f"{short_repr(path)}: not a valid path (it holds a NUL byte)") from None
    if not stat.S_ISREG(st.st_mode):
        link = " (through a symlink)" if os.path.islink(path) else ""
        raise error(
            f"{path}: is {_kind(st.st_mode)}{link}, not a regular file",
            hint="depthnav reads regular files only",
        )
    return st


def check_regular(path: str | os.PathLike[str], error: ErrorFactory = RecordingError) -> None:
    """Refuse ``path`` unless it is a regular file (or a symlink to one); opens nothing."""
    _regular_stat(os.fspath(path), error)


def check_folder(path: str | os.PathLike[str], error: ErrorFactory = RecordingError) -> None:
    """Refuse ``path`` unless it is a folder (or a symlink to one); opens nothing."""
    text = check_path_length(path, error)
    try:
        st = os.stat(text)
    except OSError as exc:
        raise _os_error(text, exc, error) from None
    except ValueError:
        raise error(f"{short_repr(text)}: not a valid path (it holds a NUL byte)") from None
    if not stat.S_ISDIR(st.st_mode):
        kind = "a regular file" if stat.S_ISREG(st.st_mode) else _kind(st.st_mode)
        raise error(f"{text}: is {kind}, not a folder", hint="name a recording folder")


def _too_big(path: str, size: int, max_bytes: int, what: str, error: ErrorFactory) -> Exception:
    return error(
        f"{path}: is {size} bytes, more than the {max_bytes} a {what} may have",
        hint="is it the right file?",
    )


def open_input(
    path: str | os.PathLike[str],
    *,
    what: str = "file",
    max_bytes: int | None = None,
    error: ErrorFactory = RecordingError,
) -> BinaryIO:
    """Open a regular file for reading in binary; the caller closes it.

    Args:
        path: the file.
        what: what the file is, for the size message ("config file", "depth image").
        max_bytes: refuse a larger file; None for no limit (a frames archive).
        error: the error type to raise, called as ``error(message, hint=...)``.

    Raises:
        error: missing, not a regular file, too long a name, too big, unreadable.
    """
    text = os.fspath(path)
    st = _regular_stat(text, error)
    if max_bytes is not None and st.st_size > max_bytes:
        raise _too_big(text, st.st_size, max_bytes, what, error)
    flags = os.O_RDONLY | os.O_NONBLOCK | os.O_CLOEXEC | os.O_NOCTTY
    try:
        fd = os.open(text, flags)
    except OSError as exc:
        raise _os_error(text, exc, error) from None
    try:
        st = os.fstat(fd)  # the file opened, which may not be the one stat() saw
        if not stat.S_ISREG(st.st_mode):
            raise error(f"{text}: is {_kind(st.st_mode)}, not a regular file")
        if max_bytes is not None and st.st_size > max_bytes:
            raise _too_big(text, st.st_size, max_bytes, what, error)
        os.set_blocking(fd, True)
        return os.fdopen(fd, "rb")
    except BaseException:
        os.close(fd)
        raise


def open_output(
    path: str | os.PathLike[str], *, what: str = "output file", error: ErrorFactory = RecordingError
) -> BinaryIO:
    """Open a file for writing in binary, truncated: a regular file (or a symlink to one) or a
    new one; the caller closes it. The inputs' guard for outputs (a figure, a config written back):

    - a FIFO (``open()`` for writing blocks until a reader comes, and a signal could not end it),
      a device (``/dev/full``, a terminal), a socket or a folder is refused from ``stat()``, and
      the opened file is checked again (``fstat``); the open uses ``O_NONBLOCK`` (a FIFO swapped
      in meanwhile fails with ENXIO instead of blocking) and never makes a controlling terminal;
    - a name over NAME_MAX bytes or a path over PATH_MAX is refused by name.

    Raises:
        error: the reason in one line (``what`` names the file), with a hint.
    """
    text = check_path_length(path, error)
    try:
        st: os.stat_result | None = os.stat(text)
    except FileNotFoundError:
        st = None  # a new file (a dangling symlink is created at its target, as open() does)
    except OSError as exc:
        raise _os_error(text, exc, error) from None
    except ValueError:
        raise error(f"{short_repr(text)}: not a valid path (it holds a NUL byte)") from None
    if st is not None and not stat.S_ISREG(st.st_mode):
        link = " (through a symlink)" if os.path.islink(text) else ""
        raise error(
            f"{text}: is {_kind(st.st_mode)}{link}, not a regular file",
            hint=f"name a regular file or a new one for the {what}",
        )
    flags = os.O_WRONLY | os.O_CREAT | os.O_TRUNC | os.O_NONBLOCK | os.O_CLOEXEC | os.O_NOCTTY
    try:
        fd = os.open(text, flags, 0o666)
    except OSError as exc:
        if exc.errno == errno.ENXIO:  # a FIFO with no reader, swapped in after the stat
            raise error(f"{text}: is a FIFO (named pipe), not a regular file") from None
        if exc.errno == errno.ENOENT and not os.path.isdir(os.path.dirname(text) or "."):
            raise error(f"{text}: its folder does not exist", hint="check the path") from None
        if exc.errno in (errno.ENOENT, errno.EACCES, errno.EPERM, errno.EROFS):
            raise error(
                f"{text}: cannot write there ({exc.strerror})",
                hint="choose a writable place",
            ) from None
        raise _os_error(text, exc, error) from None
    try:
        st = os.fstat(fd)  # the file opened, which may not be the one stat() saw
        if not stat.S_ISREG(st.st_mode):
            raise error(f"{text}: is {_kind(st.st_mode)}, not a regular file")
        os.set_blocking(fd, True)
        return os.fdopen(fd, "wb")
    except BaseException:
        os.close(fd)
        raise


def read_bytes(
    path: str | os.PathLike[str],
    *,
    what: str = "file",
    max_bytes: int,
    error: ErrorFactory = RecordingError,
) -> bytes:
    """The whole content of a regular file of at most ``max_bytes`` bytes."""
    with open_input(path, what=what, max_bytes=max_bytes, error=error) as fh:
        try:
            data = fh.read(max_bytes + 1)
        except OSError as exc:
            raise _os_error(os.fspath(path), exc, error) from None
    if len(data) > max_bytes:  # it grew after the size check
        raise _too_big(os.fspath(path), len(data), max_bytes, what, error)
    return data


def decode_text(data: bytes, where: str, error: ErrorFactory = RecordingError) -> str:
    """UTF-8 text (a leading byte-order mark dropped); anything else is refused in one line."""
    if data.startswith((codecs.BOM_UTF16_LE, codecs.BOM_UTF16_BE)):
        raise error(f"{where}: is UTF-16 text; depthnav reads UTF-8", hint="save the file as UTF-8")
    try:
        text = data.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise error(
            f"{where}: is not UTF-8 text (byte {data[exc.start]:#04x} at offset {exc.start})",
            hint="save the file as UTF-8",
        ) from None
    return text.removeprefix("\ufeff")


def read_text(
    path: str | os.PathLike[str],
    *,
    what: str = "text file",
    max_bytes: int = TEXT_MAX_BYTES,
    error: ErrorFactory = RecordingError,
) -> str:
    """A regular UTF-8 text file of at most ``max_bytes`` bytes."""
    data = read_bytes(path, what=what, max_bytes=max_bytes, error=error)
    return decode_text(data, os.fspath(path), error)


def parse_toml(text: str, where: str, error: ErrorFactory = RecordingError) -> dict[str, Any]:
    """A TOML document; every way it can fail is one line naming ``where``."""
    try:
        return tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise error(f"{where}: is not valid TOML ({short_text(str(exc))})") from None
    except RecursionError:
        raise error(f"{where}: is not valid TOML (nested too deeply)") from None
    except ValueError:  # an integer over Python's 4300-digit limit (tomllib's int() raises)
        raise error(f"{where}: is not valid TOML (a number with too many digits)") from None


def read_toml(
    path: str | os.PathLike[str],
    *,
    what: str = "TOML file",
    max_bytes: int = TEXT_MAX_BYTES,
    error: ErrorFactory = RecordingError,
) -> dict[str, Any]:
    """A regular UTF-8 TOML file of at most ``max_bytes`` bytes, parsed."""
    text = read_text(path, what=what, max_bytes=max_bytes, error=error)
    return parse_toml(text, os.fspath(path), error)


def is_regular(path: Path) -> bool:
    """True for a regular file or a symlink to one; never opens it, never raises."""
    try:
        return stat.S_ISREG(os.stat(path).st_mode)
    except (OSError, ValueError):
        return False
