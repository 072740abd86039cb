"""Bounds on what a ROS bag can make depthnav decompress or parse, put in front of ``rosbags``.

``rosbags`` inflates a whole chunk in one call and checks its size afterwards: a 750 KB MCAP whose
zstd chunk inflates to 4 GiB (declared honestly, or as 1000 bytes) reached 3.1 GB before any
check, in one C call no signal could interrupt. :func:`install` replaces its decompressors (MCAP
chunks lz4/zstd, ROS 1 chunks bz2/lz4, ROS 2 per-message zstd) with streaming ones:

- a chunk's declared size over CHUNK_MAX_BYTES is refused before anything is inflated;
- the data is inflated PIECE_BYTES at a time and refused as soon as it passes its declared size
  (or CHUNK_MAX_BYTES where the format declares none), so memory stays within the declared size
  plus one piece (twice that for the moment the pieces are joined);
- between pieces a stop requested (SIGTERM, see :func:`set_stop_check`) ends the read.

``metadata.yaml`` of a ROS 2 folder is read here first (a regular file of at most
METADATA_MAX_BYTES, UTF-8, YAML nested at most MAX_YAML_DEPTH deep, no alias of a list or
mapping) so that rosbags' own parser only ever sees a small, shallow document: a 50 MB comment
line ran past 120 s, a document nested 5000 deep took 18 s.

Errors are RecordingError, one line naming the bag.
"""

from __future__ import annotations

import bz2
import contextlib
import functools
import os
import struct
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import yaml

from drivers.base import MAX_IMAGE_SIDE
from drivers.errors import DriverError, RecordingError
from drivers.files import check_regular, read_text
from drivers.values import short_text
from drivers.yaml_bounds import BoundedYamlLoader, YamlRefusedError

# a chunk holds at least one whole message: the largest image depthnav takes, 8192x8192 32FC1,
# is 256 MiB; the rest of a chunk (CameraInfo, Imu, tf) is small
CHUNK_MAX_BYTES = MAX_IMAGE_SIDE * MAX_IMAGE_SIDE * 4 + (16 << 20)
# a file-compressed ROS 2 bag's storage file may inflate to this many times its size (depth
# images compress 2-20 times; zeros 30,000 times)
FILE_MAX_RATIO = 100
PIECE_BYTES = 16 << 20  # inflated per call: ~10-30 ms, so a stop is seen that often
METADATA_MAX_BYTES = 256 << 10  # a metadata.yaml is a few KB; 256 KiB lists ~600 topics
# records in one MCAP chunk: rosbags walks them in Python and lists a chunk's messages before
# yielding the first (~150 B each); a 256 MiB chunk of zeros or of 31-byte records is 8-30
# million of them (minutes, GBs). Writers' chunks are 768 KiB-4 MiB: ~90,000 records at most
MAX_CHUNK_RECORDS = 250_000
_RECORD_HEAD = struct.Struct("<BQ")  # opcode, length
HINT = "the bag is damaged or built to exhaust memory: re-record it"

_state: dict[str, Any] = {"installed": False, "stop": None, "armed": 0}


class StoppedError(DriverError):
    """A stop was requested while a bag was being probed: the caller's stop, not a bad bag (not a
    RecordingError, which ends a run as a failure; the frame loop takes a DriverError during a
    stop as the stop)."""


def set_stop_check(check: Callable[[], bool] | None) -> None:
    """``check()`` is asked between pieces of every chunk while a bag is probed (``stoppable``);
    True ends the read with StoppedError.

    The CLI sets it to "a stop signal came", so SIGTERM during a bag's probing ends it within a
    piece instead of after the whole chunk.
    """
    _state["stop"] = check


@contextlib.contextmanager
def stoppable() -> Iterator[None]:
    """Within it (a bag's probing), a stop requested ends the reading with StoppedError; outside
    it (frames being read) the frame loop sees the stop between two frames."""
    _state["armed"] += 1
    try:
        yield
    finally:
        _state["armed"] -= 1


def _check_stop() -> None:
    check = _state["stop"]
    if _state["armed"] and check is not None and check():
        raise StoppedError("stopped while reading the bag")


