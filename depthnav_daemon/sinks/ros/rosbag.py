"""``rosbag``: write every frame's scans, cliff points, transforms, pose and obstacle memory to
a ROS bag.

Spec: ``rosbag:PATH[?compression=..&image=0|1&tf=0|1&grid_rate=2&odom_tf=0|1&<names>]``.
``PATH.mcap`` is a ROS 2 bag (one MCAP file, CDR messages with their ``ros2msg`` definitions:
``ros2 bag play PATH.mcap``, Foxglove, rosbags, the mcap tools); ``PATH.bag`` is a ROS 1 bag
(``rosbag play``). No ROS is needed to write either (the ``rosbags`` and ``mcap`` packages).

Options:
    compression: .mcap: ``zstd`` (default) or ``none``; .bag: ``none`` (default) or ``bz2``
        (never lz4: ROS 1's own rosbag cannot read the lz4 that rosbags writes).
    image: 1 also writes the depth image (16UC1) and its CameraInfo (~0.6 MB a frame at 640x480),
        so ``replay:PATH`` reads the run back.
    tf: 0 leaves out ``/tf`` (when the robot's URDF already places the sensor).
    grid_rate, odom_tf: the obstacle memory's grid per second of frame time (default 2, 0 =
        none) and its odom -> base transform (0: the robot's odometry publishes it); with the
        memory on, ``/memory/grid``, ``/memory/scan``, ``/memory/cliff/points`` and that
        transform are added with its first frame (sinks/ros/memory_out.py).
    names: frame ids and topics, see sinks/ros/messages.py (``base_frame=base_footprint``,
        ``scan_topic=/depth/scan``, ...).

The bag is written under ``PATH.partial`` and renamed to PATH when the sink closes (a stop with
SIGINT/SIGTERM closes it). A full disk or a failing write ends the sink but leaves a readable bag
of what was written: the file is cut back to the last complete chunk and closed (a 256 KiB
reserve file beside it, removed then, keeps room for the index on a full disk). A kill -9
leaves ``PATH.partial`` without its index.
"""

from __future__ import annotations

import contextlib
import logging
import os
from pathlib import Path
from typing import TYPE_CHECKING, Any

from depthnav_daemon.errors import ConfigError, SinkError
from depthnav_daemon.sinks.base import SinkContext, SinkSpec, check_options
from depthnav_daemon.sinks.ros.memory_out import MemoryMessages
from depthnav_daemon.sinks.ros.messages import OPTIONS, MessageBuilder, RosNames, typestore

if TYPE_CHECKING:
    from depthnav_daemon.pipeline import Result
    from drivers.base import Frame

log = logging.getLogger(__name__)

GRAMMAR = (
    "rosbag:PATH.mcap|PATH.bag"
    "[?compression=..&image=0|1&tf=0|1&cliff_z=-0.05&grid_rate=2&odom_tf=0|1&base_frame=.."
    "&scan_topic=..]"
)
COMPRESSIONS = {".mcap": ("zstd", "none"), ".bag": ("none", "bz2")}  # first = default
PARTIAL = ".partial"
RESERVE = ".reserve"
RESERVE_BYTES = 256 << 10
CHUNK_BYTES = 256 << 10  # messages wait in memory until a chunk this big is written


class GuardedFile:
    """An unbuffered file that remembers clean cut points, to close a bag after a failed write."""

    def __init__(self, path: Path) -> None:
        self.file = open(path, "xb", buffering=0)
        self.cuts: list[int] = []

    def write(self, data: bytes | bytearray | memoryview) -> int:
        view = memoryview(data).cast("B")
        while view.nbytes:
            written = self.file.write(view)
            if not written:
                raise OSError("write made no progress")
            view = view[written:]
        return len(data)

    def mark(self) -> None:
        """The bytes so far end on a record boundary: a place to cut back to."""
        pos = self.file.tell()
        if not self.cuts or self.cuts[-1] != pos:
            self.cuts.append(pos)

    def tell(self) -> int:
        return self.file.tell()

    def seek(self, pos: int, whence: int = 0) -> int:
        return self.file.seek(pos, whence)

    def flush(self) -> None:
        """Nothing is buffered."""

    def cut(self, pos: int) -> None:
        self.file.truncate(pos)
        self.file.seek(pos)

    def close(self) -> None:
        with contextlib.suppress(OSError):
            os.fsync(self.file.fileno())
        self.file.close()


