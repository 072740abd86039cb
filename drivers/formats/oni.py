"""The OpenNI ``.oni`` container: a small uncompressed writer and a structural checker.

Layout (OpenNI2 Source/Core/OniDataRecords.cpp, all little-endian, packed): a 24-byte header
``NI10``, version 1.0.1.0, max timestamp u64, max node id u32; then records, each a 28-byte
header (magic ``NIR\\0``, type, node id, fieldsSize incl. the header, payloadSize, undo position
u64) followed by its fields and payload. The writer emits one depth node with the ``NONE`` codec,
which libOniFile plays back bit-exact; the checker walks the records so a truncated or foreign
file fails with a message instead of reaching the native player.
"""

from __future__ import annotations

import itertools
import math
import os
import struct
from array import array
from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import BinaryIO

import numpy as np

from drivers.base import Frame, Intrinsics
from drivers.errors import RecordingError
from drivers.files import open_input
from drivers.formats.png_folder import camera_toml_text, read_camera_toml, sidecar_intrinsics
from drivers.limits import image_size_problem
from drivers.values import short_repr

MAGIC_FILE = b"NI10"
MAGIC_RECORD = 0x0052494E
FILE_HEADER = struct.Struct(
    "<4sBBHIQI"
)  # magic, version 1.0.1.0 (u8 u8 u16 u32), max ts, max node id
RECORD_HEADER = struct.Struct("<IIIIIQ")

INT_PROPERTY, REAL_PROPERTY, GENERAL_PROPERTY = 0x03, 0x04, 0x06
NODE_REMOVED, NODE_DATA_BEGIN, NODE_STATE_READY = 0x07, 0x08, 0x09
NEW_DATA, SEEK_TABLE, END, NODE_ADDED = 0x0A, 0x0E, 0x0B, 0x0D
KNOWN_TYPES = {
    0x02,
    INT_PROPERTY,
    REAL_PROPERTY,
    0x05,
    GENERAL_PROPERTY,
    NODE_REMOVED,
    NODE_DATA_BEGIN,
    NODE_STATE_READY,
    NEW_DATA,
    END,
    0x0C,
    NODE_ADDED,
    SEEK_TABLE,
}
NODE_TYPE_DEPTH = 2
PIXEL_FORMAT_DEPTH_1_MM = 100
SIDECAR_SUFFIX = ".camera.toml"  # NAME.oni -> NAME.camera.toml: what the file cannot hold
XN_PIXEL_FORMAT_GRAYSCALE_16 = 4


def _string(text: str) -> bytes:
    data = text.encode("ascii") + b"\0"
    return struct.pack("<I", len(data)) + data


class _Writer:
    def __init__(self, fh) -> None:
        self.fh = fh

    def record(
        self, rtype: int, fields: bytes = b"", payload: bytes = b"", undo: int = 0, node: int = 1
    ) -> int:
        pos = self.fh.tell()
        self.fh.write(
            RECORD_HEADER.pack(
                MAGIC_RECORD, rtype, node, RECORD_HEADER.size + len(fields), len(payload), undo
            )
        )
        self.fh.write(fields)
        self.fh.write(payload)
        return pos

    def prop(self, rtype: int, name: str, data: bytes) -> None:
        self.record(rtype, _string(name) + struct.pack("<I", len(data)) + data)


def _node_added(n_frames: int, max_ts: int, seek_pos: int) -> bytes:
    return _string("Depth") + struct.pack(
        "<I4sIQQQ", NODE_TYPE_DEPTH, b"NONE", n_frames, 0, max_ts, seek_pos
    )


def _write_props(w: _Writer, intr: Intrinsics, fps: int) -> None:
    """The depth node's properties, as libOniFile wants them."""
    hfov = 2.0 * math.atan(intr.width / (2.0 * intr.fx))
    vfov = 2.0 * math.atan(intr.height / (2.0 * intr.fy))
    w.prop(INT_PROPERTY, "oniRequiredFrameSize", struct.pack("<Q", intr.width * intr.height * 2))
    w.prop(INT_PROPERTY, "xnIsGenerating", struct.pack("<Q", 1))
    w.prop(INT_PROPERTY, "xnDeviceMaxDepth", struct.pack("<Q", 65535))
    w.prop(GENERAL_PROPERTY, "xnMapOutputMode", struct.pack("<III", intr.width, intr.height, fps))
    w.prop(INT_PROPERTY, "xnPixelFormat", struct.pack("<Q", XN_PIXEL_FORMAT_GRAYSCALE_16))
    w.prop(INT_PROPERTY, "oniPixelFormat", struct.pack("<Q", PIXEL_FORMAT_DEPTH_1_MM))
    w.prop(GENERAL_PROPERTY, "xnFOV", struct.pack("<dd", hfov, vfov))
    # libOniFile silently drops every frame of a stream without a cropping record.
    w.prop(GENERAL_PROPERTY, "xnCropping", struct.pack("<iHHHH", 0, 0, 0, 0, 0))
    w.prop(INT_PROPERTY, "xnMirror", struct.pack("<Q", 0))


