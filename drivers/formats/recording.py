"""depthnav's recording format: a folder holding ``frames.npz`` and ``recording.toml``.

``frames.npz`` holds ``depth_mm`` (N, H, W) uint16, ``intrinsics`` float64 [fx, fy, cx, cy],
``timestamp_s`` (N,) float64 and, when every frame had one, ``accel_mps2`` (N, 3) float64 and
``odom`` (N, 3) float64 ``[x_m, y_m, yaw_rad]`` (the robot's pose in its odometry frame at each
frame).
``recording.toml`` holds ``format_version``, ``description``, ``device``, an ``[intrinsics]``
table and an optional ``[truth]`` table. A bare ``.npz`` with the same arrays is also readable.

Memory: ``read_recording`` decompresses every frame into memory, ``open_recording_stream`` one
frame at a time; ``drivers.formats.recording_writer.write_recording`` holds one frame at a time.
"""

from __future__ import annotations

import contextlib
import logging
import math
import os
import tomllib
import zipfile
from collections.abc import Iterator, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, Any

import numpy as np
import numpy.typing as npt

from drivers.base import Frame, Intrinsics
from drivers.errors import RecordingError

log = logging.getLogger(__name__)

FORMAT_VERSION = 1
FRAMES_FILE = "frames.npz"
META_FILE = "recording.toml"
DEPTH_MEMBER = "depth_mm.npy"
_MAX_HEADER_SIZE = 10_000  # np.load's limit on a .npy header, bytes


@dataclass(frozen=True, slots=True)
class Recording:
    """A recording loaded into memory.

    Attributes:
        depth_mm: (N, H, W) uint16 millimetres, 0 = no reading.
        intrinsics: intrinsics of every frame.
        timestamp_s: (N,) float64 seconds, non-decreasing.
        accel_mps2: (N, 3) float64 m/s^2 in the camera frame, or None.
        description: free text from the metadata.
        device: the device it was recorded from, free text.
        truth: the ``[truth]`` table, or {}.
        odom: (N, 3) float64 [x_m, y_m, yaw_rad] per frame, or None.
    """

    depth_mm: npt.NDArray[np.uint16]
    intrinsics: Intrinsics
    timestamp_s: npt.NDArray[np.float64]
    accel_mps2: npt.NDArray[np.float64] | None = None
    description: str = ""
    device: str = ""
    truth: Mapping[str, Any] = field(default_factory=dict)
    odom: npt.NDArray[np.float64] | None = None

    def frames(self) -> list[Frame]:
        """The recording as Frames, seq 0..N-1."""
        return [
            Frame(
                seq=i,
                timestamp_s=float(self.timestamp_s[i]),
                depth_mm=self.depth_mm[i],
                intrinsics=self.intrinsics,
                accel_mps2=None
                if self.accel_mps2 is None
                else tuple(map(float, self.accel_mps2[i])),
                odom=None if self.odom is None else tuple(map(float, self.odom[i])),
            )
            for i in range(len(self.depth_mm))
        ]


@contextlib.contextmanager
def _reading(path: Path) -> Iterator[None]:
    """Turn whatever a damaged or missing archive raises into one RecordingError line."""
    try:
        yield
    except RecordingError:
        raise
    except FileNotFoundError:
        raise RecordingError(f"{path}: no such file", hint="check the path") from None
    except Exception as exc:
        # BadZipFile, zlib.error, EOFError, ValueError, SyntaxError, tokenize.TokenError, ...
        # (found by tests/faults/test_fuzz_inputs.py); every one means the same to the user
        reason = str(exc).splitlines()[0] if str(exc) else ""
        raise RecordingError(
            f"{path}: not a readable .npz archive (corrupt or truncated: "
            f"{type(exc).__name__}{': ' + reason[:120] if reason else ''})",
            hint="re-record it or restore it from git",
        ) from exc


def _load_npz(path: Path, skip: str | None = None) -> dict[str, npt.NDArray[Any]]:
    """Every array of an .npz but ``skip``, which is never decompressed (np.load is lazy)."""
    with _reading(path), np.load(path, allow_pickle=False) as npz:
        return {name: npz[name] for name in npz.files if name != skip}


