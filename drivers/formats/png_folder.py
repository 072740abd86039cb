"""Folders of 16-bit PNG depth images (TUM RGB-D style), read and written.

Layout: ``depth.txt`` with lines ``<timestamp_s> <relative/path.png>`` (``#`` comments allowed), or,
without it, every ``*.png`` in the folder (and in ``depth/``) in name order at a fixed frame rate.
Pixel values are depth units, ``scale`` of them per metre (TUM: 5000; 1000 means millimetres),
0 = no reading. Intrinsics and scale come from a sidecar ``camera.toml``::

    depth_scale = 5000          # units per metre
    [intrinsics]
    fx = 525.0
    fy = 525.0
    cx = 319.5
    cy = 239.5
    k1 = -0.28                  # optional lens distortion (plumb_bob: k1 k2 p1 p2 k3), 0 if absent

or from the replay spec options ``fx``, ``fy``, ``cx``, ``cy``, ``k1``.. ``k3``, ``scale`` (which
win).
"""

from __future__ import annotations

import itertools
import logging
import os
import struct
from collections.abc import Iterable, Iterator
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt
from PIL import Image, UnidentifiedImageError

from drivers.base import DISTORTION_KEYS, MM_PER_M, UINT16_MAX, Frame, Intrinsics
from drivers.errors import RecordingError
from drivers.files import INDEX_MAX_BYTES, check_regular, open_input, read_bytes, read_toml
from drivers.limits import image_size_problem
from drivers.values import NumberError, short_repr, short_text, to_number

log = logging.getLogger(__name__)

SIDECAR = "camera.toml"
INDEX = "depth.txt"
MAX_SCALE = 1e6  # depth units per metre


MAX_PNG_BYTES = 256 << 20  # a 8192x8192 16-bit PNG is 128 MiB uncompressed
_PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
_IHDR = struct.Struct(">I4sII")  # chunk length, b"IHDR", width, height


def is_png_folder(folder: Path) -> bool:
    """True if the folder looks like a PNG depth folder."""
    return (
        os.path.lexists(folder / INDEX)
        or any(folder.glob("*.png"))
        or any(folder.glob("depth/*.png"))
    )


def _index_line(index: Path, number: int, text: str, folder: Path) -> tuple[float, Path]:
    """(timestamp_s, image path) of one ``depth.txt`` line, both checked."""
    parts = text.split()
    if len(parts) < 2:  # noqa: PLR2004 - timestamp and file name
        raise RecordingError(
            f"{index}:{number}: expected '<timestamp_s> <file.png>', got {short_repr(text)}"
        )
    try:
        stamp = float(to_number(parts[0], low=-1e12, high=1e12))
    except NumberError as exc:
        raise RecordingError(
            f"{index}:{number}: timestamp {short_repr(parts[0])} {exc}",
            hint="timestamps are finite numbers of seconds",
        ) from None
    path = folder / parts[1]
    # ../, /abs or a symlink out (realpath, unlike Path.resolve, never raises on a symlink loop)
    if not Path(os.path.realpath(path)).is_relative_to(os.path.realpath(folder)):
        raise RecordingError(
            f"{index}:{number}: {short_text(parts[1], 80)} is outside the recording folder",
            hint="depth.txt names images inside its own folder",
        )
    if not os.path.lexists(path):
        raise RecordingError(
            f"{index}:{number}: names {short_text(parts[1], 80)}, which is missing"
        )
    check_regular(path)  # a FIFO, a device or a folder is refused now, not at its frame
    return stamp, path


def list_frames(folder: Path, fps: float) -> list[tuple[float, Path]]:
    """(timestamp_s from the first frame, path) for every depth image, in playback order."""
    index = folder / INDEX
    items: list[tuple[float, Path]] = []
    if os.path.lexists(index):
        text = read_bytes(index, what="frame index", max_bytes=INDEX_MAX_BYTES)
        for number, raw in enumerate(text.decode("utf-8", errors="replace").splitlines(), 1):
            line = raw.strip()
            if line and not line.startswith("#"):
                items.append(_index_line(index, number, line, folder))
        if items and any(b[0] < a[0] for a, b in itertools.pairwise(items)):
            raise RecordingError(f"{index}: timestamps go backwards")
    else:
        paths = sorted(folder.glob("*.png")) or sorted(folder.glob("depth/*.png"))
        items = [(i / fps, p) for i, p in enumerate(paths)]
    if not items:
        raise RecordingError(f"{folder}: no depth images (*.png or {INDEX})")
    t0 = items[0][0]
    return [(t - t0, p) for t, p in items]