class _Mcap:
    """ROS 2: one MCAP file through the ``mcap`` writer (profile ros2, CDR)."""

    def __init__(self, out: GuardedFile, compression: str, library: str) -> None:
        from mcap.writer import CompressionType, Writer

        kind = CompressionType.ZSTD if compression == "zstd" else CompressionType.NONE
        self.out = out
        self.writer = Writer(out, chunk_size=CHUNK_BYTES, compression=kind)  # type: ignore[arg-type]
        self.writer.start(profile="ros2", library=library)
        self.store = typestore(ros1=False)
        self.channels: dict[str, int] = {}
        self.schemas: dict[str, int] = {}  # one schema record per message type

    def add(self, topic: str, msgtype: str) -> None:
        if msgtype not in self.schemas:
            msgdef = self.store.generate_msgdef(msgtype, ros_version=2)[0]
            self.schemas[msgtype] = self.writer.register_schema(msgtype, "ros2msg", msgdef.encode())
        self.channels[topic] = self.writer.register_channel(topic, "cdr", self.schemas[msgtype])

    def write(self, topic: str, t_ns: int, msg: Any) -> None:
        data = self.store.serialize_cdr(msg, msg.__msgtype__)
        self.writer.add_message(self.channels[topic], t_ns, bytes(data), t_ns)

    def finish(self) -> None:
        self.writer.finish()
        self.out.close()

    def finish_at(self, pos: int) -> None:
        """Cut the file at ``pos`` and end it there: DataEnd and a footer without a summary."""
        from mcap.data_stream import RecordBuilder
        from mcap.records import DataEnd, Footer
        from mcap.writer import MCAP0_MAGIC

        self.out.cut(pos)
        builder = RecordBuilder()
        DataEnd(0).write(builder)
        Footer(0, 0, 0).write(builder)
        self.out.write(builder.end() + MCAP0_MAGIC)
        self.out.close()


class _Bag1:
    """ROS 1: rosbags' writer, its file swapped for a GuardedFile after the bag header."""

    def __init__(self, path: Path, compression: str) -> None:
        from rosbags.rosbag1 import Writer

        self.writer = Writer(path)
        self.writer.chunk_threshold = CHUNK_BYTES
        if compression == "bz2":
            self.writer.set_compression(Writer.CompressionFormat.BZ2)
        self.writer.open()  # writes the 4 KiB bag header
        self.writer.bio.close()
        self.out = GuardedFile.__new__(GuardedFile)
        self.out.file = open(path, "r+b", buffering=0)
        self.out.file.seek(0, os.SEEK_END)
        self.out.cuts = []
        self.writer.bio = self.out
        self.store = typestore(ros1=True)
        self.conns: dict[str, Any] = {}
        self.channels = self.conns  # topic -> connection: the topics added so far

    def add(self, topic: str, msgtype: str) -> None:
        self.conns[topic] = self.writer.add_connection(topic, msgtype, typestore=self.store)

    def write(self, topic: str, t_ns: int, msg: Any) -> None:
        data = self.store.serialize_ros1(msg, msg.__msgtype__)
        self.writer.write(self.conns[topic], t_ns, data)

    def finish(self) -> None:
        self.writer.close()

    def finish_at(self, pos: int) -> None:
        """Cut the file at ``pos`` (after a complete chunk) and write the index for it."""
        self.out.cut(pos)
        self.writer.chunks = [c for c in self.writer.chunks if 0 <= c.pos < pos]
        self.writer.close()


