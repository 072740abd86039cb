"""Writing depthnav recordings (the format is described in ``drivers.formats.recording``).

``write_recording`` holds one frame at a time: the frames wait in a temporary raw file in the
target folder (so recording needs free disk for them uncompressed until ``frames.npz`` is
written), which is then compressed into the archive in chunks.
"""

from __future__ import annotations

import contextlib
import errno
import logging
import math
import os
import zipfile
from array import array
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, Any, BinaryIO

import numpy as np
import numpy.typing as npt
import tomli_w

from drivers.base import Frame, Intrinsics
from drivers.errors import RecordingError
from drivers.formats.recording import DEPTH_MEMBER, FORMAT_VERSION, FRAMES_FILE, META_FILE
from drivers.lens_model import lens_table

log = logging.getLogger(__name__)

_PARTIAL = ".partial"
_RAW_FILE = "depth_mm.raw"  # the frames' bytes while recording, under its .partial name
_COPY_CHUNK_BYTES = 1 << 20  # memory of the final compression, bytes


def _check_value(value: Any, where: str) -> None:
    """Recording metadata takes finite numbers, UTF-8 text, booleans and lists of them."""
    if isinstance(value, (list, tuple)):
        for v in value:
            _check_value(v, where)
    elif isinstance(value, float) and not math.isfinite(value):
        raise RecordingError(f"{where} = {value!r} is not a finite number")
    elif isinstance(value, str):
        try:  # checked before the first frame: recording.toml is written after the last one
            value.encode("utf-8")
        except UnicodeEncodeError:
            raise RecordingError(
                f"{where} is not UTF-8 text (it holds bytes of another encoding)"
            ) from None
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
    progress_compress: Callable[[int, int], None] | None = None,
) -> int:
    """Write frames as a depthnav recording folder, holding one frame in memory at a time.

    Each frame's bytes go to a temporary file in ``path`` as it arrives; ``frames.npz`` is
    compressed from that file at the end. Every file is written under a ``.partial`` name and
    renamed when complete; ``recording.toml`` comes last, so an interrupted write never looks
    like a recording. When ``frames`` ends early (a stop), the frames it gave are written.

    Args:
        path: the folder to create; it must not exist or must be empty.
        frames: frames with identical intrinsics.
        description: one line of free text.
        truth: optional ground truth, a flat table of numbers, text, booleans or lists.
        device: the device spec or name recorded from.
        progress: called with the number of frames taken so far, after each frame.
        progress_compress: called with (bytes compressed, total bytes) of the depth frames
            while ``frames.npz`` is written.

    Returns:
        The number of frames written.

    Raises:
        RecordingError: folder not empty, no frames, frames that differ in size or intrinsics,
            a write that fails (full disk).
    """
    folder = Path(path)
    _check_target(folder)
    if truth is not None and not isinstance(truth, Mapping):
        raise RecordingError(f"{folder}: truth must be a table (dict), got {type(truth).__name__}")
    # checked before any file exists (and before the frames come), so bad truth writes nothing
    _toml_document({"description": description, "device": device}, {"truth": dict(truth or {})})
    created = not folder.exists()
    raw_tmp = folder / (_RAW_FILE + _PARTIAL)
    try:
        try:
            folder.mkdir(parents=True, exist_ok=True)
            raw = _create_new(raw_tmp, readable=True)
        except OSError as exc:
            raise _write_failed(folder, exc) from exc
        with raw:
            kept = _spool_frames(raw, frames, folder, progress)
            document = _meta_document(kept.intrinsics, description, device, truth)
            try:
                raw.seek(0)
                _write_new(
                    folder / FRAMES_FILE, lambda fh: _write_npz(fh, raw, kept, progress_compress)
                )
                raw_tmp.unlink()  # its disk space is free before the metadata needs any
                _write_new(folder / META_FILE, lambda fh: fh.write(document.encode("utf-8")))
            except OSError as exc:
                # a full disk (ENOSPC), a file-size limit (EFBIG), a read-only mount: one line,
                # and no half-written recording left behind (.partial files go in the finally)
                (folder / FRAMES_FILE).unlink(missing_ok=True)
                raise _write_failed(folder, exc) from exc
    finally:
        for name in (_RAW_FILE, FRAMES_FILE, META_FILE):
            with contextlib.suppress(OSError):
                (folder / (name + _PARTIAL)).unlink(missing_ok=True)
        if created and folder.is_dir() and not (folder / META_FILE).exists():
            with contextlib.suppress(OSError):
                folder.rmdir()  # only if empty: never remove anything that was there before
    log.info("wrote %d frames to %s", kept.count, folder)
    return kept.count