def _intrinsics_from_meta(table: Any, shape: tuple[int, int], where: Path) -> Intrinsics:
    if not isinstance(table, dict):
        raise RecordingError(
            f"{where}: [intrinsics] table is missing", hint="add width, height, fx, fy, cx, cy"
        )
    try:
        intr = Intrinsics(
            int(table["width"]),
            int(table["height"]),
            float(table["fx"]),
            float(table["fy"]),
            float(table["cx"]),
            float(table["cy"]),
        )
    except KeyError as exc:
        raise RecordingError(f"{where}: [intrinsics] lacks {exc.args[0]!r}") from None
    except (TypeError, ValueError) as exc:
        raise RecordingError(f"{where}: bad [intrinsics]: {exc}") from None
    if (intr.height, intr.width) != shape:
        raise RecordingError(
            f"{where}: [intrinsics] says {intr.width}x{intr.height} "
            f"but frames are {shape[1]}x{shape[0]}"
        )
    return intr


def intrinsics_from_array(values: Any, shape: tuple[int, int], where: Path) -> Intrinsics:
    """Intrinsics from an [fx, fy, cx, cy] array and an (H, W) image shape."""
    arr = np.asarray(values)
    if arr.shape != (4,) or not np.issubdtype(arr.dtype, np.number):
        raise RecordingError(
            f"{where}: 'intrinsics' must be 4 numbers [fx, fy, cx, cy], got shape {arr.shape}"
        )
    try:
        return Intrinsics(shape[1], shape[0], *(float(v) for v in arr))
    except ValueError as exc:
        raise RecordingError(f"{where}: bad intrinsics: {exc}") from None