SIDECAR_KEYS = ("depth_scale", "intrinsics")
INTRINSICS_KEYS = ("width", "height", "fx", "fy", "cx", "cy", *DISTORTION_KEYS)
TUM_SCALE = 5000.0
TUM_MARK = b"rgbd_dataset_"  # TUM RGB-D's depth.txt names its bag: "# file: 'rgbd_dataset_..."
SCALE_HINT = (
    "say how many depth units make a metre: scale=1000 for millimetre PNGs (most sensors and "
    "tools), scale=5000 for TUM RGB-D; as replay:PATH?scale=1000 or depth_scale = 1000 in "
    "camera.toml"
)


def read_sidecar(folder: Path) -> dict[str, Any]:
    """The sidecar ``camera.toml`` as a dict, {} when absent.

    Raises:
        RecordingError: unreadable, or a key it does not know (listing the valid ones: a
            misspelt ``scale`` must not silently fall back to a default).
    """
    path = folder / SIDECAR
    if not os.path.lexists(path):
        return {}
    side = read_toml(path, what=SIDECAR)
    for key, value in side.items():
        if key not in SIDECAR_KEYS:
            raise RecordingError(
                f"{path}: unknown key {short_text(str(key))!r} (valid: {', '.join(SIDECAR_KEYS)})",
                hint="depth_scale = units per metre; [intrinsics] fx, fy, cx, cy in pixels, "
                "optional lens k1, k2, p1, p2, k3",
            )
        if key == "intrinsics" and isinstance(value, dict):
            for sub in value:
                if sub not in INTRINSICS_KEYS:
                    raise RecordingError(
                        f"{path}: unknown key [intrinsics] {short_text(str(sub))!r} "
                        f"(valid: {', '.join(INTRINSICS_KEYS)})"
                    )
    return side


def is_tum(folder: Path) -> bool:
    """True for a TUM RGB-D folder: its depth.txt header names the dataset's bag."""
    index = folder / INDEX
    if not os.path.lexists(index):
        return False
    head = read_bytes(index, what="frame index", max_bytes=INDEX_MAX_BYTES)[:512]
    return TUM_MARK in head


def sidecar_scale(folder: Path, side: dict[str, Any]) -> float:
    """The sidecar's ``depth_scale`` (units per metre); 5000 for a TUM RGB-D folder.

    A wrong scale is silently wrong everywhere downstream (a millimetre folder read at 5000
    units per metre puts every obstacle at a fifth of its range), so it must be stated.

    Raises:
        RecordingError: no scale and not a TUM folder (with the common values); not a number in
            1..1e6 (0 would divide by zero, text would not parse).
    """
    if "depth_scale" not in side:
        if is_tum(folder):
            log.info("%s: a TUM RGB-D folder: %g depth units per metre", folder, TUM_SCALE)
            return TUM_SCALE
        raise RecordingError(
            f"{folder}: the depth scale is not stated (no depth_scale in {SIDECAR}, no scale=)",
            hint=SCALE_HINT,
        )
    value = side["depth_scale"]
    try:
        if isinstance(value, str):
            raise NumberError("is text")
        return float(to_number(value, low=1.0, high=MAX_SCALE))
    except NumberError:
        raise RecordingError(
            f"{folder / SIDECAR}: depth_scale = {short_repr(value)} is not a number in 1..1000000",
            hint="units per metre: 5000 for TUM, 1000 for millimetres",
        ) from None


def sidecar_intrinsics(
    folder: Path, side: dict[str, Any], shape: tuple[int, ...]
) -> Intrinsics | None:
    """The sidecar's ``[intrinsics]`` for (H, W) images, or None when it has none."""
    table = side.get("intrinsics")
    if not isinstance(table, dict):
        return None
    where = folder / SIDECAR
    values = {}
    for key in ("fx", "fy", "cx", "cy", *DISTORTION_KEYS):
        if key not in table:
            if key in DISTORTION_KEYS:
                continue  # no lens coefficient: an ideal pinhole
            raise RecordingError(f"{where}: bad [intrinsics]: {key!r} is missing")
        if isinstance(table[key], str):
            raise RecordingError(f"{where}: bad [intrinsics]: {key} is text, not a number")
        try:
            values[key] = float(to_number(table[key]))
        except NumberError as exc:
            raise RecordingError(
                f"{where}: bad [intrinsics]: {key} = {short_repr(table[key])} {exc}"
            ) from None
    try:
        return Intrinsics(shape[1], shape[0], **values)
    except ValueError as exc:
        raise RecordingError(f"{where}: bad [intrinsics]: {exc}") from None


def _png_size(head: bytes) -> tuple[int, int] | None:
    """(width, height) from a PNG's IHDR chunk, or None if ``head`` is not a PNG's start."""
    if len(head) < len(_PNG_SIGNATURE) + _IHDR.size or not head.startswith(_PNG_SIGNATURE):
        return None
    _, kind, width, height = _IHDR.unpack_from(head, len(_PNG_SIGNATURE))
    return (width, height) if kind == b"IHDR" else None


