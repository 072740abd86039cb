"""Decoding ROS messages of depth cameras (sensor_msgs Image, CompressedImage, CameraInfo; tf).

Duck-typed over the message objects of the ``rosbags`` library, ROS 1 or ROS 2 field names alike.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt

from drivers.base import Intrinsics
from drivers.errors import RecordingError
from drivers.formats.compressed_depth import codec_of, decode_compressed_depth, is_compressed_depth
from drivers.lens_model import EQUIDISTANT, MODEL_KEYS, MODELS_TEXT
from drivers.values import short_text

log = logging.getLogger(__name__)

# encoding -> numpy kind (mm, m); mono16 is millimetres in the drivers that publish depth as it
DEPTH_ENCODINGS = {"16UC1": "u2", "mono16": "u2", "32FC1": "f4"}
MAX_MM = 65535  # the largest depth a uint16 millimetre image holds
HINT_BROKEN = "the bag is truncated or damaged: re-record it"  # rosbag.py names repair tools


@dataclass(frozen=True, slots=True)
class CameraModel:
    """The camera of a CameraInfo message.

    Attributes:
        intrinsics: fx, fy, cx, cy (pixels) for the depth image's size, with the lens model
            and coefficients of D (see ``camera_model``).
        distortion_model: e.g. "plumb_bob", "" when none is given.
        distortion: the D coefficients as recorded.
        frame_id: the camera's frame.
    """

    intrinsics: Intrinsics
    distortion_model: str
    distortion: tuple[float, ...]
    frame_id: str


def _field(msg: Any, *names: str) -> Any:
    """A message field under its ROS 2 or ROS 1 name (CameraInfo's ``k`` is ``K`` in ROS 1)."""
    for name in names:
        if hasattr(msg, name):
            return getattr(msg, name)
    raise AttributeError(names[0])


def stamp_s(msg: Any, log_time_ns: int) -> float:
    """The header stamp in seconds, or the bag's receive time when the stamp is zero."""
    stamp = msg.header.stamp
    sec, nsec = int(stamp.sec), int(_field(stamp, "nanosec", "nsec"))
    if sec == 0 and nsec == 0:
        return log_time_ns * 1e-9
    return sec + nsec * 1e-9


def image_kind(msg: Any) -> str:
    """What an Image or CompressedImage holds, as listed to the user: "16UC1", "jpeg",
    "16UC1 compressedDepth png"."""
    if not hasattr(msg, "format"):
        return str(msg.encoding).strip()
    fmt = str(msg.format).strip()
    if not is_compressed_depth(fmt):
        return fmt
    try:
        encoding, codec = codec_of(fmt)
    except RecordingError:
        return fmt
    return f"{encoding} compressedDepth {codec}"


def is_depth_kind(kind: str) -> bool:
    """True for an :func:`image_kind` depthnav reads as depth."""
    return kind in DEPTH_ENCODINGS or kind.endswith(("compressedDepth png", "compressedDepth rvl"))


def decode_image(msg: Any, where: str) -> npt.NDArray[np.uint16]:
    """An Image (see :func:`decode_depth`) or a compressedDepth CompressedImage as (H, W) uint16
    millimetres, 0 = no reading.

    Raises:
        RecordingError: not depth, or damaged.
    """
    if not hasattr(msg, "format"):
        return decode_depth(msg, where)
    fmt = str(msg.format).strip()
    if not is_compressed_depth(fmt):
        raise RecordingError(
            f"{where}: a CompressedImage of format {fmt!r} is not depth",
            hint="compressed depth is image_transport's compressedDepth (png or rvl); "
            "pick the depth topic with ?topic=",
        )
    return decode_compressed_depth(msg, where)


def decode_depth(msg: Any, where: str) -> npt.NDArray[np.uint16]:
    """A sensor_msgs/Image (16UC1 or mono16 mm, 32FC1 m) as (H, W) uint16 millimetres, 0 = none.

    Raises:
        RecordingError: another encoding, or data shorter than ``height * step``.
    """
    encoding = str(msg.encoding).strip()
    if encoding not in DEPTH_ENCODINGS:
        raise RecordingError(
            f"{where}: image encoding {encoding!r} is not depth",
            hint="depth images are 16UC1 or mono16 (millimetres) or 32FC1 (metres); "
            "pick one with ?topic=",
        )
    kind = DEPTH_ENCODINGS[encoding]
    height, width, step = int(msg.height), int(msg.width), int(msg.step)
    row_bytes = width * 2 if kind == "u2" else width * 4
    data = np.asarray(msg.data, dtype=np.uint8)
    if height < 1 or width < 1 or step < row_bytes or data.size < step * height:
        raise RecordingError(
            f"{where}: a {width}x{height} {encoding} image with step {step} "
            f"holds {data.size} bytes (needs {step * height})",
            hint=HINT_BROKEN,
        )
    rows = data[: step * height].reshape(height, step)[:, :row_bytes]
    dtype = np.dtype((">" if msg.is_bigendian else "<") + kind)
    values = np.ascontiguousarray(rows).view(dtype).reshape(height, width)
    if kind == "u2":
        return values.astype(np.uint16)
    with np.errstate(invalid="ignore", over="ignore"):
        mm = np.rint(values.astype(np.float64) * 1000.0)
        ok = np.isfinite(mm) & (mm > 0) & (mm <= MAX_MM)
    return np.where(ok, mm, 0).astype(np.uint16)


def camera_model(info: Any, shape: tuple[int, int], where: str) -> CameraModel | None:
    """The camera of a CameraInfo for images of ``shape`` (H, W); None when K is all zero.

    Lens distortion: a ``plumb_bob``, ``rational_polynomial`` or ``equidistant`` D is applied
    (drivers.lens_model); another model, or a D longer than its model's with a non-zero extra
    (OpenCV's thin-prism terms), is refused: reading it as a pinhole, or a model cut short,
    would be a wrong lens. An all-zero D of the other models is a rectified image
    (``image_rect``) or an ideal camera.

    Raises:
        RecordingError: K, or a D, that does not fit the image; a lens depthnav cannot express.
    """
    k = np.asarray(_field(info, "k", "K"), dtype=np.float64)
    if k.shape != (9,) or not np.any(k):
        return None  # an uncalibrated camera publishes K = 0
    height, width = shape
    info_w, info_h = int(info.width), int(info.height)
    d = tuple(float(x) for x in np.asarray(_field(info, "d", "D"), dtype=np.float64).reshape(-1))
    model = str(info.distortion_model).strip()
    lens = _lens_fields(model, d, where)
    try:
        intr = Intrinsics(
            info_w or width,
            info_h or height,
            float(k[0]),
            float(k[4]),
            float(k[2]),
            float(k[5]),
            **lens,
        )
        if (intr.width, intr.height) != (width, height):
            log.info("%s: CameraInfo is %dx%d, images %dx%d: intrinsics scaled", where,
                     intr.width, intr.height, width, height)  # fmt: skip
            intr = intr.scaled(width, height)
    except ValueError as exc:
        raise RecordingError(f"{where}: CameraInfo K/D does not fit the image: {exc}") from None
    return CameraModel(intr, model, d, str(info.header.frame_id))


MAX_D_SHOWN = 14  # coefficients of a refused D a message lists (OpenCV's longest model has 14)


def _lens_fields(model: str, d: tuple[float, ...], where: str) -> dict[str, float | str]:
    """The Intrinsics lens keywords of a CameraInfo's distortion model and D; {} for none."""
    if not d or (model != EQUIDISTANT and not any(d)):  # a fisheye's zero D is still a fisheye
        return {}
    keys = MODEL_KEYS.get(model)
    if keys is None or any(d[len(keys) :]):
        listed = ", ".join(f"{x:.4g}" for x in d[:MAX_D_SHOWN])
        more = f", ... ({len(d)} in all)" if len(d) > MAX_D_SHOWN else ""
        shown = f"{short_text(model, 60) or 'unnamed'} D = [{listed}{more}]"
        raise RecordingError(
            f"{where}: lens distortion {shown} cannot be expressed (depthnav models {MODELS_TEXT})",
            hint="replay a rectified depth topic (?topic=), or give the lens as one of these",
        )
    return {"distortion_model": model} | dict(zip(keys, d + (0.0,) * len(keys), strict=False))


def quat_matrix(q: Any) -> npt.NDArray[np.float64]:
    """(3, 3) rotation of a geometry_msgs/Quaternion."""
    x, y, z, w = float(q.x), float(q.y), float(q.z), float(q.w)
    n = math.sqrt(x * x + y * y + z * z + w * w) or 1.0
    x, y, z, w = x / n, y / n, z / n, w / n
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )
