"""Depth images of image_transport's ``compressedDepth`` plugin, decoded without OpenCV.

A ``sensor_msgs/CompressedImage`` whose ``format`` is ``"<encoding>; compressedDepth <codec>"``
(``"16UC1; compressedDepth png"``, ``"... rvl"``; older publishers wrote ``"16UC1;
compressedDepth"`` or only the encoding, both PNG). Layout of ``data``, as written by
compressed_depth_image_transport (codec.cpp, compression_common.h), in the publisher's byte order
(little-endian on every platform ROS runs on, assumed here):

- a 12-byte ConfigHeader: int32 ``format`` (0 = INV_DEPTH, the only value written), float32
  ``depthParam[2]`` (a, b: the inverse-depth quantisation of 32FC1 images; unused for 16UC1);
- PNG: a 16-bit grayscale PNG of the uint16 image (16UC1: millimetres; 32FC1: quantised inverse
  depth ``q``, depth_m = a / (q - b), q = 0 no reading);
- RVL: uint32 width, uint32 height, then Wilson's RVL stream ("Fast Lossless Depth Image
  Compression", 2017) of the same uint16 image: 32-bit words, read as little-endian int32 and
  consumed 4 bits at a time from the most significant nibble; each number is a variable-length
  code of 3-bit groups (least significant group first, bit 3 of a nibble = more to come); the
  stream is (zero-run length, non-zero-run length, that many zigzag deltas from the previous
  non-zero pixel) repeated until the image is full.

Every size is checked against drivers.limits before anything is decompressed.
"""

from __future__ import annotations

import io
import struct
import warnings
from typing import Any

import numpy as np
import numpy.typing as npt

from drivers.errors import RecordingError
from drivers.limits import image_size_problem

HEADER = struct.Struct("<iff")  # ConfigHeader: compressionFormat (int enum), depthParam[2]
RVL_SIZE = struct.Struct("<II")  # cols, rows before the RVL stream
PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
PNG_HEAD = 33  # signature, IHDR length and type, its 13 bytes, its CRC
DEPTH_BITS = 16
MAX_MM = 65535
MAX_VLE_NIBBLES = 11  # 33 bits: more than any run length or delta of a real image needs
HINT = "the compressedDepth image is damaged: re-record it, or republish it raw (image_transport)"


def is_compressed_depth(fmt: str) -> bool:
    """True for a CompressedImage ``format`` of the compressedDepth plugin."""
    return "compresseddepth" in fmt.lower()


def codec_of(fmt: str) -> tuple[str, str]:
    """(image encoding, codec "png" or "rvl") of a compressedDepth ``format`` string.

    Raises:
        RecordingError: a codec other than png or rvl.
    """
    encoding, _, rest = fmt.partition(";")
    words = rest.split()  # "compressedDepth png" | "compressedDepth" | ""
    codec = words[1].lower() if len(words) > 1 else "png"  # older publishers: PNG only
    if codec not in ("png", "rvl"):
        raise RecordingError(
            f"compressedDepth codec {codec!r} (format {fmt!r}) is not one depthnav reads",
            hint="compressedDepth images are png or rvl; republish the topic raw",
        )
    return encoding.strip(), codec


def decode_compressed_depth(msg: Any, where: str) -> npt.NDArray[np.uint16]:
    """A compressedDepth CompressedImage as (H, W) uint16 millimetres, 0 = no reading.

    Raises:
        RecordingError: a format that is not 16UC1/32FC1 compressedDepth, a short header, a PNG
            or RVL payload that is damaged, too large, or not a 16-bit grayscale image.
    """
    fmt = str(msg.format).strip()
    try:
        encoding, codec = codec_of(fmt)
    except RecordingError as exc:
        raise RecordingError(f"{where}: {exc}", hint=exc.hint) from None
    if encoding not in ("16UC1", "32FC1"):
        raise RecordingError(
            f"{where}: a compressedDepth image of encoding {encoding!r} ({fmt!r}) is not depth",
            hint="compressedDepth depth images are 16UC1 (millimetres) or 32FC1 (metres)",
        )
    data = bytes(np.asarray(msg.data, dtype=np.uint8))
    if len(data) <= HEADER.size:
        raise RecordingError(
            f"{where}: a compressedDepth image of {len(data)} bytes (the header alone is "
            f"{HEADER.size})",
            hint=HINT,
        )
    _, a, b = HEADER.unpack_from(data)
    body = data[HEADER.size :]
    image = decode_png16(body, where) if codec == "png" else decode_rvl(body, where)
    if encoding == "16UC1":
        return image
    return _inverse_depth_mm(image, a, b, where)


