"""Single depth images: 16-bit PNG and 16-bit binary PGM, read as uint16 millimetres; and telling
depth images from the colour images datasets keep beside them.

PGM (netpbm ``P5``): a header ``P5 <width> <height> <maxval>`` (whitespace and ``#`` comments
between the fields, one whitespace byte after maxval), then width x height samples; with a maxval
above 255 each is two bytes, most significant first (the netpbm spec; slambook's depth maps). The
header is parsed here, not by Pillow, which rescales samples to 0..65535 when maxval is not 65535
(a depth of 300 in a maxval-4095 file came back as 4801). Little-endian "PGM" files (libfreenect's
fakenect, NYU v2's raw frames) are not netpbm and read wrong: fakenect folders have their reader.

Every size is checked (drivers.limits) before pixels are decoded, and files are opened through
drivers.files (regular files only, bounded size).
"""

from __future__ import annotations

import re
import struct
from pathlib import Path

import numpy as np
import numpy.typing as npt
from PIL import Image, UnidentifiedImageError

from drivers.base import MM_PER_M, UINT16_MAX
from drivers.errors import RecordingError
from drivers.files import open_input
from drivers.limits import image_size_problem
from drivers.values import short_text

MAX_IMAGE_BYTES = 256 << 20  # a 8192x8192 16-bit image is 128 MiB uncompressed
SUFFIXES = (".png", ".pgm")  # depth images a folder may hold
_PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
_IHDR = struct.Struct(">I4sIIBB")  # chunk length, b"IHDR", width, height, bit depth, colour type
_HEAD_BYTES = 64  # enough for a PNG's IHDR and any sane PGM header start
# P5, then width, height, maxval separated by whitespace or comments, then one whitespace byte
_PGM_FIELD = re.compile(rb"(?:\s|#[^\n]*\n)+([0-9]{1,9})")
_PGM_HEADER_MAX = 1024  # bytes: comments included; a longer header is refused


def png_info(head: bytes) -> tuple[int, int, int, int] | None:
    """(width, height, bit depth, colour type) from a PNG's IHDR, or None if not a PNG's start."""
    if len(head) < len(_PNG_SIGNATURE) + _IHDR.size or not head.startswith(_PNG_SIGNATURE):
        return None
    _, kind, width, height, bits, colour = _IHDR.unpack_from(head, len(_PNG_SIGNATURE))
    return (width, height, bits, colour) if kind == b"IHDR" else None


def pgm_header(head: bytes) -> tuple[int, int, int, int] | None:
    """(width, height, maxval, data offset) of a binary PGM, or None if ``head`` is not one.

    Raises:
        RecordingError: a ``P5`` file whose header is malformed (fields missing or not numbers).
    """
    if not head.startswith(b"P5"):
        return None
    pos, fields = 2, []
    for _ in range(3):
        match = _PGM_FIELD.match(head, pos)
        if match is None:
            raise RecordingError(
                "PGM header is malformed (expected 'P5 <width> <height> <maxval>')",
                hint="the file is corrupt or truncated",
            )
        fields.append(int(match.group(1)))
        pos = match.end()
    if pos >= len(head) or head[pos : pos + 1] not in (b" ", b"\t", b"\n", b"\r", b"\v", b"\f"):
        raise RecordingError(
            "PGM header does not end with one whitespace byte after maxval",
            hint="the file is corrupt or truncated",
        )
    return fields[0], fields[1], fields[2], pos + 1


def kind_of(path: Path) -> str:
    """What an image file holds, from its first bytes: "depth" (16-bit single channel PNG or PGM),
    "colour" or "8-bit" (skipped when picking depth images), or "unknown" (kept: reading it
    then says what is wrong, as for a corrupt or special file)."""
    try:
        with open_input(path, what="image", max_bytes=MAX_IMAGE_BYTES) as fh:
            head = fh.read(_HEAD_BYTES)
    except (RecordingError, OSError):
        return "unknown"
    return _kind_of_head(head)


def _kind_of_head(head: bytes) -> str:
    info = png_info(head)
    if info is not None:
        _, _, bits, colour = info
        if colour != 0:  # 2 RGB, 3 palette, 4 grey+alpha, 6 RGBA
            return "colour"
        return "depth" if bits == 16 else "8-bit"  # noqa: PLR2004
    if head.startswith((b"P6", b"P3", b"\xff\xd8\xff")):  # PPM, ASCII PPM, JPEG
        return "colour"
    kind = "unknown"
    if head.startswith(b"P5"):
        try:
            parsed = pgm_header(head)
        except RecordingError:
            parsed = None
        if parsed is not None:
            kind = "depth" if parsed[2] > 255 else "8-bit"  # noqa: PLR2004
    return kind