def _check_target(folder: Path) -> None:
    """Refuse a target that is a file or a folder with something in it."""
    if folder.exists() and not folder.is_dir():
        raise RecordingError(f"{folder}: exists and is not a folder", hint="name a new folder")
    if folder.is_dir() and any(folder.iterdir()):
        raise RecordingError(
            f"{folder}: folder is not empty; refusing to overwrite", hint="name a new folder"
        )


def _write_failed(folder: Path, exc: OSError) -> RecordingError:
    return RecordingError(
        f"{folder}: writing the recording failed: {exc.strerror or exc}",
        hint="free some disk space or record to another folder",
    )


@dataclass(slots=True)
class _Kept:
    """What write_recording holds in memory: everything but the depth frames.

    Attributes:
        intrinsics: the first frame's intrinsics (None before the first frame).
        stamps: timestamp of each frame, seconds.
        accel: 3 values a frame, m/s^2 (zeros where a frame had none).
        with_accel: how many frames had accelerometer data.
        odom: 3 values a frame, [x_m, y_m, yaw_rad] (zeros where a frame had none).
        with_odom: how many frames had odometry.
    """

    intrinsics: Intrinsics | None = None
    stamps: array = field(default_factory=lambda: array("d"))
    accel: array = field(default_factory=lambda: array("d"))
    with_accel: int = 0
    odom: array = field(default_factory=lambda: array("d"))
    with_odom: int = 0

    @property
    def count(self) -> int:
        return len(self.stamps)


def _spool_frames(
    raw: BinaryIO, frames: Iterable[Frame], folder: Path, progress: Callable[[int], None] | None
) -> _Kept:
    """Append each frame's depth to ``raw`` as little-endian uint16, C order; keep the rest."""
    kept = _Kept()
    for frame in frames:
        if kept.intrinsics is None:
            _check_reads_back(frame.intrinsics, folder)
            kept.intrinsics = frame.intrinsics
        elif frame.intrinsics != kept.intrinsics:
            raise RecordingError(
                f"{folder}: frame {frame.seq} has intrinsics {frame.intrinsics}, "
                f"the first frame had {kept.intrinsics}",
                hint="a recording holds one camera setting; record each mode separately",
            )
        depth = np.ascontiguousarray(frame.depth_mm, dtype="<u2")
        if depth.shape != (kept.intrinsics.height, kept.intrinsics.width):
            raise RecordingError(
                f"{folder}: frame {frame.seq} is {depth.shape} but its intrinsics say "
                f"{kept.intrinsics.width}x{kept.intrinsics.height}"
            )
        try:
            raw.write(depth.data)
        except OSError as exc:
            raise _write_failed(folder, exc) from exc
        kept.stamps.append(float(frame.timestamp_s))
        kept.accel.extend(frame.accel_mps2 or (0.0, 0.0, 0.0))
        kept.with_accel += frame.accel_mps2 is not None
        kept.odom.extend(frame.odom or (0.0, 0.0, 0.0))
        kept.with_odom += frame.odom is not None
        if progress is not None:
            progress(kept.count)
    if kept.intrinsics is None:
        raise RecordingError(
            f"{folder}: no frames to write", hint="check that the device delivers frames"
        )
    if 0 < kept.with_accel < kept.count:
        log.warning("%s: only some frames had accelerometer data; not storing it", folder)
    if 0 < kept.with_odom < kept.count:
        log.warning("%s: only some frames had odometry; not storing it", folder)
    return kept


def _check_reads_back(intrinsics: Intrinsics, folder: Path) -> None:
    """Refuse, at the first frame, a camera the recording reader would not give back whole: a
    lens replayed as another model (a fisheye as plumb_bob) is a wrong lens, not a lossy one."""
    from drivers.formats.recording import _intrinsics_from_meta  # the reader's own parser

    shape = (intrinsics.height, intrinsics.width)
    try:
        back = _intrinsics_from_meta(intrinsics_table(intrinsics), shape, folder / META_FILE)
    except RecordingError:
        back = None
    if back != intrinsics:
        raise RecordingError(
            f"{folder}: the {intrinsics.distortion_model} lens of these frames would not read back "
            "from a depthnav recording's recording.toml",
            hint="record with --format png: its camera.toml carries every lens model",
        )