def inflate(
    new: Callable[[], Any],
    data: bytes,
    declared: int | None,
    what: str,
    walker: RecordWalker | None = None,
) -> bytes:
    """``data`` decompressed by decompressor objects from ``new()`` (one per concatenated frame),
    at most ``declared`` bytes (CHUNK_MAX_BYTES when None), PIECE_BYTES at a time; each piece
    is fed to ``walker`` (MCAP chunks: their records are checked as they arrive).

    Raises:
        RecordingError: declared or actual size over the bound, actual size under the declared,
            damaged or cut data. StoppedError: a stop was requested.
    """
    if declared is not None and declared > CHUNK_MAX_BYTES:
        raise RecordingError(
            f"a {what} chunk declares {declared} bytes inflated, more than the "
            f"{CHUNK_MAX_BYTES} a chunk may have",
            hint=HINT,
        )
    limit = CHUNK_MAX_BYTES if declared is None else declared
    pieces: list[bytes] = []
    total = 0
    dec = new()
    rest = data
    try:
        while True:
            piece = dec.decompress(rest, PIECE_BYTES)
            rest = b""
            total += len(piece)
            if total > limit:
                bound = (
                    f"its declared {declared} bytes"
                    if declared is not None
                    else f"the {CHUNK_MAX_BYTES} bytes a chunk may have"
                )
                raise RecordingError(f"a {what} chunk inflates beyond {bound}", hint=HINT)
            pieces.append(piece)
            if walker is not None:
                walker.feed(piece)
            _check_stop()
            if dec.eof:
                rest = dec.unused_data or b""
                if not rest.strip(b"\0"):  # lz4/bz2 writers may pad; nothing else follows
                    break
                dec = new()
            elif dec.needs_input:
                raise RecordingError(f"a {what} chunk is cut short", hint=HINT)
    except (RecordingError, StoppedError):
        raise
    except Exception as exc:  # the codecs' own errors (ZstdError, RuntimeError, OSError, ...)
        raise RecordingError(f"a {what} chunk cannot be decompressed ({exc})", hint=HINT) from None
    if declared is not None and total != declared:
        raise RecordingError(
            f"a {what} chunk inflates to {total} bytes, not its declared {declared}", hint=HINT
        )
    if walker is not None:
        walker.finish()
    return b"".join(pieces)


class RecordWalker:
    """Checks an MCAP chunk's records as its bytes arrive, piece by piece: valid opcodes (a
    chunk of zeros is refused at its first byte, not after inflating it all), each record within
    the chunk, at most MAX_CHUNK_RECORDS of them."""

    def __init__(self, what: str) -> None:
        self.what = what
        self.count = 0
        self._next = 0  # offset of the next record's head
        self._seen = 0  # bytes fed so far
        self._tail = b""  # the bytes from _next on, when a head straddles two pieces

    def feed(self, piece: bytes) -> None:
        buf = self._tail + piece if self._tail else piece
        base = self._seen - len(self._tail)  # offset of buf[0]
        self._seen += len(piece)
        while self._next + _RECORD_HEAD.size <= self._seen:
            op, length = _RECORD_HEAD.unpack_from(buf, self._next - base)
            if op == 0:
                raise RecordingError(
                    f"a {self.what} chunk holds no MCAP record at byte {self._next}", hint=HINT
                )
            self._next += _RECORD_HEAD.size + length
            self.count += 1
            if self.count > MAX_CHUNK_RECORDS:
                raise RecordingError(
                    f"a {self.what} chunk holds more than {MAX_CHUNK_RECORDS} records", hint=HINT
                )
            if self.count % 65536 == 0:
                _check_stop()
        self._tail = buf[self._next - base :] if self._next < self._seen else b""

    def finish(self) -> None:
        if self._next != self._seen:
            raise RecordingError(f"a {self.what} chunk ends inside a record", hint=HINT)


def check_mcap_records(records: bytes, what: str) -> bytes:
    """``records`` (an MCAP chunk's) checked by a RecordWalker; returned as they are."""
    walker = RecordWalker(what)
    walker.feed(records)
    walker.finish()
    return records


def zstd_module() -> Any:
    from backports import zstd  # rosbags' own zstd (compression.zstd from Python 3.14)

    return zstd


def lz4_decompressor() -> Any:
    from lz4.frame import LZ4FrameDecompressor

    return LZ4FrameDecompressor()


class _BoundedZstd:
    """Stands in for the ``zstd`` module in rosbags.rosbag2.reader: a bounded ``decompress``
    (per-message compression) and ``open`` (file compression: rosbags inflates each storage
    file into a temporary folder, which is often a tmpfs, that is RAM)."""

    def __init__(self, module: Any) -> None:
        self._module = module

    def decompress(self, data: bytes) -> bytes:
        return inflate(self._module.ZstdDecompressor, data, None, "zstd message")

    def open(self, fileobj: Any, mode: str = "rb") -> _BoundedFile:
        compressed = os.fstat(fileobj.fileno()).st_size
        limit = CHUNK_MAX_BYTES + FILE_MAX_RATIO * compressed
        return _BoundedFile(self._module.open(fileobj, mode), limit)


