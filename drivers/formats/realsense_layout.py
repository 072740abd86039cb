"""Intel RealSense recordings read without the SDK: the topic layout librealsense writes.

librealsense records a device as a ROS bag: a ROS 1 ``.bag`` before 2.56, a ROS 2 ``.db3`` from
2.56 on. Device ``D``, sensor ``S`` and stream index ``I`` name the topics:

- depth: ``/device_D/sensor_S/Depth_I/image/data`` (ROS 1: ``sensor_msgs/Image`` ``mono16``,
  header stamp = the frame's timestamp) or ``.../image/data/compressedDepth`` (ROS 2:
  ``CompressedImage`` "16UC1; compressedDepth png", header stamp = time since recording start);
  values are raw z16 counts, metres = counts x depth units;
- depth units: ``/device_D/sensor_S/option/Depth_Units/value`` (ROS 1 ``std_msgs/Float32``,
  ROS 2 ``std_msgs/String`` such as "0.000100"). D4xx cameras default to 1 mm, the D405 to
  0.1 mm; the option steps in whole micrometres, so the units are kept as an integer number of
  micrometres (the same conversion for every path: :func:`counts_to_mm`);
- intrinsics and the distortion model: ROS 2 ``/device_D/sensor_S/Depth_I/camera_info``
  (``std_msgs/String`` "width=..;height=..;fx=..;ppx=..;fy=..;ppy=..;model=Brown
  Conrady;coeffs=.."), ROS 1 ``.../Depth_I/info/camera_info`` (``sensor_msgs/CameraInfo`` whose
  ``distortion_model`` is the SDK's name). ROS 2's ``sensor_msgs/CameraInfo`` beside the image
  says "plumb_bob" whatever the model (an Inverse Brown-Conrady included), so it is not used;
- the accelerometer: ``/device_D/sensor_S/Accel_I/imu/data`` (``sensor_msgs/Imu``), whose
  samples the SDK has already turned into the depth camera's axes (x right, y down, z forward;
  at rest and level about (0, -9.81, 0)): Intel's D435i documentation says each IMU sample is
  multiplied by the IMU-to-depth extrinsic inside the SDK.

The SDK's Brown-Conrady model is OpenCV's plumb_bob (coefficients k1, k2, p1, p2, k3) and its
Kannala-Brandt4 (fisheye streams) is OpenCV's fisheye, ROS ``equidistant`` (k1..k4): both are
read as the image's lens (drivers/lens_model.py). A non-zero Inverse or Modified Brown-Conrady
or an F-theta model is refused with one line (no equivalent model here). All-zero coefficients
are an ideal pinhole whatever the model's name (D4xx depth streams report zeros).
"""

from __future__ import annotations

import math
import re
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt

from drivers.base import EQUIDISTANT, PLUMB_BOB, Intrinsics
from drivers.errors import RecordingError
from drivers.values import short_repr

DEPTH_TOPIC = re.compile(r"/device_(\d+)/sensor_(\d+)/Depth_(\d+)/image/data(/compressedDepth)?\Z")
MM_UM = 1000  # micrometres in a millimetre
MIN_UNITS_UM, MAX_UNITS_UM = 1, 10_000  # the SDK's Depth Units option: 1e-6 .. 0.01 m
# the SDK's rs2_distortion_to_string names (lower case) -> depthnav's model and its keys
SDK_MODELS = {
    "brown conrady": (PLUMB_BOB, ("k1", "k2", "p1", "p2", "k3")),
    "kannala brandt4": (EQUIDISTANT, ("k1", "k2", "k3", "k4")),
}
HINT_LENS = (
    "depthnav models the SDK's Brown-Conrady (plumb_bob) and Kannala-Brandt4 (equidistant) "
    "lenses; give an equivalent lens as options, e.g. ?k1=..&k2=..&p1=..&p2=..&k3=.."
)


def units_um_from_m(units_m: float, where: str) -> int:
    """Depth units in metres per count as whole micrometres (the option's step).

    Raises:
        RecordingError: not finite, or outside 1 um .. 10 mm.
    """
    if not isinstance(units_m, (int, float)) or not math.isfinite(units_m):
        raise RecordingError(f"{where}: depth units {short_repr(units_m)} are not a number")
    units_um = round(units_m * 1e6)
    if not MIN_UNITS_UM <= units_um <= MAX_UNITS_UM:
        raise RecordingError(
            f"{where}: depth units {units_m:g} m are outside what a RealSense sets "
            "(0.000001 .. 0.01 m)"
        )
    return int(units_um)


