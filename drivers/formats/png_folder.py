"""Folders of 16-bit PNG or PGM depth images (TUM RGB-D style), read and written.

Which images (at a fixed frame rate unless ``depth.txt`` gives timestamps):
- the replay option ``glob=PATTERN`` (relative to the folder, e.g. ``*_depth.png``,
  ``depth/*.pgm``): the files it matches, in natural name order (2 before 10);
- else ``depth.txt`` with lines ``<timestamp_s> <relative/path.png>`` (``#`` comments allowed);
- else the folder's ``*.png`` and ``*.pgm`` files, or if none of them is depth those in
  ``depth/``, in natural name order. Colour images (RGB PNG, PPM, JPEG) and 8-bit images beside
  them are skipped, said in one INFO line (TUM's rgb/ + depth/, slambook's color/ + depth/,
  ``1.png`` beside ``1_depth.png``, ``N_depth_u16.png`` beside its ``N_depth_u8.png`` preview:
  what each file is comes from its header, drivers.formats.image_kinds); a folder of colour
  images only is refused in one line.

Images are read by drivers.formats.depth_images (16-bit single-channel PNG; binary PGM with
maxval above 255, big-endian as netpbm says). Pixel values are depth units, ``scale`` of them
per metre (TUM: 5000, assumed for a folder laid out as TUM's, drivers.formats.tum; 1000 means
millimetres), 0 = no reading. Intrinsics and scale come from
a sidecar ``camera.toml``::

    depth_scale = 5000          # units per metre
    [intrinsics]
    fx = 525.0
    fy = 525.0
    cx = 319.5
    cy = 239.5
    k1 = -0.28                  # optional lens distortion (plumb_bob: k1 k2 p1 p2 k3), 0 if absent

with, for other lenses, ``distortion_model = "rational_polynomial"`` (k1-k6, p1, p2) or
``"equidistant"`` (fisheye, k1-k4), as ROS CameraInfo names them (drivers.lens_model); or from the
replay spec options ``fx``, ``fy``, ``cx``, ``cy``, ``k1``.. ``k3``, ``scale`` (which win).
"""

from __future__ import annotations

import itertools
import logging
import os
from collections.abc import Iterable, Iterator
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt
from PIL import Image

from drivers.base import LENS_KEYS, UINT16_MAX, Frame, Intrinsics
from drivers.errors import RecordingError
from drivers.files import INDEX_MAX_BYTES, check_regular, read_bytes, read_toml
from drivers.formats.depth_images import MAX_IMAGE_BYTES, SUFFIXES, read_depth_image
from drivers.formats.image_kinds import DIGITS, image_kinds
from drivers.formats.tum import INDEX, TUM_SCALE, recognise_tum
from drivers.lens_model import lens_fields, lens_table
from drivers.values import NumberError, short_repr, short_text, to_number

log = logging.getLogger(__name__)

SIDECAR = "camera.toml"
MAX_SCALE = 1e6  # depth units per metre


MAX_PNG_BYTES = MAX_IMAGE_BYTES


def _images(where: Path) -> list[Path]:
    """The PNG and PGM files directly in ``where``, in natural name order (2.png before 10.png)."""
    try:
        names = [p for p in where.iterdir() if p.suffix.lower() in SUFFIXES]
    except OSError:  # not a folder, unreadable
        return []
    return sorted(names, key=_natural_key)


def _natural_key(path: Path) -> tuple[tuple[int, int | str], ...]:
    return tuple(
        (0, int(part)) if part.isdigit() else (1, part) for part in DIGITS.split(path.name) if part
    )


def is_png_folder(folder: Path) -> bool:
    """True if the folder looks like a folder of depth images (PNG or PGM)."""
    return os.path.lexists(folder / INDEX) or any(_images(w) for w in (folder, folder / "depth"))


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


def _globbed(folder: Path, pattern: str) -> list[Path]:
    """The files ``pattern`` (relative to the folder, ``*``, ``?``, ``[..]``, ``**``) matches."""
    if not pattern or Path(pattern).is_absolute() or ".." in Path(pattern).parts:
        raise RecordingError(
            f"glob={short_repr(pattern)} must be a pattern inside the folder, e.g. depth_*.png"
        )
    try:
        paths = [p for p in folder.glob(pattern) if not p.is_dir()]
    except (ValueError, OSError) as exc:
        raise RecordingError(f"glob={short_repr(pattern)}: {short_text(str(exc), 80)}") from None
    root = os.path.realpath(folder)
    for path in paths:  # a symlink out of the folder is not part of the recording
        if not Path(os.path.realpath(path)).is_relative_to(root):
            raise RecordingError(f"{path}: is outside the recording folder")
    if not paths:
        raise RecordingError(
            f"{folder}: glob={short_repr(pattern)} matches no file",
            hint="the pattern is relative to the folder, e.g. glob=depth/*.png or glob=*_depth.png",
        )
    return sorted(paths, key=_natural_key)


