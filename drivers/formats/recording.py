"""depthnav's recording format: a folder holding ``frames.npz`` and ``recording.toml``.

``frames.npz`` holds ``depth_mm`` (N, H, W) uint16, ``intrinsics`` float64 [fx, fy, cx, cy],
``timestamp_s`` (N,) float64 and, when every frame had one, ``accel_mps2`` (N, 3) float64 and
``odom`` (N, 3) float64 ``[x_m, y_m, yaw_rad]`` (the robot's pose in its odometry frame at each
frame; rows outside the odometry limits of drivers.base are read as they are and refused by the
memory, frame by frame).
``recording.toml`` holds ``format_version``, ``description``, ``device``, an ``[intrinsics]``
table (width, height, fx, fy, cx, cy and, for a distorting lens, plumb_bob k1, k2, p1, p2, k3; 0
when absent) and an optional ``[truth]`` table. A bare ``.npz`` with the same arrays is also
readable (as a pinhole: its ``intrinsics`` array has no lens coefficients); it may hold
``depth_m`` float32/float64 (N, H, W) metres instead of ``depth_mm`` (converted by
``metres_to_mm``), and its intrinsics may come from the caller (replay's ``fx, fy, cx, cy``).

Memory: ``read_recording`` decompresses every frame into memory, ``open_recording_stream`` one
frame at a time; ``drivers.formats.recording_writer.write_recording`` holds one frame at a time.
Nothing is decoded before its size is known (drivers.formats.npz): ``depth_mm`` must be uint16
(N, H, W) with N <= MAX_FRAMES and an image depthnav takes (drivers.limits), ``timestamp_s``
(N,), ``accel_mps2`` (N, 3) and ``intrinsics`` (4,) numbers; other members are never read.
"""

from __future__ import annotations

import logging
import math
import os
from collections.abc import Iterator, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from drivers.base import DISTORTION_KEYS, MM_PER_M, UINT16_MAX, Frame, Intrinsics
from drivers.errors import DeviceSpecError, RecordingError
from drivers.files import read_toml
from drivers.formats.npz import Archive, Member, is_numeric, open_archive
from drivers.lens_model import lens_fields
from drivers.limits import image_size_problem
from drivers.values import NumberError, short_repr, to_number

log = logging.getLogger(__name__)

FORMAT_VERSION = 1
FRAMES_FILE = "frames.npz"
META_FILE = "recording.toml"
DEPTH_MEMBER = "depth_mm.npy"
MAX_FRAMES = 1_000_000  # 9 hours at 30 frames/s; bounds the small arrays (timestamps: 8 MB)


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


def _intrinsics_from_meta(table: Any, shape: tuple[int, int], where: Path) -> Intrinsics:
    if not isinstance(table, dict):
        raise RecordingError(
            f"{where}: [intrinsics] table is missing", hint="add width, height, fx, fy, cx, cy"
        )
    values: dict[str, int | float | str] = {}
    for key in ("width", "height", "fx", "fy", "cx", "cy"):
        if key not in table:
            raise RecordingError(f"{where}: [intrinsics] lacks {key!r}")
        try:
            values[key] = to_number(table[key], integer=key in ("width", "height"))
        except NumberError as exc:
            raise RecordingError(
                f"{where}: [intrinsics] {key} = {short_repr(table[key])} {exc}"
            ) from None
    try:  # the lens: none in recordings of a pinhole (and those older than the lens models)
        values |= lens_fields(table)
    except ValueError as exc:
        raise RecordingError(f"{where}: [intrinsics] {exc}") from None
    try:
        intr = Intrinsics(**values)  # type: ignore[arg-type]
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
    if arr.shape != (4,) or arr.dtype.kind not in "iuf":
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
    if not os.path.lexists(meta_path):
        raise RecordingError(
            f"{folder}: not a depthnav recording (no {META_FILE})",
            hint="an interrupted `depthnav record` leaves no recording.toml; record again",
        )
    meta = read_toml(meta_path, what=META_FILE)
    version = meta.get("format_version")
    if isinstance(version, bool) or not isinstance(version, int) or version < 1:
        raise RecordingError(f"{meta_path}: format_version is missing or not a positive integer")
    if version > FORMAT_VERSION:
        raise RecordingError(
            f"{meta_path}: has format_version {short_repr(version)}; "
            f"this depthnav reads up to {FORMAT_VERSION}",
            hint="update depthnav",
        )
    return meta