def read_depth_png(path: Path, scale: float) -> npt.NDArray[np.uint16]:
    """One 16-bit PNG as (H, W) uint16 millimetres, given ``scale`` units per metre.

    The size in the PNG's header is checked (drivers.limits) before anything is decoded: a PNG
    claiming 20000x20000 pixels is one line, not Pillow's DecompressionBombError, and a 12000 x
    12000 one is refused before its 3 GB are allocated.
    """
    with open_input(path, what="depth image", max_bytes=MAX_PNG_BYTES) as fh:
        size = _png_size(fh.read(len(_PNG_SIGNATURE) + _IHDR.size))
        if size is None:
            raise RecordingError(f"{path}: not a PNG file", hint="the file is corrupt or truncated")
        problem = image_size_problem(*size)
        if problem:
            raise RecordingError(f"{path}: {problem}")
        fh.seek(0)
        try:
            with Image.open(fh, formats=["PNG"]) as img:
                img.load()
                if img.mode not in ("I;16", "I;16B", "I;16L", "I"):
                    raise RecordingError(
                        f"{path}: a {img.mode} image, expected 16-bit greyscale depth"
                    )
                raw = np.asarray(img)
        except Image.DecompressionBombError as exc:
            raise RecordingError(f"{path}: too big to decode ({exc})") from None
        except (UnidentifiedImageError, OSError, SyntaxError, ValueError, EOFError) as exc:
            raise RecordingError(
                f"{path}: not a readable PNG ({short_text(str(exc), 120)})",
                hint="the file is corrupt or truncated",
            ) from None
    if raw.ndim != 2 or raw.min() < 0 or raw.max() > UINT16_MAX:  # noqa: PLR2004 - (H, W)
        raise RecordingError(f"{path}: not a single-channel 16-bit depth image")
    if scale == MM_PER_M:
        return raw.astype(np.uint16)
    mm = np.rint(raw.astype(np.float64) * (1000.0 / scale))
    return np.clip(mm, 0, 65535).astype(np.uint16)


def iter_png_folder(
    folder: Path, intrinsics: Intrinsics | None, scale: float, fps: float
) -> Iterator[tuple[float, npt.NDArray[np.uint16]]]:
    """Yield (timestamp_s, depth_mm (H, W)); every image must match ``intrinsics`` in size."""
    for stamp, path in list_frames(folder, fps):
        depth = read_depth_png(path, scale)
        if intrinsics is not None and depth.shape != (intrinsics.height, intrinsics.width):
            raise RecordingError(
                f"{path}: image is {depth.shape[1]}x{depth.shape[0]}, "
                f"the recording is {intrinsics.width}x{intrinsics.height}"
            )
        yield stamp, depth


def write_png_folder(
    folder: str | os.PathLike[str], frames: Iterable[Frame], scale: float = 5000.0
) -> int:
    """Write frames as a TUM-style PNG folder with ``depth.txt`` and ``camera.toml``.

    Raises:
        RecordingError: the folder is not empty, or a depth value does not fit 16 bits at ``scale``.
    """
    out = Path(folder)
    if out.exists() and any(out.iterdir()):
        raise RecordingError(f"{out}: folder is not empty; refusing to overwrite")
    (out / "depth").mkdir(parents=True, exist_ok=True)
    lines = ["# depth maps written by depthnav", "# timestamp filename"]
    intr: Intrinsics | None = None
    for frame in frames:
        intr = frame.intrinsics
        units = np.rint(frame.depth_mm.astype(np.float64) * (scale / 1000.0))
        if units.max(initial=0) > UINT16_MAX:
            raise RecordingError(
                f"{out}: frame {frame.seq} has depth beyond 16 bits at scale {scale:g}"
            )
        name = f"depth/{frame.timestamp_s:.6f}.png"
        Image.fromarray(units.astype(np.uint16)).save(out / name)
        lines.append(f"{frame.timestamp_s:.6f} {name}")
    if intr is None:
        raise RecordingError(f"{out}: no frames to write")
    (out / INDEX).write_text("\n".join(lines) + "\n", encoding="utf-8")
    (out / SIDECAR).write_text(
        f"depth_scale = {scale!r}\n\n[intrinsics]\nwidth = {intr.width}\nheight = {intr.height}\n"
        f"fx = {intr.fx!r}\nfy = {intr.fy!r}\ncx = {intr.cx!r}\ncy = {intr.cy!r}\n"
        + "".join(
            f"{key} = {float(value)!r}\n"
            for key, value in zip(DISTORTION_KEYS, intr.distortion, strict=True)
            if intr.has_distortion
        ),
        encoding="utf-8",
    )
    return len(lines) - 2