def _depth_images(folder: Path) -> list[Path]:
    """The depth images of a folder without ``depth.txt``: its own PNG/PGM files, else those in
    ``depth/``; colour and 8-bit images beside them are skipped (said in one INFO line)."""
    skipped: list[tuple[Path, str]] = []
    for where in (folder, folder / "depth"):
        kinds = image_kinds(_images(where))  # by each file's header, not its name
        depth = [p for p, kind in kinds if kind in ("depth", "unknown")]
        skipped += [(p, kind) for p, kind in kinds if kind not in ("depth", "unknown")]
        if depth:
            break
    counts = {k: sum(1 for _, kind in skipped if kind == k) for k in ("colour", "8-bit")}
    said = " and ".join(f"{n} {k}" for k, n in counts.items() if n)
    if not depth:
        if skipped:
            raise RecordingError(
                f"{folder}: no 16-bit depth images; skipped {said} images "
                f"(e.g. {short_text(skipped[0][0].name, 60)})",
                hint="depth images are single-channel 16-bit PNG or PGM; "
                "name others with replay:PATH?glob=PATTERN",
            )
        raise RecordingError(f"{folder}: no depth images (*.png, *.pgm or {INDEX})")
    if skipped:
        log.info(
            "%s: reading %d depth images%s; skipped %s images (e.g. %s); choose with ?glob=PATTERN",
            folder,
            len(depth),
            "" if depth[0].parent == folder else " from depth/",
            said,
            skipped[0][0].relative_to(folder),
        )
    return depth


def list_frames(folder: Path, fps: float, pattern: str | None = None) -> list[tuple[float, Path]]:
    """(timestamp_s from the first frame, path) for every depth image, in playback order.

    The images are the ones ``pattern`` (a glob relative to the folder) matches, else those
    ``depth.txt`` names, else the folder's 16-bit PNG and PGM images (or ``depth/``'s).
    """
    index = folder / INDEX
    items: list[tuple[float, Path]] = []
    if pattern is not None:
        items = [(i / fps, p) for i, p in enumerate(_globbed(folder, pattern))]
    elif os.path.lexists(index):
        text = read_bytes(index, what="frame index", max_bytes=INDEX_MAX_BYTES)
        for number, raw in enumerate(text.decode("utf-8", errors="replace").splitlines(), 1):
            line = raw.strip()
            if line and not line.startswith("#"):
                items.append(_index_line(index, number, line, folder))
        if items and any(b[0] < a[0] for a, b in itertools.pairwise(items)):
            raise RecordingError(f"{index}: timestamps go backwards")
    else:
        items = [(i / fps, p) for i, p in enumerate(_depth_images(folder))]
    if not items:
        raise RecordingError(f"{folder}: no depth images (*.png, *.pgm or {INDEX})")
    t0 = items[0][0]
    return [(t - t0, p) for t, p in items]


SIDECAR_KEYS = ("depth_scale", "intrinsics")
INTRINSICS_KEYS = ("width", "height", "fx", "fy", "cx", "cy", *LENS_KEYS)
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
    return read_camera_toml(path, SIDECAR_KEYS)


def read_camera_toml(path: Path, keys: tuple[str, ...]) -> dict[str, Any]:
    """A ``camera.toml`` (a folder's, or an ``.oni`` file's ``NAME.camera.toml``) as a dict.

    Raises:
        RecordingError: unreadable, or a key it does not know (outside ``keys`` at the top,
            ``INTRINSICS_KEYS`` in ``[intrinsics]``).
    """
    side = read_toml(path, what=path.name)
    for key, value in side.items():
        if key not in keys:
            raise RecordingError(
                f"{path}: unknown key {short_text(str(key))!r} (valid: {', '.join(keys)})",
                hint="depth_scale = units per metre; [intrinsics] fx, fy, cx, cy in pixels, "
                "optional lens distortion_model and k1, k2, p1, p2, k3 (k4-k6)",
            )
        if key == "intrinsics" and isinstance(value, dict):
            for sub in value:
                if sub not in INTRINSICS_KEYS:
                    raise RecordingError(
                        f"{path}: unknown key [intrinsics] {short_text(str(sub))!r} "
                        f"(valid: {', '.join(INTRINSICS_KEYS)})"
                    )
    return side


