"""A bare ``.npy`` depth array: (N, H, W) or one (H, W) frame, uint16 millimetres or float32 /
float64 metres, read one frame at a time.

The header is read first (drivers.formats.npz.read_header: no pickles, bounded header) and the
declared size is checked against the image limits and the file's own size before any frame is
read. A ``.npy`` holds no intrinsics or timestamps: those come from the replay spec
(``fx, fy, cx, cy``) and ``fps``.
"""

from __future__ import annotations

import math
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from drivers.errors import RecordingError
from drivers.files import open_input
from drivers.formats.npz import read_header
from drivers.formats.recording import MAX_FRAMES, metres_to_mm
from drivers.limits import image_size_problem
from drivers.values import short_text


@dataclass(frozen=True, slots=True)
class NpyDepth:
    """The checked header of a depth ``.npy``.

    Attributes:
        path: the file.
        shape: (N, H, W) (one frame when the array is (H, W)).
        dtype: uint16 (mm) or float32/float64 (m).
        offset: where the data starts, bytes.
    """

    path: Path
    shape: tuple[int, int, int]
    dtype: np.dtype[Any]
    offset: int


def open_npy(path: Path) -> NpyDepth:
    """Read and check a depth ``.npy``'s header.

    Raises:
        RecordingError: not a readable .npy, a layout depthnav does not read, an image too big,
            or fewer bytes than the header declares.
    """
    with open_input(path, what=".npy array") as fh:
        try:
            shape, fortran, dtype = read_header(fh)
        except (ValueError, SyntaxError, EOFError) as exc:
            raise RecordingError(
                f"{path}: not a readable .npy array ({short_text(str(exc), 80)})",
                hint="save it with np.save",
            ) from None
        offset = fh.tell()
        size = fh.seek(0, 2)
    uint = dtype == np.uint16
    floating = dtype.kind == "f" and dtype.itemsize in (4, 8) and dtype.fields is None
    if dtype.hasobject or not (uint or floating) or len(shape) not in (2, 3) or fortran:
        raise RecordingError(
            f"{path}: expected (N, H, W) or (H, W) uint16 millimetres or float32 metres in C "
            f"order, got {dtype} {shape}{' in Fortran order' if fortran else ''}"
        )
    full = (1, *shape) if len(shape) == 2 else shape  # noqa: PLR2004 - one (H, W) frame
    n, height, width = full
    problem = image_size_problem(width, height)
    if problem:
        raise RecordingError(f"{path}: holds {problem}")
    if not 1 <= n <= MAX_FRAMES:
        raise RecordingError(f"{path}: holds {n} frames (accepted: 1..{MAX_FRAMES})")
    if size - offset < math.prod(full) * dtype.itemsize:
        raise RecordingError(
            f"{path}: {size - offset} bytes of data, too few for {dtype} {shape} (truncated)"
        )
    return NpyDepth(path, (n, height, width), dtype, offset)


def iter_npy(npy: NpyDepth) -> Iterator[npt.NDArray[np.uint16]]:
    """Each frame as (H, W) uint16 millimetres, one read from the file at a time.

    Raises:
        RecordingError: the file changed or ended early.
    """
    n, height, width = npy.shape
    frame_bytes = height * width * npy.dtype.itemsize
    with open_input(npy.path, what=".npy array") as fh:
        fh.seek(npy.offset)
        for i in range(n):
            data = fh.read(frame_bytes)
            if len(data) != frame_bytes:
                raise RecordingError(f"{npy.path}: ends in frame {i} of {n} (changed while read?)")
            frame = np.frombuffer(data, dtype=npy.dtype).reshape(height, width)
            yield metres_to_mm(frame, npy.path) if npy.dtype.kind == "f" else frame
