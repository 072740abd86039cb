"""depthnav's recording format: a folder holding ``frames.npz`` and ``recording.toml``.

``frames.npz`` holds ``depth_mm`` (N, H, W) uint16, ``intrinsics`` float64 [fx, fy, cx, cy],
``timestamp_s`` (N,) float64 and, when every frame had one, ``accel_mps2`` (N, 3) float64.
``recording.toml`` holds ``format_version``, ``description``, ``device``, an ``[intrinsics]``
table and an optional ``[truth]`` table. A bare ``.npz`` with the same arrays is also readable.
"""

from __future__ import annotations

import contextlib
import logging
import math
import os
import tomllib
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, BinaryIO

import numpy as np
import numpy.typing as npt
import tomli_w

from drivers.base import Frame, Intrinsics
from drivers.errors import RecordingError

log = logging.getLogger(__name__)

FORMAT_VERSION = 1
FRAMES_FILE = "frames.npz"
META_FILE = "recording.toml"
_PARTIAL = ".partial"


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
    """

    depth_mm: npt.NDArray[np.uint16]
    intrinsics: Intrinsics
    timestamp_s: npt.NDArray[np.float64]
    accel_mps2: npt.NDArray[np.float64] | None = None
    description: str = ""
    device: str = ""
    truth: Mapping[str, Any] = field(default_factory=dict)

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
            )
            for i in range(len(self.depth_mm))
        ]


def _check_value(value: Any, where: str) -> None:
    """Recording metadata takes finite numbers, text, booleans and lists of them."""
    if isinstance(value, (list, tuple)):
        for v in value:
            _check_value(v, where)
    elif isinstance(value, float) and not math.isfinite(value):
        raise RecordingError(f"{where} = {value!r} is not a finite number")
    elif not isinstance(value, (bool, int, float, str)):
        raise RecordingError(
            f"{where} has a {type(value).__name__}; "
            "recording metadata takes numbers, text, booleans or lists"
        )


def _toml_document(meta: Mapping[str, Any], tables: Mapping[str, Mapping[str, Any]]) -> str:
    """The recording.toml text (tomli-w does the quoting and escaping)."""
    for key, value in meta.items():
        _check_value(value, key)
    for name, table in tables.items():
        for key, value in table.items():
            if not key.replace("_", "").isalnum():
                raise RecordingError(f"{name}.{key}: keys must be letters, digits and '_'")
            _check_value(value, f"{name}.{key}")
    return tomli_w.dumps({**meta, **{name: dict(t) for name, t in tables.items()}})


def write_recording(
    path: str | os.PathLike[str],
    frames: Iterable[Frame],
    *,
    description: str = "",
    truth: dict[str, Any] | None = None,
    device: str = "",
    progress: Callable[[int], None] | None = None,
) -> int:
    """Write frames as a depthnav recording folder.

    Every file is written under a ``.partial`` name inside ``path`` and renamed when complete;
    ``recording.toml`` comes last, so an interrupted write never looks like a recording.

    Args:
        path: the folder to create; it must not exist or must be empty.
        frames: frames with identical intrinsics.
        description: one line of free text.
        truth: optional ground truth, a flat table of numbers, text, booleans or lists.
        device: the device spec or name recorded from.
        progress: called with the number of frames collected so far.

    Returns:
        The number of frames written.

    Raises:
        RecordingError: folder not empty, no frames, frames that differ in size or intrinsics.
    """
    folder = Path(path)
    if folder.exists() and not folder.is_dir():
        raise RecordingError(f"{folder}: exists and is not a folder", hint="name a new folder")
    if folder.is_dir() and any(folder.iterdir()):
        raise RecordingError(
            f"{folder}: folder is not empty; refusing to overwrite", hint="name a new folder"
        )
    if truth is not None and not isinstance(truth, Mapping):
        raise RecordingError(f"{folder}: truth must be a table (dict), got {type(truth).__name__}")
    depth: list[npt.NDArray[np.uint16]] = []
    stamps: list[float] = []
    accels: list[tuple[float, float, float] | None] = []
    intrinsics: Intrinsics | None = None
    for frame in frames:
        if intrinsics is None:
            intrinsics = frame.intrinsics
        elif frame.intrinsics != intrinsics:
            raise RecordingError(
                f"{folder}: frame {frame.seq} has intrinsics {frame.intrinsics}, "
                f"the first frame had {intrinsics}",
                hint="a recording holds one camera setting; record each mode separately",
            )
        depth.append(np.array(frame.depth_mm, dtype=np.uint16, copy=True))
        stamps.append(float(frame.timestamp_s))
        accels.append(frame.accel_mps2)
        if progress is not None:
            progress(len(depth))
    if intrinsics is None:
        raise RecordingError(
            f"{folder}: no frames to write", hint="check that the device delivers frames"
        )
    arrays: dict[str, npt.NDArray[Any]] = {
        "depth_mm": np.stack(depth),
        "intrinsics": intrinsics.as_array(),
        "timestamp_s": np.asarray(stamps, dtype=np.float64),
    }
    if all(a is not None for a in accels):
        arrays["accel_mps2"] = np.asarray(accels, dtype=np.float64)
    elif any(a is not None for a in accels):
        log.warning("%s: only some frames had accelerometer data; not storing it", folder)
    meta = {"format_version": FORMAT_VERSION, "description": description, "device": device}
    tables: dict[str, Mapping[str, Any]] = {
        "intrinsics": {
            "width": intrinsics.width,
            "height": intrinsics.height,
            "fx": float(intrinsics.fx),
            "fy": float(intrinsics.fy),
            "cx": float(intrinsics.cx),
            "cy": float(intrinsics.cy),
        }
    }
    if truth:
        tables["truth"] = dict(truth)
    document = _toml_document(meta, tables)  # before any file exists, so bad truth writes nothing

    created = not folder.exists()
    npz_tmp = folder / (FRAMES_FILE + _PARTIAL)
    meta_tmp = folder / (META_FILE + _PARTIAL)
    try:
        folder.mkdir(parents=True, exist_ok=True)
        with _create_new(npz_tmp) as fh:
            np.savez_compressed(fh, **arrays)
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(npz_tmp, folder / FRAMES_FILE)
        with _create_new(meta_tmp) as fh:
            fh.write(document.encode("utf-8"))
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(meta_tmp, folder / META_FILE)
    except OSError as exc:
        # a full disk (ENOSPC), a file-size limit (EFBIG), a read-only mount: one line, and no
        # half-written recording left behind (the .partial files go in the finally below)
        (folder / FRAMES_FILE).unlink(missing_ok=True)
        raise RecordingError(
            f"{folder}: writing the recording failed: {exc.strerror or exc}",
            hint="free some disk space or record to another folder",
        ) from exc
    finally:
        for tmp in (npz_tmp, meta_tmp):
            with contextlib.suppress(OSError):
                tmp.unlink(missing_ok=True)
        if created and folder.is_dir() and not (folder / META_FILE).exists():
            with contextlib.suppress(OSError):
                folder.rmdir()  # only if empty: never remove anything that was there before
    log.info("wrote %d frames to %s", len(depth), folder)
    return len(depth)


def _create_new(path: Path) -> BinaryIO:
    """Open ``path`` for writing only if nothing (not even a symlink) is there yet.

    O_EXCL keeps a write inside the folder it names: a planted ``frames.npz.partial`` symlink
    pointing elsewhere makes the write fail instead of following the link.
    """
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL | getattr(os, "O_NOFOLLOW", 0), 0o644)
    return os.fdopen(fd, "wb")


def _load_npz(path: Path) -> dict[str, npt.NDArray[Any]]:
    try:
        with np.load(path, allow_pickle=False) as npz:
            return {name: npz[name] for name in npz.files}
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


def _checked_depth(arrays: dict[str, npt.NDArray[Any]], npz_path: Path) -> npt.NDArray[np.uint16]:
    depth = arrays.get("depth_mm")
    if depth is None:
        raise RecordingError(
            f"{npz_path}: has no 'depth_mm' array (found: {', '.join(arrays) or 'none'})"
        )
    if depth.dtype != np.uint16 or depth.ndim != 3 or depth.shape[0] < 1:  # noqa: PLR2004
        raise RecordingError(
            f"{npz_path}: 'depth_mm' must be uint16 (N, H, W) with N >= 1, "
            f"got {depth.dtype} {depth.shape}"
        )
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


def read_recording(path: str | os.PathLike[str], default_fps: float = 30.0) -> Recording:
    """Load a recording folder or a bare ``.npz``.

    Args:
        path: a recording folder (``recording.toml`` + ``frames.npz``) or an ``.npz`` file.
        default_fps: frame rate assumed when the file has no timestamps, frames per second.

    Raises:
        RecordingError: missing, corrupt, truncated or inconsistent; the message names the file.
    """
    where = Path(path)
    meta: dict[str, Any] = {}
    if where.is_dir():
        meta = _read_meta(where)
        npz_path = where / FRAMES_FILE
    elif where.suffix.lower() == ".npz" or where.is_file():
        npz_path = where
    else:
        raise RecordingError(f"{where}: no such file or folder", hint="check the path")
    arrays = _load_npz(npz_path)
    depth = _checked_depth(arrays, npz_path)
    n, shape = depth.shape[0], (depth.shape[1], depth.shape[2])
    if "intrinsics" in meta:
        intr = _intrinsics_from_meta(meta["intrinsics"], shape, where / META_FILE)
    elif "intrinsics" in arrays:
        intr = intrinsics_from_array(arrays["intrinsics"], shape, npz_path)
    else:
        raise RecordingError(f"{npz_path}: has no 'intrinsics' array [fx, fy, cx, cy]")
    truth = meta.get("truth", {})
    return Recording(
        depth_mm=depth,
        intrinsics=intr,
        timestamp_s=_checked_stamps(arrays.get("timestamp_s"), n, npz_path, default_fps),
        accel_mps2=_checked_accel(arrays.get("accel_mps2"), n, npz_path),
        description=str(meta.get("description", "")),
        device=str(meta.get("device", "")),
        truth=truth if isinstance(truth, dict) else {},
    )