def _read_meta(folder: Path) -> dict[str, Any]:
    """``recording.toml`` of a recording folder, with its format_version checked."""
    meta_path = folder / META_FILE
    try:
        meta = tomllib.loads(meta_path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise RecordingError(
            f"{folder}: not a depthnav recording (no {META_FILE})",
            hint="an interrupted `depthnav record` leaves no recording.toml; record again",
        ) from None
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
        raise RecordingError(f"{meta_path}: not valid TOML ({exc})") from None
    version = meta.get("format_version")
    if not isinstance(version, int) or version < 1:
        raise RecordingError(f"{meta_path}: format_version is missing or not a positive integer")
    if version > FORMAT_VERSION:
        raise RecordingError(
            f"{meta_path}: has format_version {version}; "
            f"this depthnav reads up to {FORMAT_VERSION}",
            hint="update depthnav",
        )
    return meta


def _check_depth_layout(dtype: np.dtype[Any], shape: tuple[int, ...], npz_path: Path) -> None:
    if dtype != np.uint16 or len(shape) != 3 or min(shape) < 1:  # noqa: PLR2004
        raise RecordingError(
            f"{npz_path}: 'depth_mm' must be uint16 (N, H, W) with N >= 1, got {dtype} {shape}"
        )


def _checked_depth(arrays: dict[str, npt.NDArray[Any]], npz_path: Path) -> npt.NDArray[np.uint16]:
    depth = arrays.get("depth_mm")
    if depth is None:
        raise RecordingError(
            f"{npz_path}: has no 'depth_mm' array (found: {', '.join(arrays) or 'none'})"
        )
    _check_depth_layout(depth.dtype, depth.shape, npz_path)
    return depth


def _checked_stamps(
    stamps: npt.NDArray[Any] | None, n: int, npz_path: Path, default_fps: float
) -> npt.NDArray[np.float64]:
    if stamps is None:
        return np.arange(n, dtype=np.float64) / default_fps
    stamps = np.asarray(stamps)
    if stamps.shape != (n,) or not np.issubdtype(stamps.dtype, np.number):
        raise RecordingError(
            f"{npz_path}: 'timestamp_s' must be {n} numbers, got {stamps.dtype} {stamps.shape}"
        )
    stamps = stamps.astype(np.float64)
    if not np.all(np.isfinite(stamps)) or np.any(np.diff(stamps) < 0):
        raise RecordingError(f"{npz_path}: 'timestamp_s' must be finite and non-decreasing")
    return stamps


def _checked_accel(
    accel: npt.NDArray[Any] | None, n: int, npz_path: Path
) -> npt.NDArray[np.float64] | None:
    if accel is None:
        return None
    if accel.shape != (n, 3) or not np.issubdtype(accel.dtype, np.number):
        raise RecordingError(
            f"{npz_path}: 'accel_mps2' must be ({n}, 3) numbers, got {accel.shape}"
        )
    accel = accel.astype(np.float64)
    if not np.all(np.isfinite(accel)):
        raise RecordingError(f"{npz_path}: 'accel_mps2' has non-finite values")
    return accel


def _checked_odom(
    odom: npt.NDArray[Any] | None, n: int, npz_path: Path
) -> npt.NDArray[np.float64] | None:
    if odom is None:
        return None
    if odom.shape != (n, 3) or not np.issubdtype(odom.dtype, np.number):
        raise RecordingError(
            f"{npz_path}: 'odom' must be ({n}, 3) numbers [x_m, y_m, yaw_rad] (one row per "
            f"frame), got {odom.dtype} {odom.shape}"
        )
    odom = odom.astype(np.float64)
    if not np.all(np.isfinite(odom)):
        raise RecordingError(f"{npz_path}: 'odom' has non-finite values")
    return odom


def _locate(path: str | os.PathLike[str]) -> tuple[Path, dict[str, Any], Path]:
    """(the path, its recording.toml or {} for a bare .npz, the .npz holding the frames)."""
    where = Path(path)
    if where.is_dir():
        return where, _read_meta(where), where / FRAMES_FILE
    if where.suffix.lower() == ".npz" or where.is_file():
        return where, {}, where
    raise RecordingError(f"{where}: no such file or folder", hint="check the path")


def _described(
    where: Path,
    meta: dict[str, Any],
    npz_path: Path,
    arrays: dict[str, npt.NDArray[Any]],
    shape: tuple[int, int, int],
    default_fps: float,
) -> dict[str, Any]:
    """Everything of a recording but its depth, checked against the depth's (N, H, W)."""
    n, image = shape[0], (shape[1], shape[2])
    if "intrinsics" in meta:
        intr = _intrinsics_from_meta(meta["intrinsics"], image, where / META_FILE)
    elif "intrinsics" in arrays:
        intr = intrinsics_from_array(arrays["intrinsics"], image, npz_path)
    else:
        raise RecordingError(f"{npz_path}: has no 'intrinsics' array [fx, fy, cx, cy]")
    truth = meta.get("truth", {})
    return {
        "intrinsics": intr,
        "timestamp_s": _checked_stamps(arrays.get("timestamp_s"), n, npz_path, default_fps),
        "accel_mps2": _checked_accel(arrays.get("accel_mps2"), n, npz_path),
        "odom": _checked_odom(arrays.get("odom"), n, npz_path),
        "description": str(meta.get("description", "")),
        "device": str(meta.get("device", "")),
        "truth": truth if isinstance(truth, dict) else {},
    }


def read_recording(path: str | os.PathLike[str], default_fps: float = 30.0) -> Recording:
    """Load a recording folder or a bare ``.npz``, every frame decompressed into memory.

    Args:
        path: a recording folder (``recording.toml`` + ``frames.npz``) or an ``.npz`` file.
        default_fps: frame rate assumed when the file has no timestamps, frames per second.

    Raises:
        RecordingError: missing, corrupt, truncated or inconsistent; the message names the file.
    """
    where, meta, npz_path = _locate(path)
    arrays = _load_npz(npz_path)
    depth = _checked_depth(arrays, npz_path)
    return Recording(
        depth_mm=depth, **_described(where, meta, npz_path, arrays, depth.shape, default_fps)
    )


# --- streaming: one frame in memory at a time -------------------------------------------------
@dataclass(frozen=True, slots=True)
class _DepthHeader:
    """The .npy header of the ``depth_mm`` member: shape, dtype and memory order.

    Attributes:
        member: its name in the zip archive.
        member_size: its size uncompressed (header and data) as the archive says, bytes.
    """

    member: str
    member_size: int
    shape: tuple[int, ...]
    fortran_order: bool
    dtype: np.dtype[Any]

    @property
    def nbytes(self) -> int:
        """Decoded size of the array, bytes."""
        return math.prod(self.shape) * self.dtype.itemsize


def _depth_member(npz: zipfile.ZipFile, npz_path: Path) -> str:
    """The member np.load would read as ``depth_mm``."""
    names = npz.namelist()
    for name in (DEPTH_MEMBER, "depth_mm"):
        if name in names:
            return name
    found = ", ".join(n.removesuffix(".npy") for n in names) or "none"
    raise RecordingError(f"{npz_path}: has no 'depth_mm' array (found: {found})")


def _read_header(fid: IO[bytes]) -> tuple[tuple[int, ...], bool, np.dtype[Any]]:
    """(shape, Fortran order, dtype) from the start of a .npy member; leaves fid after it."""
    version = np.lib.format.read_magic(fid)
    if version == (1, 0):
        shape, fortran, dtype = np.lib.format.read_array_header_1_0(fid, _MAX_HEADER_SIZE)
    elif version == (2, 0):
        shape, fortran, dtype = np.lib.format.read_array_header_2_0(fid, _MAX_HEADER_SIZE)
    else:
        raise ValueError(f"unsupported .npy format version {version[0]}.{version[1]}")
    return tuple(shape), bool(fortran), dtype


def _depth_header(npz_path: Path) -> _DepthHeader:
    """The ``depth_mm`` header of an .npz, without decompressing the frames."""
    with _reading(npz_path), zipfile.ZipFile(npz_path) as npz:
        member = _depth_member(npz, npz_path)
        with npz.open(member) as fid:
            return _DepthHeader(member, npz.getinfo(member).file_size, *_read_header(fid))


def recording_depth_nbytes(path: str | os.PathLike[str]) -> int:
    """Decoded size of a recording's depth frames, bytes, from the .npy header alone.

    Raises:
        RecordingError: no such file, or not a readable .npz.
    """
    where = Path(path)
    return _depth_header(where / FRAMES_FILE if where.is_dir() else where).nbytes


@dataclass(frozen=True, slots=True)
class RecordingStream:
    """A recording whose depth frames stay on disk; ``iter_depth`` reads them one at a time.

    Attributes:
        npz_path: the ``.npz`` holding the frames.
        shape: (N, H, W) of ``depth_mm``.
        intrinsics, timestamp_s, accel_mps2, description, device, truth, odom: as in Recording.
    """

    npz_path: Path
    shape: tuple[int, int, int]
    intrinsics: Intrinsics
    timestamp_s: npt.NDArray[np.float64]
    accel_mps2: npt.NDArray[np.float64] | None = None
    description: str = ""
    device: str = ""
    truth: Mapping[str, Any] = field(default_factory=dict)
    odom: npt.NDArray[np.float64] | None = None

    @property
    def depth_nbytes(self) -> int:
        """Decoded size of every depth frame together, bytes."""
        return math.prod(self.shape) * 2

    def iter_depth(self) -> Iterator[npt.NDArray[np.uint16]]:
        """Each frame's (H, W) uint16 depth, mm, read-only; one frame decompressed at a time.

        Every call reopens the file and starts at frame 0.

        Raises:
            RecordingError: the file is corrupt, truncated or changed since it was opened.
        """
        n, height, width = self.shape
        frame_bytes = height * width * 2
        with _reading(self.npz_path), zipfile.ZipFile(self.npz_path) as npz:
            with npz.open(_depth_member(npz, self.npz_path)) as fid:
                if _read_header(fid) != (self.shape, False, np.dtype(np.uint16)):
                    raise RecordingError(f"{self.npz_path}: changed while being replayed")
                for i in range(n):
                    data = fid.read(frame_bytes)
                    if len(data) != frame_bytes:
                        raise EOFError(f"'depth_mm' ends in frame {i} of {n}")
                    yield np.frombuffer(data, dtype=np.uint16).reshape(height, width)
                fid.read(1)  # to the end of the member, where zipfile checks its CRC-32


def open_recording_stream(
    path: str | os.PathLike[str], default_fps: float = 30.0
) -> RecordingStream:
    """Open a recording folder or a bare ``.npz`` for reading frame by frame.

    Only the metadata and the small arrays (timestamps, accelerometer, intrinsics) are loaded;
    the depth frames are decompressed by ``RecordingStream.iter_depth``.

    Args:
        path: a recording folder (``recording.toml`` + ``frames.npz``) or an ``.npz`` file.
        default_fps: frame rate assumed when the file has no timestamps, frames per second.

    Raises:
        RecordingError: missing, corrupt or inconsistent, or ``depth_mm`` not stored as uint16
            in C order; the message names the file.
    """
    where, meta, npz_path = _locate(path)
    header = _depth_header(npz_path)
    _check_depth_layout(header.dtype, header.shape, npz_path)
    if header.fortran_order:
        raise RecordingError(
            f"{npz_path}: 'depth_mm' must be uint16 (N, H, W) in C order, "
            f"got {header.dtype} {header.shape} in Fortran order",
            hint="save it again with np.ascontiguousarray(depth_mm)",
        )
    shape = (header.shape[0], header.shape[1], header.shape[2])
    # the archive's own size record bounds N before anything is sized by it (a damaged header)
    if header.member_size < header.nbytes:
        raise RecordingError(
            f"{npz_path}: 'depth_mm' holds {header.member_size} bytes, too few for "
            f"{shape} uint16 (truncated)",
            hint="re-record it or restore it from git",
        )
    arrays = _load_npz(npz_path, skip="depth_mm")
    return RecordingStream(
        npz_path=npz_path,
        shape=shape,
        **_described(where, meta, npz_path, arrays, shape, default_fps),
    )