class _BoundedFile:
    """A decompressing file read by ``shutil.copyfileobj``: refused past ``limit`` bytes, and a
    stop is seen between two reads."""

    def __init__(self, inner: Any, limit: int) -> None:
        self._inner, self._limit, self._total = inner, limit, 0

    def read(self, size: int = -1) -> bytes:
        if size < 0:  # everything, still a piece at a time
            return b"".join(iter(lambda: self.read(PIECE_BYTES), b""))
        _check_stop()
        data = self._inner.read(min(size, PIECE_BYTES))
        self._total += len(data)
        if self._total > self._limit:
            raise RecordingError(
                f"a zstd-compressed storage file inflates beyond {self._limit} bytes "
                f"({FILE_MAX_RATIO} times its size)",
                hint=HINT,
            )
        return data

    def __enter__(self) -> _BoundedFile:
        return self

    def __exit__(self, *exc: object) -> None:
        self._inner.close()


def install() -> None:
    """Put the bounded decompressors into rosbags (once; idempotent)."""
    if _state["installed"]:
        return
    from rosbags.rosbag1 import reader as ros1
    from rosbags.rosbag2 import reader as ros2
    from rosbags.rosbag2 import storage_mcap as mcap

    zstd = zstd_module()
    mcap.DECOMPRESSORS["zstd"] = lambda data, size: inflate(
        zstd.ZstdDecompressor, data, size, "zstd", RecordWalker("zstd")
    )
    mcap.DECOMPRESSORS["lz4"] = lambda data, size: inflate(
        lz4_decompressor, data, size, "lz4", RecordWalker("lz4")
    )
    mcap.DECOMPRESSORS[""] = lambda data, size: check_mcap_records(data, "uncompressed")
    ros2.zstd = _BoundedZstd(zstd)
    _install_ros1(ros1)
    _state["installed"] = True


def _install_ros1(ros1: Any) -> None:
    """ROS 1 chunks: rosbags does not pass the header's ``size`` to its decompressor, so the
    chunk header is read again here for it."""
    original = ros1.Reader.read_chunk
    codecs: dict[str, Callable[[], Any]] = {"bz2": bz2.BZ2Decompressor, "lz4": lz4_decompressor}

    @functools.wraps(original)
    def read_chunk(self: Any) -> Any:
        start = self.bio.tell()
        chunk = original(self)
        end = self.bio.tell()
        self.bio.seek(start)
        header = ros1.Header.read(self.bio, ros1.RecordType.CHUNK)
        compression = header.get_string("compression")
        size = header.get_uint32("size") if "size" in header else None
        self.bio.seek(end)
        new = codecs.get(compression)
        if new is None:  # 'none': the data is read from the file as it is
            return chunk
        bounded = functools.partial(_inflate_ros1, new, size, compression)
        return chunk._replace(decompressor=bounded)

    ros1.Reader.read_chunk = read_chunk


def _inflate_ros1(new: Callable[[], Any], size: int | None, what: str, data: bytes) -> bytes:
    return inflate(new, data, size, what)


# --- metadata.yaml -----------------------------------------------------------------------------
def check_metadata(folder: Path) -> None:
    """Refuse a ROS 2 folder's ``metadata.yaml`` that is not a small, shallow YAML mapping, and
    storage files (``.mcap``, ``.db3``, ``.zstd``) that are not regular files.

    Raises:
        RecordingError: special file, over METADATA_MAX_BYTES, not UTF-8, not YAML, too deep,
            an alias of a collection, not a mapping.
    """
    path = folder / "metadata.yaml"
    text = read_text(path, what="bag metadata file", max_bytes=METADATA_MAX_BYTES)
    loader = BoundedYamlLoader(text)
    try:
        doc = loader.get_single_node()
    except YamlRefusedError as exc:
        raise RecordingError(f"{path}: not accepted as bag metadata: {exc}", hint=HINT) from None
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        at = f" at line {mark.line + 1}" if mark is not None else ""
        problem = short_text(str(getattr(exc, "problem", "") or ""), 60)
        raise RecordingError(f"{path}: not valid YAML{at} ({problem})", hint=HINT) from None
    except (RecursionError, ValueError):
        raise RecordingError(f"{path}: not valid YAML (nested too deeply)", hint=HINT) from None
    finally:
        loader.dispose()
    if not isinstance(doc, yaml.MappingNode):
        raise RecordingError(f"{path}: is not a ROS 2 bag's metadata (not a mapping)", hint=HINT)
    for storage in folder.iterdir():  # rosbags opens them itself: regular files only
        if storage.name.endswith((".mcap", ".db3", ".zstd")):
            check_regular(storage)