def _depth(archive: Archive, bare: bool = False) -> Member:
    """The depth header, checked: ``depth_mm`` uint16 (N, H, W) (or, in a bare ``.npz``,
    ``depth_m`` float32/float64 metres), a size depthnav takes, all stored."""
    member = archive.member("depth_mm")
    if member is None and bare:
        member = archive.member("depth_m")
    if member is None:
        found = ", ".join(short_repr(n, 30) for n in archive.names()[:8]) or "none"
        raise RecordingError(
            f"{archive.path}: has no 'depth_mm' array (found: {found})",
            hint="depth_mm: uint16 (N, H, W) millimetres"
            + ("; or depth_m: float32 (N, H, W) metres" if bare else ""),
        )
    shape = member.shape
    if member.name == "depth_m":
        dtype_ok = member.dtype.kind == "f" and member.dtype.itemsize in (4, 8)
    else:
        dtype_ok = member.dtype == np.uint16
    if not dtype_ok or len(shape) != 3 or min(shape) < 1:  # noqa: PLR2004
        what = "float32 or float64 metres" if member.name == "depth_m" else "uint16"
        hint = None
        if member.name == "depth_mm" and member.dtype.kind == "f":
            hint = "store float depth in metres as 'depth_m' (a bare .npz), or uint16 millimetres"
        raise RecordingError(
            f"{archive.path}: {member.name!r} must be {what} (N, H, W) with N >= 1, "
            f"got {member.dtype} {shape}",
            hint=hint,
        )
    problem = image_size_problem(shape[2], shape[1])
    if problem:
        raise RecordingError(f"{archive.path}: {member.name!r} holds {problem}")
    if shape[0] > MAX_FRAMES:
        raise RecordingError(
            f"{archive.path}: {member.name!r} holds {shape[0]} frames, more than the "
            f"{MAX_FRAMES} a recording may have",
            hint="split it into several recordings",
        )
    return member


MAX_DEPTH_M = 65.535  # the largest depth uint16 millimetres hold


def metres_to_mm(depth_m: npt.NDArray[np.floating], where: Path) -> npt.NDArray[np.uint16]:
    """Float metres (any shape) as uint16 millimetres, rounded as the pipeline's depth_to_mm:
    NaN, inf, 0 and negative depths become 0 (no reading); finite depths beyond 65.535 m become
    0 as well, with a warning (a rendered sky at 1e10 m is no reading, not an error)."""
    with np.errstate(invalid="ignore", over="ignore"):
        mm = np.rint(depth_m.astype(np.float64) * MM_PER_M)
    finite = np.isfinite(mm)
    far = finite & (mm > UINT16_MAX)
    if far.any():
        log.warning(
            "%s: %d depths beyond %g m (the uint16 millimetre limit) read as no reading",
            where,
            int(far.sum()),
            MAX_DEPTH_M,
        )
    return np.where(finite & (mm > 0) & ~far, mm, 0).astype(np.uint16)


def _small(archive: Archive, name: str, shape: tuple[int, ...], what: str) -> Any:
    """Array ``name`` if it holds numbers of ``shape``: checked from its header, then decoded."""
    member = archive.member(name)
    if member is None:
        return None
    if member.shape != shape or not is_numeric(member):
        raise RecordingError(
            f"{archive.path}: {name!r} must be {what}, got {member.dtype} {member.shape}"
        )
    return archive.read(member)


def _small_arrays(archive: Archive, n: int, with_intrinsics: bool) -> dict[str, Any]:
    """The small arrays of an N-frame recording, each decoded only after its header is checked
    (``intrinsics`` only when recording.toml does not give them)."""
    arrays = {
        "timestamp_s": _small(archive, "timestamp_s", (n,), f"{n} numbers"),
        "accel_mps2": _small(archive, "accel_mps2", (n, 3), f"({n}, 3) numbers"),
        "odom": _small(archive, "odom", (n, 3), f"({n}, 3) numbers [x_m, y_m, yaw_rad]"),
    }
    if with_intrinsics:
        arrays["intrinsics"] = _small(archive, "intrinsics", (4,), "4 numbers [fx, fy, cx, cy]")
    return {k: v for k, v in arrays.items() if v is not None}