def _inverse_depth_mm(q: npt.NDArray[np.uint16], a: float, b: float, where: str) -> Any:
    """The 32FC1 image of quantised inverse depth ``q`` as uint16 mm (a / (q - b) metres)."""
    if not (np.isfinite(a) and np.isfinite(b) and a > 0):
        raise RecordingError(
            f"{where}: 32FC1 compressedDepth header has quantisation a={a!r}, b={b!r}", hint=HINT
        )
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        # float32 as the reference decoder computes it, so the same metres come out
        metres = np.float32(a) / (q.astype(np.float32) - np.float32(b))
        mm = np.rint(metres.astype(np.float64) * 1000.0)
        ok = (q > 0) & np.isfinite(mm) & (mm > 0) & (mm <= MAX_MM)
    return np.where(ok, mm, 0).astype(np.uint16)


def _checked_size(width: int, height: int, what: str, where: str) -> None:
    problem = image_size_problem(width, height)
    if problem is not None:
        raise RecordingError(f"{where}: the {what} declares {problem}", hint=HINT)


def decode_png16(data: bytes, where: str) -> npt.NDArray[np.uint16]:
    """A 16-bit grayscale PNG as (H, W) uint16; its IHDR is checked before decoding.

    Raises:
        RecordingError: not a PNG, not 16-bit grayscale, too large (drivers.limits), damaged.
    """
    # IHDR is the first chunk: length 13, "IHDR", width, height (big-endian), bit depth, colour
    if len(data) < PNG_HEAD or data[:8] != PNG_SIGNATURE or data[12:16] != b"IHDR":
        raise RecordingError(
            f"{where}: the compressedDepth payload is not a PNG ({len(data)} bytes, "
            f"starts {data[:8].hex()})",
            hint=HINT,
        )
    width, height, bits, colour = struct.unpack_from(">IIBB", data, 16)
    if bits != DEPTH_BITS or colour != 0:
        kind = {0: "grayscale", 2: "RGB", 3: "palette", 4: "grayscale+alpha", 6: "RGBA"}
        raise RecordingError(
            f"{where}: the compressedDepth PNG is {bits}-bit {kind.get(colour, f'type {colour}')}, "
            "not 16-bit grayscale depth",
            hint="the topic does not carry depth; pick the depth topic with ?topic=",
        )
    _checked_size(width, height, "PNG", where)
    from PIL import Image

    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # the size is checked above; no bomb warning
            with Image.open(io.BytesIO(data), formats=["PNG"]) as img:
                img.load()
                mode = img.mode
                values = np.asarray(img)
    except Exception as exc:  # Pillow raises many types on a damaged stream
        text = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        raise RecordingError(
            f"{where}: the compressedDepth PNG is damaged ({text})", hint=HINT
        ) from None
    if values.shape != (height, width) or mode not in ("I;16", "I;16B", "I;16L", "I"):
        raise RecordingError(
            f"{where}: the compressedDepth PNG decoded as {mode} {values.shape}", hint=HINT
        )
    if values.dtype != np.uint16:  # older Pillow: mode "I" (int32) holding 0..65535
        values = np.clip(values, 0, MAX_MM)
    return np.ascontiguousarray(values, dtype=np.uint16)