def _write_body(fh: BinaryIO, first: Frame, frames: Iterator[Frame], fps: int, where: str) -> int:
    """Header, node, frames one at a time, seek table; the counts patched in at the end."""
    w = _Writer(fh)
    intr, t0 = first.intrinsics, first.timestamp_s
    fh.write(FILE_HEADER.pack(MAGIC_FILE, 1, 0, 1, 0, 0, 1))  # max timestamp patched below
    added = w.record(NODE_ADDED, _node_added(0, 0, 0))
    _write_props(w, intr, fps)
    w.record(NODE_STATE_READY)
    begin = w.record(NODE_DATA_BEGIN, struct.pack("<IQ", 0, 0))
    stamps, positions = array("Q"), array("Q")  # the seek table: 16 bytes a frame
    last = 0
    for number, frame in enumerate(itertools.chain([first], frames), 1):
        if frame.depth_mm.shape != (intr.height, intr.width):
            raise RecordingError(f"{where}: frame {frame.seq} changes the image size")
        ts = max(0, round((frame.timestamp_s - t0) * 1e6))
        payload = np.ascontiguousarray(frame.depth_mm, dtype="<u2").tobytes()
        last = w.record(NEW_DATA, struct.pack("<QI", ts, number), payload, undo=last)
        stamps.append(ts)
        positions.append(last)
    n, max_ts = len(stamps), max(stamps)
    w.record(NODE_REMOVED, undo=added)
    seek_pos = fh.tell()
    fh.write(RECORD_HEADER.pack(MAGIC_RECORD, SEEK_TABLE, 1, RECORD_HEADER.size, 20 + 20 * n, 0))
    fh.write(b"\0" * 20)
    for i in range(0, n, 4096):  # written in chunks: no second copy of the table
        fh.write(
            b"".join(
                struct.pack("<QIQ", ts, 0, pos)
                for ts, pos in zip(stamps[i : i + 4096], positions[i : i + 4096], strict=True)
            )
        )
    w.record(END, node=0)
    fh.seek(0)
    fh.write(FILE_HEADER.pack(MAGIC_FILE, 1, 0, 1, 0, max_ts, 1))
    fh.seek(added + RECORD_HEADER.size)
    fh.write(_node_added(n, max_ts, seek_pos))
    fh.seek(begin + RECORD_HEADER.size)
    fh.write(struct.pack("<IQ", n, max_ts))
    return n


def sidecar_path(path: Path) -> Path:
    """The ``camera.toml`` beside an ``.oni`` file: ``NAME.oni`` -> ``NAME.camera.toml``."""
    return path.with_suffix(SIDECAR_SUFFIX)


def needs_sidecar(intr: Intrinsics) -> bool:
    """True when an ``.oni`` file cannot hold this camera: it keeps fx, fy as a field of view,
    and no principal point (playback puts it at the image centre) or lens."""
    centre = ((intr.width - 1) / 2.0, (intr.height - 1) / 2.0)
    return intr.has_distortion or (intr.cx, intr.cy) != centre


