"""The fakenect recording format (libfreenect's ``fakenect-record``), read and written in Python.

A folder holds ``INDEX.txt`` (one file name per line, in playback order), depth frames
``d-<time_s>-<device_ts>.pgm`` (header ``P5 640 480 65535\\n`` then 640x480 little-endian 11-bit
disparity, 2047 = no reading), colour frames ``r-...ppm`` (ignored here) and accelerometer dumps
``a-<time_s>-<device_ts>.dump`` (12 bytes, ``<hhhbxi``: x, y, z counts, tilt half-degrees, status).

Disparity converts to millimetres with libfreenect's own zero-plane formula (src/registration.c,
``freenect_raw_to_mm``) and the usual Kinect 360 constants; pass the device's ``const_shift`` when
known. Unlike libfreenect, which clamps far values to 10000 mm, values outside 1..9999 mm become 0.
"""

from __future__ import annotations

import functools
import logging
import os
import re
import struct
from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import numpy.typing as npt

from drivers.base import KINECT_V1, Frame, Intrinsics
from drivers.errors import RecordingError
from drivers.files import INDEX_MAX_BYTES, check_folder, check_regular, read_bytes
from drivers.formats.png_folder import camera_toml_text, read_camera_toml, sidecar_intrinsics
from drivers.kinect.axes import camera_to_accel_counts
from drivers.values import NumberError, short_repr, to_number

log = logging.getLogger(__name__)

WIDTH, HEIGHT = 640, 480
PGM_HEADER = b"P5 640 480 65535\n"
NO_DISPARITY = 2047
MAX_MM = 10000
ACCEL_DUMP = struct.Struct("<hhhbxi")
_NAME = re.compile(r"([dra])-([0-9]+(?:\.[0-9]*)?)-([0-9]+)(?:-.*)?\.(pgm|ppm|dump)\Z")

# Kinect 360 zero-plane constants as libfreenect reads them from the device; typical values.
CONST_SHIFT = 200.0
REFERENCE_DISTANCE = 120.0  # zero-plane distance, cm
REFERENCE_PIXEL_SIZE = 0.1042  # zero-plane pixel size, mm
DCMOS_EMITTER_DIST = 7.5  # emitter to IR camera baseline, cm


@functools.lru_cache(maxsize=8)
def disparity_to_mm_table(const_shift: float = CONST_SHIFT) -> npt.NDArray[np.uint16]:
    """Millimetres for each raw 11-bit disparity value, libfreenect's formula.

    Returns:
        (2048,) uint16, read-only; 0 where there is no reading.
    """
    raw = np.arange(2048, dtype=np.float64)
    fixed_ref_x = (raw - 4.0 * const_shift) / 4.0 - 0.375
    metric = fixed_ref_x * REFERENCE_PIXEL_SIZE
    with np.errstate(divide="ignore", invalid="ignore"):
        mm = 10.0 * (
            metric * REFERENCE_DISTANCE / (DCMOS_EMITTER_DIST - metric) + REFERENCE_DISTANCE
        )
    valid = (metric < DCMOS_EMITTER_DIST) & (mm >= 1.0) & (mm < MAX_MM)
    table = np.where(valid, np.trunc(np.where(valid, mm, 0.0)), 0.0).astype(
        np.uint16
    )  # C truncates
    table[NO_DISPARITY] = 0
    table.setflags(write=False)
    return table


def disparity_to_mm(
    raw: npt.NDArray[np.uint16], const_shift: float = CONST_SHIFT
) -> npt.NDArray[np.uint16]:
    """(H, W) raw disparity to (H, W) uint16 millimetres, 0 = no reading."""
    return disparity_to_mm_table(const_shift)[np.minimum(raw, NO_DISPARITY)]


def mm_to_disparity(
    depth_mm: npt.NDArray[np.uint16], const_shift: float = CONST_SHIFT
) -> npt.NDArray[np.uint16]:
    """(H, W) millimetres to the raw disparity whose depth is nearest; 0 mm -> 2047."""
    table = disparity_to_mm_table(const_shift)
    raws = np.flatnonzero(table)  # valid raw values, depth increasing
    depths = table[raws].astype(np.float64)
    mm = np.asarray(depth_mm, dtype=np.float64)
    idx = np.clip(np.searchsorted(depths, mm), 1, len(raws) - 1)
    nearer_low = (mm - depths[idx - 1]) <= (depths[idx] - mm)
    out = raws[np.where(nearer_low, idx - 1, idx)].astype(np.uint16)
    out[mm <= 0] = NO_DISPARITY
    return out