def _checked_stamps(
    stamps: npt.NDArray[Any] | None, n: int, npz_path: Path, default_fps: float
) -> npt.NDArray[np.float64]:
    if stamps is None:
        return np.arange(n, dtype=np.float64) / default_fps
    stamps = stamps.astype(np.float64)
    if not np.all(np.isfinite(stamps)) or np.any(np.diff(stamps) < 0):
        raise RecordingError(f"{npz_path}: 'timestamp_s' must be finite and non-decreasing")
    return stamps


def _checked_accel(
    accel: npt.NDArray[Any] | None, npz_path: Path
) -> npt.NDArray[np.float64] | None:
    if accel is None:
        return None
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
    # rows outside the odometry limits (NaN, 1e19, a uint64's maximum) are kept as they are: the
    # memory refuses those frames' poses, one warning per kind (drivers.base.check_odom_pose),
    # and the rest of the recording plays on
    with np.errstate(over="ignore", invalid="ignore"):
        return odom.astype(np.float64)


def _locate(path: str | os.PathLike[str]) -> tuple[Path, dict[str, Any], Path]:
    """(the path, its recording.toml or {} for a bare .npz, the .npz holding the frames)."""
    where = Path(path)
    if where.is_dir():
        return where, _read_meta(where), where / FRAMES_FILE
    if where.suffix.lower() == ".npz" or os.path.lexists(where):
        return where, {}, where
    raise RecordingError(f"{where}: no such file or folder", hint="check the path")


def _described(
    where: Path,
    meta: dict[str, Any],
    npz_path: Path,
    arrays: dict[str, npt.NDArray[Any]],
    shape: tuple[int, int, int],
    default_fps: float,
    intrinsics_override: Mapping[str, float] | None = None,
) -> dict[str, Any]:
    """Everything of a recording but its depth, checked against the depth's (N, H, W).

    ``intrinsics_override`` (fx, fy, cx, cy, pixels) stands in for intrinsics the file lacks.
    """
    n, image = shape[0], (shape[1], shape[2])
    if "intrinsics" in meta:
        intr = _intrinsics_from_meta(meta["intrinsics"], image, where / META_FILE)
    elif "intrinsics" in arrays:
        intr = intrinsics_from_array(arrays["intrinsics"], image, npz_path)
    elif intrinsics_override and all(k in intrinsics_override for k in ("fx", "fy", "cx", "cy")):
        keys = ("fx", "fy", "cx", "cy", *DISTORTION_KEYS)
        values = {k: float(v) for k, v in intrinsics_override.items() if k in keys}
        try:
            intr = Intrinsics(image[1], image[0], **values)
        except ValueError as exc:
            raise DeviceSpecError(
                f"{npz_path}: intrinsics options do not fit the {image[1]}x{image[0]} image: {exc}"
            ) from None
    else:
        raise RecordingError(
            f"{npz_path}: has no 'intrinsics' array [fx, fy, cx, cy]",
            hint="add one, or give them in the spec: replay:PATH?fx=..&fy=..&cx=..&cy=..",
        )
    truth = meta.get("truth", {})
    return {
        "intrinsics": intr,
        "timestamp_s": _checked_stamps(arrays.get("timestamp_s"), n, npz_path, default_fps),
        "accel_mps2": _checked_accel(arrays.get("accel_mps2"), npz_path),
        "odom": _checked_odom(arrays.get("odom"), n, npz_path),
        "description": str(meta.get("description", "")),
        "device": str(meta.get("device", "")),
        "truth": truth if isinstance(truth, dict) else {},
    }