def write_oni(path: str | os.PathLike[str], frames: Iterable[Frame], fps: int = 30) -> int:
    """Write depth frames to an uncompressed ``.oni`` file (DEPTH_1_MM), one frame in memory at
    a time (the seek table keeps 16 bytes a frame); written as ``PATH.partial``, renamed when
    complete.

    The field of view is derived from the first frame's fx, fy; OpenNI has no principal point or
    lens, so a camera with either (``needs_sidecar``) also gets ``NAME.camera.toml`` beside the
    file, which depthnav's playback (drivers.openni) reads: nothing is lost. Other players see
    the principal point at the image centre and no lens.

    Returns:
        The number of frames written.

    Raises:
        RecordingError: no frames, frames that change size or camera, the file or its sidecar
            exists, a failed write.
    """
    out = Path(path)
    items = iter(frames)
    first = next(items, None)
    if first is None:
        raise RecordingError(f"{out}: no frames to write")
    side = sidecar_path(out) if needs_sidecar(first.intrinsics) else None
    for target in (out, side):
        if target is not None and os.path.lexists(target):
            raise RecordingError(
                f"{target}: exists; refusing to overwrite", hint="choose a new name"
            )
    partial = out.with_name(out.name + ".partial")
    side_partial = None if side is None else side.with_name(side.name + ".partial")
    try:
        with open(partial, "xb") as fh:
            n = _write_body(fh, first, items, fps, str(out))
        if side is not None and side_partial is not None:
            with open(side_partial, "x", encoding="utf-8") as sh:
                sh.write(f"# the camera of {out.name}, which OpenNI cannot hold\n")
                sh.write(camera_toml_text(first.intrinsics))
            os.replace(side_partial, side)
        os.replace(partial, out)
    except OSError as exc:
        _remove(partial, side_partial, side)
        raise RecordingError(f"{out}: cannot write: {exc.strerror or exc}") from None
    except BaseException:
        _remove(partial, side_partial, side)
        raise
    return n


def _remove(*paths: Path | None) -> None:
    for p in paths:
        if p is not None:
            p.unlink(missing_ok=True)


def read_sidecar_intrinsics(path: Path, width: int, height: int) -> Intrinsics | None:
    """The camera an ``.oni`` file's ``NAME.camera.toml`` gives for its (width, height) depth
    stream, or None when there is no such file.

    Raises:
        RecordingError: unreadable, an unknown key, bad intrinsics, or a size other than the
            stream's.
    """
    side = sidecar_path(path)
    if not os.path.lexists(side):
        return None
    table = read_camera_toml(side, ("intrinsics",))
    intr = sidecar_intrinsics(side.parent, table, (height, width), where=side)
    if intr is None:
        raise RecordingError(f"{side}: has no [intrinsics] table", hint="add fx, fy, cx, cy")
    given = table["intrinsics"]
    for key, size in (("width", width), ("height", height)):
        if key in given and given[key] != size:
            raise RecordingError(
                f"{side}: [intrinsics] {key} = {short_repr(given[key])}, but the depth stream of "
                f"{path.name} is {width}x{height}",
                hint=f"it belongs to another recording; remove it or fix {key}",
            )
    return intr


@dataclass(frozen=True, slots=True)
class OniSummary:
    """What :func:`check_oni` found."""

    depth_nodes: int
    frames: int
    has_end: bool


PROPERTY_TYPES = {INT_PROPERTY, REAL_PROPERTY, 0x05, GENERAL_PROPERTY}
MAX_NAME = 256
U32 = 4  # bytes of a length field
PRINTABLE = range(0x20, 0x7F)  # plain ASCII, no control characters
MAX_SIDE = 8192  # pixels, as drivers.base.Intrinsics


def _name(fields: bytes, path: Path, pos: int) -> tuple[str, int]:
    """The record's leading string (u32 length incl. NUL, bytes) and the offset after it.

    libOniFile crashes (SIGSEGV, found by tests/faults/test_native_fuzz.py) on a property whose
    name is not plain ASCII, so anything else is rejected here, before it reaches the player.
    """
    if len(fields) < U32:
        raise RecordingError(f"{path}: corrupt record at byte {pos} (no name)")
    (length,) = struct.unpack_from("<I", fields)
    raw = fields[4 : 4 + length]
    if (
        not 1 < length <= MAX_NAME  # at least one character and its NUL
        or len(raw) != length
        or raw[-1:] != b"\0"
        or not all(c in PRINTABLE for c in raw[:-1])
    ):
        raise RecordingError(f"{path}: corrupt record at byte {pos} (bad name)")
    return raw[:-1].decode("ascii"), 4 + length