def intrinsics_table(intrinsics: Intrinsics) -> dict[str, Any]:
    """recording.toml's ``[intrinsics]``: the pinhole, and the lens only when there is one (a
    pinhole recording reads as before; plumb_bob as its coefficients, another model named)."""
    return {
        "width": intrinsics.width,
        "height": intrinsics.height,
        "fx": float(intrinsics.fx),
        "fy": float(intrinsics.fy),
        "cx": float(intrinsics.cx),
        "cy": float(intrinsics.cy),
    } | lens_table(intrinsics.distortion_model, intrinsics.distortion)


def _meta_document(
    intrinsics: Intrinsics | None, description: str, device: str, truth: Mapping[str, Any] | None
) -> str:
    """The recording.toml text."""
    assert intrinsics is not None
    meta = {"format_version": FORMAT_VERSION, "description": description, "device": device}
    tables: dict[str, Mapping[str, Any]] = {"intrinsics": intrinsics_table(intrinsics)}
    if truth:
        tables["truth"] = dict(truth)
    return _toml_document(meta, tables)


def _write_new(final: Path, write: Callable[[BinaryIO], object]) -> None:
    """Write ``final`` under its ``.partial`` name, fsync it, then rename it into place."""
    tmp = final.with_name(final.name + _PARTIAL)
    with _create_new(tmp) as fh:
        write(fh)
        fh.flush()
        os.fsync(fh.fileno())
    os.replace(tmp, final)


def _write_npz(
    fh: BinaryIO,
    raw: BinaryIO,
    kept: _Kept,
    progress_compress: Callable[[int, int], None] | None,
) -> None:
    """``frames.npz`` as np.savez_compressed writes it, its depth copied from ``raw`` in chunks."""
    intr = kept.intrinsics
    assert intr is not None
    small: dict[str, npt.NDArray[np.float64]] = {
        "intrinsics": intr.as_array(),
        "timestamp_s": np.frombuffer(kept.stamps, dtype=np.float64),
    }
    if kept.with_accel == kept.count:
        small["accel_mps2"] = np.frombuffer(kept.accel, dtype=np.float64).reshape(-1, 3)
    if kept.with_odom == kept.count:
        small["odom"] = np.frombuffer(kept.odom, dtype=np.float64).reshape(-1, 3)
    header = {
        "descr": np.lib.format.dtype_to_descr(np.dtype("<u2")),
        "fortran_order": False,
        "shape": (kept.count, intr.height, intr.width),
    }
    with zipfile.ZipFile(fh, mode="w", compression=zipfile.ZIP_DEFLATED) as npz:
        # force_zip64 as numpy does (gh-10776): the size is not known when the member starts
        with npz.open(DEPTH_MEMBER, "w", force_zip64=True) as member:
            np.lib.format.write_array_header_1_0(member, header)
            _copy_depth(raw, member, kept.count * intr.height * intr.width * 2, progress_compress)
        for name, values in small.items():
            with npz.open(name + ".npy", "w", force_zip64=True) as member:
                np.lib.format.write_array(member, values, allow_pickle=False)


def _copy_depth(
    src: BinaryIO,
    dst: IO[bytes],
    total: int,
    progress_compress: Callable[[int, int], None] | None,
) -> None:
    """Copy ``total`` bytes in chunks of _COPY_CHUNK_BYTES, reporting (done, total) after each."""
    buffer = memoryview(bytearray(max(min(_COPY_CHUNK_BYTES, total), 1)))
    done = 0
    while done < total:
        got = src.readinto(buffer[: min(len(buffer), total - done)])
        if not got:
            raise OSError(errno.EIO, "the temporary frame file ended early")
        dst.write(buffer[:got])
        done += got
        if progress_compress is not None:
            progress_compress(done, total)


def _create_new(path: Path, *, readable: bool = False) -> BinaryIO:
    """Open ``path`` for writing (and reading) only if nothing, not even a symlink, is there yet.

    O_EXCL keeps a write inside the folder it names: a planted ``frames.npz.partial`` symlink
    pointing elsewhere makes the write fail instead of following the link.
    """
    access = os.O_RDWR if readable else os.O_WRONLY
    flags = access | os.O_CREAT | os.O_EXCL | getattr(os, "O_NOFOLLOW", 0)
    fd = os.open(path, flags, 0o644)
    return os.fdopen(fd, "w+b" if readable else "wb")