def decode_rvl(data: bytes, where: str) -> npt.NDArray[np.uint16]:
    """An RVL payload (uint32 cols, uint32 rows, RVL words) as (rows, cols) uint16.

    Bounded: the size is checked against drivers.limits and the payload's length before any
    decoding, and a stream that fills more pixels than the image or ends early is refused.

    Raises:
        RecordingError: a damaged or oversized payload.
    """
    if len(data) < RVL_SIZE.size:
        raise RecordingError(f"{where}: an RVL payload of {len(data)} bytes", hint=HINT)
    width, height = RVL_SIZE.unpack_from(data)
    _checked_size(width, height, "RVL header", where)
    n = width * height
    stream = data[RVL_SIZE.size :]
    # at most 8 nibbles a pixel (two 1-nibble run lengths, a 6-nibble delta): 4 bytes, plus a word
    if len(stream) > 4 * n + 8:
        raise RecordingError(
            f"{where}: an RVL payload of {len(stream)} bytes for a {width}x{height} image "
            f"(at most {4 * n + 8})",
            hint=HINT,
        )
    values = _vle_values(stream, where)
    out = np.zeros(n, dtype=np.uint16)
    starts: list[int] = []  # pixel index of each non-zero run
    firsts: list[int] = []  # index of its first delta in ``values``
    lengths: list[int] = []  # its length
    numbers = values.tolist()  # the run lengths are read one by one: a list is faster
    pixel = pos = 0
    count = len(numbers)
    while pixel < n:  # one pass per run: at most len(values) / 2 passes
        if pos + 2 > count:
            raise RecordingError(
                f"{where}: the RVL stream ends after {pixel} of {n} pixels", hint=HINT
            )
        zeros, nonzeros = numbers[pos], numbers[pos + 1]
        pos += 2
        if zeros + nonzeros > n - pixel:
            raise RecordingError(
                f"{where}: the RVL stream claims {pixel + zeros + nonzeros} pixels of a "
                f"{width}x{height} image",
                hint=HINT,
            )
        if pos + nonzeros > count:
            raise RecordingError(
                f"{where}: the RVL stream ends after {pixel + zeros} of {n} pixels", hint=HINT
            )
        pixel += zeros
        if nonzeros:
            starts.append(pixel)
            firsts.append(pos)
            lengths.append(nonzeros)
        pixel += nonzeros
        pos += nonzeros
    if lengths:
        runs = np.asarray(lengths, dtype=np.int64)
        total = int(runs.sum())
        step = np.arange(total) - np.repeat(np.cumsum(runs) - runs, runs)  # index within its run
        zigzag = values[np.repeat(np.asarray(firsts, dtype=np.int64), runs) + step]
        deltas = (zigzag >> 1) ^ -(zigzag & 1)  # zigzag: 0, -1, 1, -2, ... from 0, 1, 2, 3, ...
        pixels = np.cumsum(deltas) & 0xFFFF  # each value is the previous non-zero plus its delta
        out[np.repeat(np.asarray(starts, dtype=np.int64), runs) + step] = pixels.astype(np.uint16)
    return out.reshape(height, width)


def _vle_values(stream: bytes, where: str) -> npt.NDArray[np.int64]:
    """Every variable-length number of an RVL stream, in order (trailing padding gives zeros)."""
    usable = len(stream) // 4 * 4
    words = np.frombuffer(stream[:usable], dtype="<u4")
    shifts = np.arange(28, -4, -4, dtype=np.uint32)  # the most significant nibble first
    nibbles = ((words[:, None] >> shifts) & 0xF).astype(np.uint8).reshape(-1)
    if nibbles.size == 0:
        return np.zeros(0, dtype=np.int64)
    last = (nibbles & 0x8) == 0  # a nibble without the "more" bit ends its number
    ends = np.flatnonzero(last)
    if ends.size == 0:
        raise RecordingError(f"{where}: the RVL stream holds no complete number", hint=HINT)
    nibbles = nibbles[: ends[-1] + 1]  # an unfinished number at the end is dropped
    starts = np.r_[0, ends[:-1] + 1]
    if int(np.max(ends - starts)) >= MAX_VLE_NIBBLES:
        raise RecordingError(f"{where}: the RVL stream holds an overlong number", hint=HINT)
    number = np.repeat(np.arange(ends.size), ends - starts + 1)
    place = np.arange(nibbles.size) - starts[number]  # 3-bit group index, least significant first
    groups = (nibbles & 0x7).astype(np.int64) << (3 * place)
    return np.add.reduceat(groups, starts)
