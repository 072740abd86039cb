"""A ROS 2 ``.mcap`` read front to back, record by record, without its summary or footer.

An MCAP file is readable without its end: every record in the data section stands alone
(schemas and channels come before the messages that use them). ``rosbags`` needs the footer, so a
file cut even one byte short (a recorder killed, a copy that stopped) gave no frame at all. This
reader is the fallback (drivers/formats/rosbag.py): it offers the part of the ``rosbags``
reader interface DepthBag uses (``connections``, ``messages()``, ``deserialize()``,
``close()``), scans the file once when opened for the channels and their message counts, and
streams it again for the messages. Chunks are inflated through drivers/formats/bag_limits.py.

A file cut inside a record yields every message before the cut, then raises; one cut between
records, or in the summary after the data, ends cleanly.
"""

from __future__ import annotations

import struct
from collections.abc import Iterator
from dataclasses import dataclass
from io import BytesIO
from pathlib import Path
from typing import Any, BinaryIO

from drivers.errors import RecordingError
from drivers.files import open_input
from drivers.formats import bag_limits

MAGIC = b"\x89MCAP0\r\n"
OP_HEADER, OP_SCHEMA, OP_CHANNEL, OP_MESSAGE, OP_CHUNK, OP_DATA_END = 1, 3, 4, 5, 6, 0x0F
MESSAGE_HEAD = 22  # channel id u16, sequence u32, log time u64, publish time u64
MAX_META_RECORD = 16 << 20  # a schema or channel record larger than this is not a ROS bag's
_U16, _U32, _U64 = struct.Struct("<H"), struct.Struct("<I"), struct.Struct("<Q")


def is_cut_short(path: Path) -> bool:
    """True for a regular file that starts as an MCAP file and does not end as one (no end
    magic: cut short, or its writer stopped before the footer); never raises."""
    try:
        with open_input(path, what="ROS 2 bag") as fh:
            head = fh.read(len(MAGIC))
            size = fh.seek(0, 2)
            fh.seek(max(size - len(MAGIC), 0))
            tail = fh.read(len(MAGIC))
    except (RecordingError, OSError):
        return False
    return head == MAGIC and (size < 2 * len(MAGIC) or tail != MAGIC)


def open_cut_short(path: Path) -> StreamedMcap | None:
    """A bag's one ``.mcap`` (``path`` itself, or the one in a ROS 2 folder) opened for reading
    front to back when it is cut short and holds messages; else None (whole files that rosbags
    refused stay refused: bad metadata, damage).

    Raises:
        bag_limits.StoppedError: a stop came while it was scanned.
    """
    files = [path] if path.is_file() else sorted(path.glob("*.mcap"))
    if len(files) != 1 or files[0].suffix.lower() != ".mcap" or not is_cut_short(files[0]):
        return None
    reader = StreamedMcap(files[0])
    try:
        reader.open()
    except RecordingError:
        return None
    return reader if any(c.msgcount for c in reader.connections) else None


class CutShortError(RecordingError):
    """The file ends inside a record."""


@dataclass(frozen=True)
class StreamConnection:
    """A channel, as DepthBag reads a rosbags Connection."""

    id: int
    topic: str
    msgtype: str
    msgcount: int


def _string(buf: BytesIO) -> str:
    (n,) = _U32.unpack(_exact(buf, 4))
    return _exact(buf, n).decode("utf-8", errors="replace")


def _exact(buf: BinaryIO | BytesIO, n: int) -> bytes:
    data = buf.read(n)
    if len(data) != n:
        raise CutShortError(f"cut short inside a record ({len(data)} of {n} bytes)")
    return data