class RosbagSink:
    """Writes a ROS 1 or ROS 2 bag (see the module docstring)."""

    def __init__(self, name: str, path: Path, compression: str, names: RosNames) -> None:
        self.name = name
        self.path = path
        self.compression = compression
        self.names = names
        self.partial = path.with_name(path.name + PARTIAL)
        self.reserve = path.with_name(path.name + PARTIAL + RESERVE)
        self._bag: _Mcap | _Bag1 | None = None
        self._builder: MessageBuilder | None = None
        self._memory: MemoryMessages | None = None
        self._memory_types: dict[str, str] = {}
        self.messages = 0

    @classmethod
    def from_spec(cls, spec: SinkSpec) -> RosbagSink:
        """Build from a parsed spec (no I/O). Raises ConfigError for a bad path or option."""
        check_options(spec, ("compression", *OPTIONS), GRAMMAR)
        path = Path(spec.target)
        suffix = path.suffix.lower()
        if not spec.target or suffix not in COMPRESSIONS:
            raise ConfigError(
                f"sink {spec.text!r}: a rosbag is a .mcap (ROS 2) or .bag (ROS 1) file",
                hint="e.g. rosbag:run.mcap or rosbag:run.bag",
            )
        allowed = COMPRESSIONS[suffix]
        compression = spec.options.get("compression", allowed[0]).strip().lower()
        if compression not in allowed:
            raise ConfigError(
                f"option compression={compression!r} in sink spec {spec.text!r}: a {suffix} "
                f"bag takes {' or '.join(allowed)}",
                hint="ROS 1's own rosbag cannot read lz4 written by rosbags"
                if suffix == ".bag"
                else None,
            )
        return cls(spec.text, path, compression, RosNames.from_spec(spec))

    def open(self, context: SinkContext) -> None:
        """Create ``PATH.partial`` and its reserve, start the bag, declare its topics.

        Raises:
            SinkError: PATH exists, the folder is missing or not writable, the disk is full.
        """
        if self.path.exists():
            raise SinkError(
                f"rosbag sink: {self.path} exists; not overwriting", hint="name a new file"
            )
        for leftover in (self.partial, self.reserve):
            if leftover.exists():  # never remove it: it may be another run's bag in the making
                raise SinkError(
                    f"rosbag sink: {leftover} exists (another run writing, or one that died)",
                    hint="remove it or name another file",
                )
        try:
            with open(self.reserve, "xb") as fh:
                fh.write(bytes(RESERVE_BYTES))
            if self.path.suffix.lower() == ".mcap":
                self._bag = _Mcap(
                    GuardedFile(self.partial), self.compression, f"depthnav {context.version}"
                )
            else:
                self._bag = _Bag1(self.partial, self.compression)
            self._builder = MessageBuilder(self._bag.store, self.names)
            for topic, msgtype in self._builder.msgtypes().items():
                self._bag.add(topic, msgtype)
                self._bag.store.get_msgdef(msgtype)  # generates its serializer now, not per frame
            # the memory's topics are added with its first message (no empty topics without it)
            self._memory = MemoryMessages(self._builder)
            self._memory_types = self._memory.msgtypes()
            self._bag.out.mark()
        except Exception as exc:  # a file error, or a library's own on a bad name
            self._discard()
            text = exc.strerror if isinstance(exc, OSError) and exc.strerror else str(exc)
            raise SinkError(f"rosbag sink: cannot write {self.partial}: {text}") from None
        log.info("rosbag sink writing %s (%s)", self.path, self.compression)

    def _discard(self) -> None:
        bag, self._bag = self._bag, None
        if bag is not None:
            with contextlib.suppress(OSError):
                bag.out.file.close()
        for p in (self.partial, self.reserve):
            with contextlib.suppress(OSError):
                p.unlink()

    def write(self, frame: Frame, result: Result) -> None:
        """Append the frame's messages; a failed write closes the bag at its last whole chunk."""
        if self._bag is None or self._builder is None or self._memory is None:
            raise SinkError(f"sink {self.name!r} is not open")
        t_ns, messages = self._builder.messages(frame, result)
        messages += self._memory.messages(result, t_ns)
        try:
            for topic, msg in messages:
                if topic not in self._bag.channels:
                    self._bag.add(topic, self._memory_types[topic])
                self._bag.write(topic, t_ns, msg)
                self.messages += 1
                self._bag.out.mark()
        except OSError as exc:
            kept = self._salvage()
            raise SinkError(
                f"rosbag sink: writing {self.path} failed ({exc.strerror or exc}); {kept}",
                hint="free some disk space",
            ) from None

    def _salvage(self) -> str:
        """End the bag at the latest cut that fits; rename it into place. Returns what was kept."""
        bag, self._bag = self._bag, None
        assert bag is not None
        with contextlib.suppress(OSError):
            self.reserve.unlink()
        for pos in reversed(bag.out.cuts):
            try:
                bag.finish_at(pos)
            except OSError:
                continue
            os.replace(self.partial, self.path)
            return f"{self.path} keeps what was written up to then ({pos} bytes)"
        with contextlib.suppress(OSError):
            bag.out.file.close()
        return f"nothing readable could be kept in {self.partial}"

    def close(self) -> None:
        """Write the index, rename PATH.partial to PATH. Safe to call twice."""
        if self._bag is None:
            return
        with contextlib.suppress(OSError):
            self.reserve.unlink()
        try:
            self._bag.finish()
        except OSError as exc:
            kept = self._salvage()
            raise SinkError(
                f"rosbag sink: closing {self.path} failed ({exc.strerror or exc}); {kept}"
            ) from None
        self._bag = None
        os.replace(self.partial, self.path)
        log.info("rosbag sink: %d messages in %s", self.messages, self.path)