def read_recording(
    path: str | os.PathLike[str],
    default_fps: float = 30.0,
    max_depth_bytes: int | None = None,
    intrinsics_override: Mapping[str, float] | None = None,
) -> Recording:
    """Load a recording folder or a bare ``.npz``, every frame decompressed into memory.

    Args:
        path: a recording folder (``recording.toml`` + ``frames.npz``) or an ``.npz`` file.
        default_fps: frame rate assumed when the file has no timestamps, frames per second.
        max_depth_bytes: refuse (before decoding) depth frames larger than this, bytes; the
            limit applies to exactly the member that is decoded.
        intrinsics_override: fx, fy, cx, cy (pixels) for a file that has no intrinsics.

    Raises:
        RecordingError: missing, corrupt, truncated, inconsistent or too big; the message names
            the file.
    """
    where, meta, npz_path = _locate(path)
    with open_archive(npz_path) as archive:
        member = _depth(archive, bare=not meta)
        if max_depth_bytes is not None and member.nbytes > max_depth_bytes:
            raise RecordingError(
                f"{npz_path}: {member.name!r} decodes to {member.nbytes} bytes, more than the "
                f"{max_depth_bytes} allowed here (changed while being opened?)"
            )
        depth = archive.read(member)
        arrays = _small_arrays(archive, member.shape[0], "intrinsics" not in meta)
    if depth.dtype.kind == "f":
        depth = metres_to_mm(depth, npz_path)
    shape = (member.shape[0], member.shape[1], member.shape[2])
    described = _described(where, meta, npz_path, arrays, shape, default_fps, intrinsics_override)
    return Recording(depth_mm=depth, **described)


# --- streaming: one frame in memory at a time -------------------------------------------------
def recording_depth_nbytes(path: str | os.PathLike[str]) -> int:
    """Decoded size of a recording's depth frames, bytes, from the .npy header alone.

    Raises:
        RecordingError: no such file, not a readable .npz, or a ``depth_mm`` depthnav refuses.
    """
    where = Path(path)
    with open_archive(where / FRAMES_FILE if where.is_dir() else where) as archive:
        return _depth(archive, bare=not where.is_dir()).nbytes


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
    bare: bool = False  # a bare .npz (may hold float 'depth_m')

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
        with open_archive(self.npz_path) as archive:
            member = _depth(archive, bare=self.bare)
            if (member.shape, member.fortran_order) != (self.shape, False):
                raise RecordingError(f"{self.npz_path}: changed while being replayed")
            frame_bytes = height * width * member.dtype.itemsize
            with archive.data(member) as fid:
                for i in range(n):
                    data = fid.read(frame_bytes)
                    if len(data) != frame_bytes:
                        raise EOFError(f"{member.name!r} ends in frame {i} of {n}")
                    frame = np.frombuffer(data, dtype=member.dtype).reshape(height, width)
                    if member.dtype.kind == "f":  # float metres, bare .npz only
                        frame = metres_to_mm(frame, self.npz_path)
                    yield frame
                if member.stored_bytes == member.nbytes:
                    fid.read(1)  # to the end of the member, where zipfile checks its CRC-32


def open_recording_stream(
    path: str | os.PathLike[str],
    default_fps: float = 30.0,
    intrinsics_override: Mapping[str, float] | None = None,
) -> RecordingStream:
    """Open a recording folder or a bare ``.npz`` for reading frame by frame.

    Only the metadata and the small arrays (timestamps, accelerometer, intrinsics) are loaded;
    the depth frames are decompressed by ``RecordingStream.iter_depth``.

    Args:
        path: a recording folder (``recording.toml`` + ``frames.npz``) or an ``.npz`` file.
        default_fps: frame rate assumed when the file has no timestamps, frames per second.
        intrinsics_override: fx, fy, cx, cy (pixels) for a file that has no intrinsics.

    Raises:
        RecordingError: missing, corrupt or inconsistent, or ``depth_mm`` not stored as uint16
            in C order; the message names the file.
    """
    where, meta, npz_path = _locate(path)
    with open_archive(npz_path) as archive:
        member = _depth(archive, bare=not meta)
        if member.fortran_order:
            raise RecordingError(
                f"{npz_path}: {member.name!r} must be "
                f"{'float' if member.name == 'depth_m' else 'uint16'} (N, H, W) in C order, "
                f"got {member.dtype} {member.shape} in Fortran order",
                hint="save it again with np.ascontiguousarray(depth_mm)",
            )
        arrays = _small_arrays(archive, member.shape[0], "intrinsics" not in meta)
    shape = (member.shape[0], member.shape[1], member.shape[2])
    return RecordingStream(
        npz_path=npz_path,
        shape=shape,
        bare=not meta,
        **_described(where, meta, npz_path, arrays, shape, default_fps, intrinsics_override),
    )