def camera_toml_text(intr: Intrinsics, depth_scale: float | None = None) -> str:
    """The ``camera.toml`` text ``read_camera_toml`` and ``sidecar_intrinsics`` read back: the
    intrinsics whole (pinhole and lens), and the depth scale when given."""
    scale = "" if depth_scale is None else f"depth_scale = {depth_scale!r}\n\n"
    return (
        f"{scale}[intrinsics]\nwidth = {intr.width}\nheight = {intr.height}\n"
        f"fx = {intr.fx!r}\nfy = {intr.fy!r}\ncx = {intr.cx!r}\ncy = {intr.cy!r}\n"
        + "".join(
            f"{key} = {value!r}\n"
            for key, value in lens_table(intr.distortion_model, intr.distortion).items()
        )
    )


def is_tum(folder: Path) -> bool:
    """True for a TUM RGB-D folder, recognised by its structure (drivers.formats.tum)."""
    return recognise_tum(folder)[0]


def sidecar_scale(folder: Path, side: dict[str, Any]) -> float:
    """The sidecar's ``depth_scale`` (units per metre); 5000 for a TUM RGB-D folder.

    A wrong scale is silently wrong everywhere downstream (a millimetre folder read at 5000
    units per metre puts every obstacle at a fifth of its range), so it must be stated.

    Raises:
        RecordingError: no scale and not a TUM folder (drivers.formats.tum, by its structure;
            the message says what is not TUM about a folder that looks partly like one, the
            hint the common values); not a number in 1..1e6 (0 would divide by zero).
    """
    if "depth_scale" not in side:
        tum, why = recognise_tum(folder)
        if tum:
            log.info(
                "%s: a TUM RGB-D folder (%s): %g depth units per metre, as the format defines; "
                "for another unit give replay:PATH?scale=N or depth_scale in %s",
                folder,
                why,
                TUM_SCALE,
                SIDECAR,
            )
            return TUM_SCALE
        raise RecordingError(
            f"{folder}: the depth scale is not stated (no depth_scale in {SIDECAR}, no scale=)"
            + (f"; {why}" if why else ""),
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
    folder: Path, side: dict[str, Any], shape: tuple[int, ...], *, where: Path | None = None
) -> Intrinsics | None:
    """The sidecar's ``[intrinsics]`` for (H, W) images, or None when it has none; ``where``
    names the file in messages (default the folder's camera.toml)."""
    table = side.get("intrinsics")
    if not isinstance(table, dict):
        return None
    where = where or folder / SIDECAR
    values: dict[str, float | str] = {}
    for key in ("fx", "fy", "cx", "cy"):
        if key not in table:
            raise RecordingError(f"{where}: bad [intrinsics]: {key!r} is missing")
        if isinstance(table[key], str):
            raise RecordingError(f"{where}: bad [intrinsics]: {key} is text, not a number")
        try:
            values[key] = float(to_number(table[key]))
        except NumberError as exc:
            raise RecordingError(
                f"{where}: bad [intrinsics]: {key} = {short_repr(table[key])} {exc}"
            ) from None
    try:  # the lens: no coefficient is an ideal pinhole
        values |= lens_fields(table)
    except ValueError as exc:
        raise RecordingError(f"{where}: bad [intrinsics]: {exc}") from None
    try:
        return Intrinsics(shape[1], shape[0], **values)
    except ValueError as exc:
        raise RecordingError(f"{where}: bad [intrinsics]: {exc}") from None


read_depth_png = read_depth_image  # the older name: it reads 16-bit PGM as well


def iter_png_folder(
    folder: Path,
    intrinsics: Intrinsics | None,
    scale: float,
    fps: float,
    frames: list[tuple[float, Path]] | None = None,
) -> Iterator[tuple[float, npt.NDArray[np.uint16]]]:
    """Yield (timestamp_s, depth_mm (H, W)) of ``frames`` (default: ``list_frames``); every image
    must match ``intrinsics`` in size."""
    for stamp, path in frames if frames is not None else list_frames(folder, fps):
        depth = read_depth_image(path, scale)
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
        # numbered: two frames with one timestamp (a device's clock, a paused replay) keep both
        name = f"depth/{len(lines) - 2:06d}.png"
        Image.fromarray(units.astype(np.uint16)).save(out / name)
        lines.append(f"{frame.timestamp_s:.6f} {name}")
    if intr is None:
        raise RecordingError(f"{out}: no frames to write")
    (out / INDEX).write_text("\n".join(lines) + "\n", encoding="utf-8")
    (out / SIDECAR).write_text(camera_toml_text(intr, scale), encoding="utf-8")
    return len(lines) - 2