def check_oni(path: Path) -> OniSummary:
    """Walk the records of an ``.oni`` file without decoding frames.

    Besides the structure, it checks what the native player trusts blindly: names are ASCII,
    every depth node states a sane resolution (``xnMapOutputMode``), and an uncompressed
    (``NONE``) frame holds exactly width x height x 2 bytes.

    Raises:
        RecordingError: not an .oni file, a broken or truncated record, or no depth frames.
    """
    fh = open_input(path, what=".oni file")  # a FIFO would block libOniFile's own open
    size = os.fstat(fh.fileno()).st_size
    depth: dict[int, dict[str, object]] = {}  # node id -> codec, mode
    with fh:
        _check_file_header(fh.read(FILE_HEADER.size), path)
        pos, frames, has_end = FILE_HEADER.size, 0, False
        while pos + RECORD_HEADER.size <= size:
            fh.seek(pos)
            magic, rtype, node, fields, payload, _ = RECORD_HEADER.unpack(
                fh.read(RECORD_HEADER.size)
            )
            if magic == 0 and has_end:
                break  # the OpenNI recorder leaves zero padding after END
            _check_record(path, pos, size, magic, rtype, fields + payload)
            if rtype == NODE_ADDED or rtype in PROPERTY_TYPES:
                _check_node_record(
                    fh.read(fields - RECORD_HEADER.size), path, pos, rtype, node, depth
                )
            elif rtype == NEW_DATA:
                frames += 1
                _check_depth_frame(depth.get(node), path, pos, payload)
            elif rtype == END:
                has_end = True
                break
            pos += fields + payload
        if not has_end and pos != size:
            raise RecordingError(f"{path}: truncated inside a record header at byte {pos}")
    if not depth:
        raise RecordingError(f"{path}: has no depth stream")
    return OniSummary(len(depth), frames, has_end)


def _check_file_header(head: bytes, path: Path) -> None:
    if len(head) < FILE_HEADER.size or not head.startswith(MAGIC_FILE):
        raise RecordingError(f"{path}: not an .oni file (no NI10 header)")
    version = struct.unpack_from("<BBHI", head, 4)
    if version < (1, 0, 1, 0):
        raise RecordingError(
            f"{path}: .oni version {'.'.join(map(str, version))} is too old; "
            "OpenNI2 reads 1.0.1.0 and later"
        )


def _check_record(path: Path, pos: int, size: int, magic: int, rtype: int, nbytes: int) -> None:
    """A record header that is sane and whose record fits in the file."""
    if magic != MAGIC_RECORD:
        raise RecordingError(f"{path}: corrupt record at byte {pos} (bad magic {magic:#x})")
    if rtype not in KNOWN_TYPES or nbytes < RECORD_HEADER.size:
        raise RecordingError(f"{path}: corrupt record at byte {pos} (type {rtype:#x})")
    if pos + nbytes > size:
        raise RecordingError(
            f"{path}: truncated: record at byte {pos} needs {nbytes} bytes, "
            f"the file ends at {size}",
            hint="the recording was cut short; re-record it",
        )


def _check_node_record(
    body: bytes, path: Path, pos: int, rtype: int, node: int, depth: dict[int, dict[str, object]]
) -> None:
    """A NODE_ADDED or property record: notes depth nodes and their resolution in ``depth``."""
    name, at = _name(body, path, pos)
    if rtype == NODE_ADDED:
        if len(body) < at + 8:
            raise RecordingError(f"{path}: corrupt NODE_ADDED record at byte {pos}")
        node_type, codec = struct.unpack_from("<I4s", body, at)
        if node_type == NODE_TYPE_DEPTH:
            depth[node] = {"codec": codec, "mode": None}
    elif name == "xnMapOutputMode" and node in depth:
        if len(body) < at + 16:
            raise RecordingError(f"{path}: corrupt xnMapOutputMode at byte {pos}")
        width, height = struct.unpack_from("<II", body, at + 4)
        if not (1 <= width <= MAX_SIDE and 1 <= height <= MAX_SIDE):
            raise RecordingError(
                f"{path}: depth resolution {width}x{height} is out of range "
                f"(1..{MAX_SIDE} pixels each way)"
            )
        problem = image_size_problem(width, height)
        if problem:
            raise RecordingError(f"{path}: depth stream of {problem}")
        depth[node]["mode"] = (width, height)


def _check_depth_frame(info: dict[str, object] | None, path: Path, pos: int, payload: int) -> None:
    """A frame of a depth node (``info``; None for other nodes) that the player can copy."""
    if info is None:
        return
    if info["mode"] is None:
        raise RecordingError(
            f"{path}: depth frame at byte {pos} before the stream's resolution "
            "(no xnMapOutputMode record)"
        )
    width, height = info["mode"]  # type: ignore[misc]
    if info["codec"] == b"NONE" and payload != width * height * 2:
        raise RecordingError(
            f"{path}: depth frame at byte {pos} holds {payload} bytes, "
            f"a {width}x{height} frame needs {width * height * 2}"
        )