@dataclass(frozen=True, slots=True)
class Entry:
    """One line of INDEX.txt."""

    kind: str  # "d", "r" or "a"
    time_s: float  # host time when recorded, seconds
    device_ts: int  # device timestamp (depth) or last frame timestamp seen (accel)
    path: Path


MAX_DUMP_BYTES = 4096  # an accelerometer dump has 12; a bigger file is not read whole


def read_index(folder: Path) -> list[Entry]:
    """Parse and check INDEX.txt; every named file must exist and be a regular file."""
    check_folder(folder)  # kinect?fakenect=/dev/zero: one line, not NotADirectoryError
    index = folder / "INDEX.txt"
    if not os.path.lexists(index):
        raise RecordingError(f"{folder}: not a fakenect recording (no INDEX.txt)")
    data = read_bytes(index, what="fakenect index", max_bytes=INDEX_MAX_BYTES)
    try:
        lines = data.decode("ascii").splitlines()
    except UnicodeDecodeError:
        raise RecordingError(f"{index}: not a text file") from None
    entries = []
    for number, line in enumerate(lines, 1):
        name = line.strip()
        if name:
            entries.append(_entry(folder, index, number, name))
    if not any(e.kind == "d" for e in entries):
        raise RecordingError(f"{index}: lists no depth frames (d-*.pgm)")
    return entries


def _entry(folder: Path, index: Path, number: int, name: str) -> Entry:
    """One INDEX.txt line: a fakenect file name whose time and timestamp are sane numbers."""
    match = _NAME.match(name)
    try:
        if not match or "/" in name:
            raise NumberError("")
        time_s = float(to_number(match.group(2), low=0.0, high=1e12))
        device_ts = int(to_number(match.group(3), integer=True, low=0, high=2**64 - 1))
    except NumberError:
        raise RecordingError(
            f"{index}:{number}: {short_repr(name)} is not a fakenect file name "
            "(d-/r-/a-<time>-<ts>.<ext>)"
        ) from None
    path = folder / name
    if not os.path.lexists(path):
        raise RecordingError(
            f"{index}:{number}: names {name}, which is missing",
            hint="the recording is incomplete",
        )
    check_regular(path)
    return Entry(match.group(1), time_s, device_ts, path)


def read_depth_pgm(path: Path) -> npt.NDArray[np.uint16]:
    """Read one fakenect depth file as (480, 640) raw disparity."""
    expected = len(PGM_HEADER) + WIDTH * HEIGHT * 2
    data = read_bytes(path, what="fakenect depth file", max_bytes=expected)
    if not data.startswith(PGM_HEADER):
        raise RecordingError(
            f"{path}: header is not {PGM_HEADER[:-1].decode()!r}; "
            "only 640x480 11-bit depth is supported"
        )
    if len(data) != expected:
        raise RecordingError(
            f"{path}: {len(data)} bytes, expected {expected} (truncated or corrupt)"
        )
    raw = np.frombuffer(data, dtype="<u2", offset=len(PGM_HEADER)).reshape(HEIGHT, WIDTH)
    if int(raw.max()) > NO_DISPARITY:
        raise RecordingError(f"{path}: values above 2047; not 11-bit disparity")
    return raw.astype(np.uint16)


def read_accel_dump(path: Path) -> tuple[int, int, int, int, int] | None:
    """(x, y, z counts, tilt half-degrees, status) from an a-*.dump; None if the size is wrong."""
    data = read_bytes(path, what="accelerometer dump", max_bytes=MAX_DUMP_BYTES)
    if len(data) != ACCEL_DUMP.size:
        log.warning("%s: %d bytes, expected %d; ignoring it", path, len(data), ACCEL_DUMP.size)
        return None
    return ACCEL_DUMP.unpack(data)


