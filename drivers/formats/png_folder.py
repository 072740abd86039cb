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

or from the replay spec options ``fx``, ``fy``, ``cx``, ``cy``, ``scale`` (which win).
"""

from __future__ import annotations

import itertools
import logging
import math
import os
import tomllib
from collections.abc import Iterable, Iterator
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt
from PIL import Image, UnidentifiedImageError

from drivers.base import MM_PER_M, UINT16_MAX, Frame, Intrinsics
from drivers.errors import RecordingError

log = logging.getLogger(__name__)

SIDECAR = "camera.toml"
INDEX = "depth.txt"
MAX_SCALE = 1e6  # depth units per metre


def is_png_folder(folder: Path) -> bool:
    """True if the folder looks like a PNG depth folder."""
    return (
        (folder / INDEX).is_file() or any(folder.glob("*.png")) or any(folder.glob("depth/*.png"))
    )


def list_frames(folder: Path, fps: float) -> list[tuple[float, Path]]:
    """(timestamp_s from the first frame, path) for every depth image, in playback order."""
    index = folder / INDEX
    items: list[tuple[float, Path]] = []
    if index.is_file():
        for number, line in enumerate(
            index.read_text(encoding="utf-8", errors="replace").splitlines(), 1
        ):
            text = line.strip()
            if not text or text.startswith("#"):
                continue
            parts = text.split()
            try:
                stamp = float(parts[0])
                path = folder / parts[1]
            except (ValueError, IndexError):
                raise RecordingError(
                    f"{index}:{number}: expected '<timestamp_s> <file.png>', got {text!r}"
                ) from None
            root = folder.resolve()
            if not path.resolve().is_relative_to(root):  # ../, an absolute path or a symlink out
                raise RecordingError(
                    f"{index}:{number}: {parts[1]} is outside the recording folder",
                    hint="depth.txt names images inside its own folder",
                )
            if not path.is_file():
                raise RecordingError(f"{index}:{number}: names {parts[1]}, which is missing")
            items.append((stamp, path))
        if items and any(b[0] < a[0] for a, b in itertools.pairwise(items)):
            raise RecordingError(f"{index}: timestamps go backwards")
    else:
        paths = sorted(folder.glob("*.png")) or sorted(folder.glob("depth/*.png"))
        items = [(i / fps, p) for i, p in enumerate(paths)]
    if not items:
        raise RecordingError(f"{folder}: no depth images (*.png or {INDEX})")
    t0 = items[0][0]
    return [(t - t0, p) for t, p in items]


def read_sidecar(folder: Path) -> dict[str, Any]:
    """The sidecar ``camera.toml`` as a dict, {} when absent."""
    path = folder / SIDECAR
    if not path.is_file():
        return {}
    try:
        return tomllib.loads(path.read_text(encoding="utf-8"))
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
        raise RecordingError(f"{path}: not valid TOML ({exc})") from None


def sidecar_scale(folder: Path, side: dict[str, Any]) -> float:
    """The sidecar's ``depth_scale`` (units per metre), 5000 when absent.

    Raises:
        RecordingError: not a number in 1..1e6 (0 would divide by zero, text would not parse).
    """
    value = side.get("depth_scale", 5000.0)
    if (
        isinstance(value, bool)
        or not isinstance(value, (int, float))
        or not (math.isfinite(value) and 1.0 <= value <= MAX_SCALE)
    ):
        raise RecordingError(
            f"{folder / SIDECAR}: depth_scale = {value!r} is not a number in 1..1000000",
            hint="units per metre: 5000 for TUM, 1000 for millimetres",
        )
    return float(value)


def read_depth_png(path: Path, scale: float) -> npt.NDArray[np.uint16]:
    """One 16-bit PNG as (H, W) uint16 millimetres, given ``scale`` units per metre."""
    try:
        with Image.open(path) as img:
            img.load()
            if img.mode not in ("I;16", "I;16B", "I;16L", "I"):
                raise RecordingError(f"{path}: a {img.mode} image, expected 16-bit greyscale depth")
            raw = np.asarray(img)
    except (UnidentifiedImageError, OSError, SyntaxError, ValueError) as exc:
        raise RecordingError(
            f"{path}: not a readable PNG ({exc})", hint="the file is corrupt or truncated"
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
        f"fx = {intr.fx!r}\nfy = {intr.fy!r}\ncx = {intr.cx!r}\ncy = {intr.cy!r}\n",
        encoding="utf-8",
    )
    return len(lines) - 2