class StreamedMcap:
    """A ROS 2 ``.mcap`` streamed (see the module docstring); open() before use."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self.connections: list[StreamConnection] = []
        self.cut = False  # the file ends inside a record
        self.ended = False  # the data section's end record was read
        self._schemas: dict[int, str] = {}
        self._channels: dict[int, str] = {}  # id -> topic
        self._channel_types: dict[int, str] = {}  # id -> message type
        self._typestore: Any = None

    def open(self) -> None:
        """Scan the file: channels, their message types and counts.

        Raises:
            RecordingError: not an MCAP file, not the ros2 profile, a damaged record before the
                first message.
        """
        from rosbags.typesys import Stores, get_typestore

        self._typestore = get_typestore(Stores.ROS2_HUMBLE)
        counts: dict[int, int] = {}
        try:
            for channel, _t, _data in self._records(want=None):
                counts[channel] = counts.get(channel, 0) + 1
        except CutShortError:
            self.cut = True
        self.connections = [
            StreamConnection(cid, topic, self._channel_types.get(cid, ""), counts.get(cid, 0))
            for cid, topic in self._channels.items()
        ]

    def _records(self, want: set[int] | None) -> Iterator[tuple[int, int, bytes]]:
        """(channel id, log time ns, data) of every message, in file order (a chunk's by time);
        ``want`` None counts every message without reading its data."""
        self._schemas.clear()
        self._channels.clear()
        self._channel_types.clear()
        with open_input(self.path, what="ROS 2 bag") as fh:
            size = fh.seek(0, 2)
            fh.seek(0)
            if fh.read(8) != MAGIC or fh.read(1) != bytes([OP_HEADER]):
                raise RecordingError(f"{self.path}: not an MCAP file (no magic and header)")
            fh.seek(8)
            while fh.tell() < size:
                op = fh.read(1)[0]
                (length,) = _U64.unpack(_exact(fh, 8))
                if length > size - fh.tell():
                    raise CutShortError(f"cut short inside a record of {length} bytes")
                if op == OP_DATA_END:
                    self.ended = True
                    return
                if op == OP_CHUNK:
                    yield from self._chunk(_exact(fh, length), want)
                elif op == OP_MESSAGE:
                    yield from self._file_message(fh, length, want)
                elif op in (OP_HEADER, OP_SCHEMA, OP_CHANNEL):
                    if length > MAX_META_RECORD:
                        raise RecordingError(
                            f"{self.path}: an MCAP record of {length} bytes (opcode {op})",
                            hint=bag_limits.HINT,
                        )
                    self._meta(op, BytesIO(_exact(fh, length)))
                else:
                    fh.seek(length, 1)

    def _file_message(
        self, fh: BinaryIO, length: int, want: set[int] | None
    ) -> Iterator[tuple[int, int, bytes]]:
        """A message record outside chunks; the data of one not wanted is skipped unread."""
        if length < MESSAGE_HEAD:
            raise RecordingError(f"{self.path}: a message record of {length} bytes")
        head = _exact(fh, MESSAGE_HEAD)
        (cid,) = _U16.unpack_from(head, 0)
        if want is not None and cid in want:
            yield cid, _U64.unpack_from(head, 6)[0], _exact(fh, length - MESSAGE_HEAD)
            return
        fh.seek(length - MESSAGE_HEAD, 1)
        if want is None:
            yield cid, _U64.unpack_from(head, 6)[0], b""

    def _meta(self, op: int, body: BytesIO) -> None:
        if op == OP_HEADER:
            profile = _string(body)
            if profile != "ros2":
                raise RecordingError(
                    f"{self.path}: an MCAP file of profile {profile[:40]!r}, not a ROS 2 bag"
                )
        elif op == OP_SCHEMA:
            (sid,) = _U16.unpack(_exact(body, 2))
            self._schemas[sid] = _string(body)
        else:
            cid, sid = struct.unpack("<HH", _exact(body, 4))
            self._channels[cid] = _string(body)
            self._channel_types[cid] = self._schemas.get(sid, "")

    def _message(self, body: bytes, want: set[int] | None) -> Iterator[tuple[int, int, bytes]]:
        if len(body) < MESSAGE_HEAD:
            raise RecordingError(f"{self.path}: a message record of {len(body)} bytes")
        cid = _U16.unpack_from(body, 0)[0]
        if want is None or cid in want:
            yield cid, _U64.unpack_from(body, 6)[0], body[MESSAGE_HEAD:]

    def _chunk(self, body: bytes, want: set[int] | None) -> Iterator[tuple[int, int, bytes]]:
        buf = BytesIO(body)
        _start, _end, size = struct.unpack("<QQQ", _exact(buf, 24))
        _exact(buf, 4)  # the crc of the inflated records (rosbags checks it; a cut file: no)
        compression = _string(buf)
        (n,) = _U64.unpack(_exact(buf, 8))
        data = _exact(buf, n)
        walker = bag_limits.RecordWalker(compression or "uncompressed")
        if compression == "zstd":
            zstd = bag_limits.zstd_module()
            records = bag_limits.inflate(zstd.ZstdDecompressor, data, size, "zstd", walker)
        elif compression == "lz4":
            records = bag_limits.inflate(bag_limits.lz4_decompressor, data, size, "lz4", walker)
        elif compression == "":
            records = bag_limits.check_mcap_records(data, "uncompressed")
        else:
            raise RecordingError(f"{self.path}: chunk compression {compression[:20]!r} unknown")
        inner = BytesIO(records)
        messages: list[tuple[int, int, bytes]] = []
        while inner.tell() < len(records):
            op = _exact(inner, 1)[0]
            (length,) = _U64.unpack(_exact(inner, 8))
            rec = _exact(inner, length)
            if op == OP_MESSAGE:
                messages.extend(self._message(rec, want))
            elif op in (OP_SCHEMA, OP_CHANNEL):
                self._meta(op, BytesIO(rec))
        messages.sort(key=lambda m: m[1])
        yield from messages

    def messages(
        self, connections: list[StreamConnection] | None = None
    ) -> Iterator[tuple[StreamConnection, int, bytes]]:
        """(connection, log time ns, raw CDR) of the messages on ``connections`` (default all).

        Raises:
            CutShortError: after the last whole message, when the file ends inside a record.
        """
        conns = {c.id: c for c in (connections or self.connections)}
        for cid, t_ns, data in self._records(set(conns)):
            yield conns[cid], t_ns, data

    def deserialize(self, raw: bytes, msgtype: str) -> Any:
        return self._typestore.deserialize_cdr(raw, msgtype)

    def close(self) -> None:
        """Nothing stays open between calls."""