def iter_fakenect(
    folder: Path, const_shift: float = CONST_SHIFT
) -> Iterator[tuple[float, npt.NDArray[np.uint16], tuple[int, int, int, int, int] | None]]:
    """Yield (time_s from the first record, depth_mm (480, 640), accel dump or None).

    fakenect-record snapshots the accelerometer right after a depth frame, so a frame gets the
    first ``a-`` dump before the next depth frame, else the last one seen before it.
    """
    entries = read_index(folder)
    t0 = entries[0].time_s
    accel = None
    for i, entry in enumerate(entries):
        if entry.kind == "a":
            accel = read_accel_dump(entry.path)
        elif entry.kind == "d":
            for later in entries[i + 1 :]:
                if later.kind == "d":
                    break
                if later.kind == "a":
                    accel = read_accel_dump(later.path) or accel
                    break
            yield entry.time_s - t0, disparity_to_mm(read_depth_pgm(entry.path), const_shift), accel


SIDECAR = "camera.toml"  # the camera of frames that are not a Kinect v1's (not in INDEX.txt)


def folder_intrinsics(folder: Path) -> Intrinsics | None:
    """The camera a fakenect folder's ``camera.toml`` gives (written by ``write_fakenect`` for
    frames of another camera than the Kinect v1 the format assumes), None without one.

    Raises:
        RecordingError: unreadable, an unknown key, or bad intrinsics for 640x480 depth.
    """
    path = folder / SIDECAR
    if not os.path.lexists(path):
        return None
    table = read_camera_toml(path, ("intrinsics",))
    intr = sidecar_intrinsics(folder, table, (HEIGHT, WIDTH), where=path)
    if intr is None:
        raise RecordingError(f"{path}: has no [intrinsics] table", hint="add fx, fy, cx, cy")
    return intr


def write_fakenect(
    folder: str | os.PathLike[str],
    frames: Iterable[Frame],
    const_shift: float = CONST_SHIFT,
    start_time_s: float = 1_000_000.0,
) -> int:
    """Write frames as a fakenect recording (depth quantised to 11-bit disparity).

    Each frame with an accelerometer vector gets an ``a-`` dump after its depth file, as
    fakenect-record does; the tilt angle is written as 0 and the status as stopped. The format
    has no intrinsics (libfreenect's replay is a Kinect v1, ``KINECT_V1``): frames of another
    camera or with a lens get a ``camera.toml`` beside INDEX.txt, which depthnav's replay reads.

    Returns:
        The number of depth frames written.

    Raises:
        RecordingError: a frame that is not 640x480, or a folder that is not empty.
    """
    out = Path(folder)
    if out.exists() and any(out.iterdir()):
        raise RecordingError(f"{out}: folder is not empty; refusing to overwrite")
    names = []
    count = 0
    camera: Intrinsics | None = None
    for frame in frames:
        if camera is not None and frame.intrinsics != camera:
            raise RecordingError(
                f"{out}: frame {frame.seq} has another camera than the first",
                hint="a recording holds one camera setting; record each mode separately",
            )
        camera = frame.intrinsics
        if frame.depth_mm.shape != (HEIGHT, WIDTH):
            raise RecordingError(
                f"{out}: fakenect holds 640x480 depth only, frame {frame.seq} is "
                f"{frame.depth_mm.shape[1]}x{frame.depth_mm.shape[0]}"
            )
        out.mkdir(parents=True, exist_ok=True)  # once a frame fits: a refused one leaves nothing
        t = start_time_s + frame.timestamp_s
        ts = round(frame.timestamp_s * 1e6) & 0xFFFFFFFF
        name = f"d-{t:.6f}-{ts}.pgm"
        raw = mm_to_disparity(frame.depth_mm, const_shift).astype("<u2")
        (out / name).write_bytes(PGM_HEADER + raw.tobytes())
        names.append(name)
        if frame.accel_mps2 is not None:
            x, y, z = camera_to_accel_counts(frame.accel_mps2)
            aname = f"a-{t:.6f}-{ts}.dump"
            (out / aname).write_bytes(ACCEL_DUMP.pack(x, y, z, 0, 0))
            names.append(aname)
        count += 1
    out.mkdir(parents=True, exist_ok=True)
    if count and camera != KINECT_V1 and camera is not None:
        (out / SIDECAR).write_text(
            "# the camera of these frames, which fakenect cannot hold\n" + camera_toml_text(camera),
            encoding="utf-8",
        )
    (out / "INDEX.txt").write_text("".join(n + "\n" for n in names), encoding="ascii")
    return count