def _read_png(path: Path) -> npt.NDArray[np.generic]:
    """One 16-bit greyscale PNG's raw values (H, W)."""
    with open_input(path, what="depth image", max_bytes=MAX_IMAGE_BYTES) as fh:
        info = png_info(fh.read(len(_PNG_SIGNATURE) + _IHDR.size))
        if info is None:
            raise RecordingError(f"{path}: not a PNG file", hint="the file is corrupt or truncated")
        problem = image_size_problem(info[0], info[1])
        if problem:
            raise RecordingError(f"{path}: {problem}")
        fh.seek(0)
        try:
            with Image.open(fh, formats=["PNG"]) as img:
                img.load()
                if img.mode not in ("I;16", "I;16B", "I;16L", "I"):
                    raise RecordingError(
                        f"{path}: a {img.mode} image, expected 16-bit greyscale depth",
                        hint="depth images are single-channel 16-bit; "
                        "pick them with replay:PATH?glob=PATTERN",
                    )
                return np.asarray(img)
        except Image.DecompressionBombError as exc:
            raise RecordingError(f"{path}: too big to decode ({exc})") from None
        except (UnidentifiedImageError, OSError, SyntaxError, ValueError, EOFError) as exc:
            raise RecordingError(
                f"{path}: not a readable PNG ({short_text(str(exc), 120)})",
                hint="the file is corrupt or truncated",
            ) from None


def _read_pgm(path: Path) -> npt.NDArray[np.uint16]:
    """One 16-bit binary PGM's values (H, W), big-endian as netpbm says."""
    with open_input(path, what="depth image", max_bytes=MAX_IMAGE_BYTES) as fh:
        head = fh.read(_PGM_HEADER_MAX)
        try:
            parsed = pgm_header(head)
        except RecordingError as exc:
            raise RecordingError(f"{path}: {exc}", hint=exc.hint) from None
        assert parsed is not None  # the caller saw "P5"
        width, height, maxval, offset = parsed
        if not 0 < maxval <= UINT16_MAX:
            raise RecordingError(f"{path}: PGM maxval {maxval} is not in 1..65535")
        if maxval <= 255:  # noqa: PLR2004 - one byte a sample
            raise RecordingError(
                f"{path}: an 8-bit PGM (maxval {maxval}), expected 16-bit depth",
                hint="depth images are single-channel 16-bit; "
                "pick them with replay:PATH?glob=PATTERN",
            )
        problem = image_size_problem(width, height)
        if problem:
            raise RecordingError(f"{path}: {problem}")
        nbytes = width * height * 2
        fh.seek(offset)
        data = fh.read(nbytes)
    if len(data) != nbytes:
        raise RecordingError(
            f"{path}: {len(data)} bytes of pixels, expected {nbytes} for {width}x{height}",
            hint="the file is truncated",
        )
    raw = np.frombuffer(data, dtype=">u2").reshape(height, width)
    if int(raw.max(initial=0)) > maxval:
        raise RecordingError(f"{path}: values above the PGM's maxval {maxval} (corrupt)")
    return raw.astype(np.uint16)


def read_depth_image(path: Path, scale: float) -> npt.NDArray[np.uint16]:
    """One 16-bit PNG or PGM as (H, W) uint16 millimetres, given ``scale`` units per metre.

    The size in the header is checked (drivers.limits) before anything is decoded: a PNG claiming
    20000x20000 pixels is one line, not Pillow's DecompressionBombError, and a 12000 x 12000 one
    is refused before its 3 GB are allocated.
    """
    with open_input(path, what="depth image", max_bytes=MAX_IMAGE_BYTES) as fh:
        magic = fh.read(2)
    raw = _read_pgm(path) if magic == b"P5" else _read_png(path)
    if raw.ndim != 2 or raw.min() < 0 or raw.max() > UINT16_MAX:  # noqa: PLR2004 - (H, W)
        raise RecordingError(f"{path}: not a single-channel 16-bit depth image")
    if scale == MM_PER_M:
        return raw.astype(np.uint16)
    mm = np.rint(raw.astype(np.float64) * (1000.0 / scale))
    return np.clip(mm, 0, 65535).astype(np.uint16)