def counts_to_mm(counts: npt.NDArray[np.uint16], units_um: int) -> npt.NDArray[np.uint16]:
    """z16 counts (H, W) of ``units_um`` micrometres each as uint16 millimetres, rounded half up;
    0 stays 0 (no reading) and a depth beyond 65535 mm becomes 0 (no reading, never a near one).

    1 mm units return ``counts`` itself (no copy).
    """
    if units_um == MM_UM:
        return counts
    mm = (counts.astype(np.uint32) * np.uint32(units_um) + np.uint32(MM_UM // 2)) // np.uint32(
        MM_UM
    )
    if units_um > MM_UM:
        mm[mm > np.iinfo(np.uint16).max] = 0
    return mm.astype(np.uint16)


def lens_fields(model: str, coeffs: tuple[float, ...], where: str) -> dict[str, Any]:
    """The :class:`Intrinsics` lens fields for a stream's SDK distortion model and coefficients
    ({} for an ideal pinhole).

    Raises:
        RecordingError: a model depthnav does not model, with non-zero coefficients.
    """
    name = " ".join(model.replace("_", " ").lower().split())
    if not any(coeffs):
        return {}
    if name in SDK_MODELS:
        target, keys = SDK_MODELS[name]
        values = (tuple(float(c) for c in coeffs) + (0.0,) * len(keys))[: len(keys)]
        return {"distortion_model": target, **dict(zip(keys, values, strict=True))}
    shown = ", ".join(f"{c:.4g}" for c in coeffs)
    raise RecordingError(
        f"{where}: the depth stream's lens model {model!r} [{shown}] is not supported",
        hint=HINT_LENS,
    )


def intrinsics_of(
    width: int,
    height: int,
    fx: float,
    fy: float,
    ppx: float,
    ppy: float,
    model: str,
    coeffs: tuple[float, ...],
    where: str,
) -> Intrinsics:
    """The :class:`Intrinsics` of an SDK stream profile (rs2_intrinsics fields).

    Raises:
        RecordingError: a lens model depthnav does not model, or values that do not fit.
    """
    # the SDK's values are float32: a recording's decimal text of them and the SDK's own give
    # the same Intrinsics once both are rounded to float32
    f32 = [float(np.float32(v)) for v in (fx, fy, ppx, ppy)]
    lens = lens_fields(model, tuple(float(np.float32(c)) for c in coeffs), where)
    try:
        return Intrinsics(width, height, *f32, **lens)
    except ValueError as exc:
        raise RecordingError(f"{where}: the depth stream's intrinsics do not fit: {exc}") from None


@dataclass(frozen=True, slots=True)
class RealSenseLayout:
    """What the RealSense topics of a bag say about its depth stream.

    Attributes:
        depth_topic: the depth image topic.
        units_um: depth units, micrometres per count.
        intrinsics: the depth stream's camera (None when the recording lacks its camera_info).
        model: the SDK's name of the distortion model ("" when unknown).
        accel_topic: the accelerometer's Imu topic of the same device, or None.
    """

    depth_topic: str
    units_um: int
    intrinsics: Intrinsics | None
    model: str
    accel_topic: str | None


def _text(msg: Any) -> str:
    return str(getattr(msg, "data", ""))


def _parse_pairs(text: str) -> dict[str, str]:
    """'a=1;b=2;' as {'a': '1', 'b': '2'}."""
    out = {}
    for part in text.split(";"):
        key, eq, value = part.partition("=")
        if eq:
            out[key.strip().lower()] = value.strip()
    return out


def probe_layout(
    depth_topic: str,
    topic_names: list[str],
    first: Callable[[str], Any],
    shape: tuple[int, int],
    where: str,
) -> RealSenseLayout:
    """The layout of the RealSense depth stream on ``depth_topic``.

    Args:
        depth_topic: a topic :data:`DEPTH_TOPIC` matches.
        topic_names: every topic of the bag.
        first: a callable (topic) -> the first message on that topic, or None when absent.
        shape: (H, W) of the depth images.
        where: the bag, for messages.

    Raises:
        RecordingError: no or bad depth units, a lens model depthnav does not model, a camera
            that does not fit the images.
    """
    match = DEPTH_TOPIC.match(depth_topic)
    assert match is not None
    device, sensor, index = match.group(1), match.group(2), match.group(3)
    sensor_root = f"/device_{device}/sensor_{sensor}"
    stream_root = f"{sensor_root}/Depth_{index}"
    units_msg = first(f"{sensor_root}/option/Depth_Units/value")
    if units_msg is None:
        raise RecordingError(
            f"{where}: a RealSense recording without {sensor_root}/option/Depth_Units/value: "
            "the depth units are unknown",
            hint="record with the RealSense SDK's recorder (rs-record, realsense-viewer), "
            "which writes the depth sensor's options",
        )
    raw_units = getattr(units_msg, "data", None)
    try:
        units_m = float(raw_units) if isinstance(raw_units, (str, int, float)) else math.nan
    except ValueError:
        units_m = math.nan
    units_um = units_um_from_m(units_m, f"{where} {sensor_root}/option/Depth_Units")
    height, width = shape
    intr: Intrinsics | None = None
    model = ""
    info_where = f"{where} {stream_root} camera_info"
    text_info = first(f"{stream_root}/camera_info")  # ROS 2: a String of key=value pairs
    cam_info = first(f"{stream_root}/info/camera_info")  # ROS 1: CameraInfo, SDK model name
    try:
        if text_info is not None:
            pairs = _parse_pairs(_text(text_info))
            model = pairs.get("model", "")
            coeffs = tuple(float(c) for c in pairs.get("coeffs", "").split(",") if c.strip())
            size = (int(pairs["width"]), int(pairs["height"]))
            values = [float(pairs[k]) for k in ("fx", "fy", "ppx", "ppy")]
        elif cam_info is not None:
            model = str(cam_info.distortion_model)
            k = np.asarray(getattr(cam_info, "K", getattr(cam_info, "k", ())), dtype=np.float64)
            d = getattr(cam_info, "D", getattr(cam_info, "d", ()))
            coeffs = tuple(float(c) for c in np.asarray(d, dtype=np.float64).reshape(-1))
            size = (int(cam_info.width), int(cam_info.height))
            values = [float(k[0]), float(k[4]), float(k[2]), float(k[5])]
        else:
            size = None
    except (KeyError, ValueError, IndexError, TypeError):
        raise RecordingError(f"{info_where} cannot be read", hint="re-record it") from None
    if size is not None:
        if size != (width, height):
            raise RecordingError(
                f"{info_where} is {size[0]}x{size[1]}, the images {width}x{height}",
                hint="the recording is damaged: re-record it",
            )
        intr = intrinsics_of(width, height, *values, model, coeffs, info_where)
    accel = accel_topic_of(depth_topic, topic_names)
    return RealSenseLayout(depth_topic, units_um, intr, model, accel)


def accel_topic_of(depth_topic: str, topics: list[str]) -> str | None:
    """The accelerometer Imu topic of the depth stream's device (the first Accel stream)."""
    match = DEPTH_TOPIC.match(depth_topic)
    if match is None:
        return None
    pattern = re.compile(rf"/device_{match.group(1)}/sensor_\d+/Accel_\d+/imu/data\Z")
    found = sorted(t for t in topics if pattern.match(t))
    return found[0] if found else None


def probe_bag(
    depth_topic: str,
    topics: dict[str, tuple[str, list[Any], int]],
    first_of: Callable[[list[Any]], tuple[Any, int] | None],
    shape: tuple[int, int],
    where: str,
) -> RealSenseLayout | None:
    """The RealSense layout of a bag whose depth is on ``depth_topic``, or None when the topic
    is not librealsense's (the hook drivers/formats/rosbag.py calls).

    Args:
        topics: topic -> (message type, its connections, message count), as rosbag.py lists them.
        first_of: a callable (connections) -> (first message, log time) or None.
    """
    if not DEPTH_TOPIC.match(depth_topic):
        return None

    def first(topic: str) -> Any:
        if topic not in topics or topics[topic][2] <= 0:
            return None
        found = first_of(topics[topic][1])
        return None if found is None else found[0]

    layout = probe_layout(depth_topic, list(topics), first, shape, where)
    if layout.accel_topic is not None and topics[layout.accel_topic][2] <= 0:
        layout = RealSenseLayout(
            layout.depth_topic, layout.units_um, layout.intrinsics, layout.model, None
        )
    return layout
