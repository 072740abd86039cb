"""Test-only: ROS bags written with rosbags' own writers from depthnav frames."""

from __future__ import annotations

import math
import shutil
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from drivers.base import Frame

DEPTH_TOPIC = "/camera/depth/image_raw"
INFO_TOPIC = "/camera/depth/camera_info"
IMU_TOPIC = "/camera/imu"
OPTICAL = "camera_depth_optical_frame"
T0_S = 1_700_000_000  # header stamps: a realistic UNIX time


@dataclass
class BagSpec:
    """How to write a test bag.

    Attributes:
        kind: "ros1" (.bag), "db3" or "mcap" (ROS 2 folders).
        encoding: "16UC1" (mm) or "32FC1" (m).
        bigendian: write the image bytes big-endian.
        pad: bytes of padding after each image row (``step`` larger than the row).
        info: write a CameraInfo per image.
        imu_frame: write an Imu per image in this frame (None: no Imu).
        tf_static: (parent, child, quaternion xyzw[, translation xyz]) static transforms.
        extra_images: more Image topics: name -> encoding (written with the same frames).
        distortion: D coefficients of the CameraInfo.
        distortion_model: its distortion_model.
        depth_topic: the topic of the depth images.
        compress: writes CompressedImage depth instead of Image: frame -> (format, data bytes).
        info_on_depth: also write a CameraInfo on the depth topic, before its first image.
    """

    kind: str = "ros1"
    encoding: str = "16UC1"
    bigendian: bool = False
    pad: int = 0
    info: bool = True
    imu_frame: str | None = None
    tf_static: Sequence[tuple] = ()
    extra_images: dict[str, str] = field(default_factory=dict)
    distortion: tuple[float, ...] = (0.0, 0.0, 0.0, 0.0, 0.0)
    distortion_model: str = "plumb_bob"
    depth_topic: str = DEPTH_TOPIC
    compress: Callable[[Frame], tuple[str, bytes]] | None = None
    info_on_depth: bool = False


def _typestore(kind: str) -> Any:
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore

    if kind != "ros1":
        return get_typestore(Stores.ROS2_HUMBLE)
    store = get_typestore(Stores.ROS1_NOETIC)
    store.register(
        get_types_from_msg("geometry_msgs/TransformStamped[] transforms", "tf2_msgs/msg/TFMessage")
    )
    return store


def image_msg(ts: Any, frame: Frame, stamp: Any, spec: BagSpec, encoding: str) -> Any:
    """A sensor_msgs/Image of ``frame`` in ``encoding`` with the spec's byte order and padding."""
    order = ">" if spec.bigendian else "<"
    if encoding == "32FC1":
        values = (frame.depth_mm.astype(np.float64) / 1000.0).astype(order + "f4")
        values[frame.depth_mm == 0] = np.nan  # REP 118: NaN is "no reading"
    elif encoding in ("16UC1", "mono16"):
        values = frame.depth_mm.astype(order + "u2")
    else:  # a colour image: rgb8
        values = np.repeat((frame.depth_mm >> 8).astype(np.uint8)[..., None], 3, axis=2)
    h, w = frame.depth_mm.shape
    row = values.reshape(h, -1).view(np.uint8)
    data = np.zeros((h, row.shape[1] + spec.pad), dtype=np.uint8)
    data[:, : row.shape[1]] = row
    data[:, row.shape[1] :] = 0xAB  # padding must be skipped, not read
    return ts.types["sensor_msgs/msg/Image"](
        header=header(ts, stamp, OPTICAL),
        height=h,
        width=w,
        encoding=encoding,
        is_bigendian=int(spec.bigendian),
        step=data.shape[1],
        data=data.reshape(-1),
    )


def compressed_msg(ts: Any, stamp: Any, fmt: str, data: bytes) -> Any:
    """A sensor_msgs/CompressedImage of ``format`` ``fmt`` holding ``data``."""
    return ts.types["sensor_msgs/msg/CompressedImage"](
        header=header(ts, stamp, OPTICAL), format=fmt, data=np.frombuffer(data, dtype=np.uint8)
    )


def header(ts: Any, stamp: Any, frame_id: str) -> Any:
    cls = ts.types["std_msgs/msg/Header"]
    if "seq" in cls.__dataclass_fields__:
        return cls(seq=0, stamp=stamp, frame_id=frame_id)
    return cls(stamp=stamp, frame_id=frame_id)


def info_msg(ts: Any, frame: Frame, stamp: Any, spec: BagSpec) -> Any:
    i = frame.intrinsics
    k = np.array([i.fx, 0, i.cx, 0, i.fy, i.cy, 0, 0, 1], dtype=np.float64)
    p = np.array([i.fx, 0, i.cx, 0, 0, i.fy, i.cy, 0, 0, 0, 1, 0], dtype=np.float64)
    names = ("D", "K", "R", "P") if spec.kind == "ros1" else ("d", "k", "r", "p")
    arrays = (np.array(spec.distortion), k, np.eye(3).reshape(-1), p)
    roi = ts.types["sensor_msgs/msg/RegionOfInterest"](
        x_offset=0, y_offset=0, height=0, width=0, do_rectify=False
    )
    return ts.types["sensor_msgs/msg/CameraInfo"](
        header=header(ts, stamp, OPTICAL),
        height=i.height,
        width=i.width,
        distortion_model=spec.distortion_model,
        binning_x=0,
        binning_y=0,
        roi=roi,
        **dict(zip(names, arrays, strict=True)),
    )


def imu_msg(ts: Any, accel: tuple[float, float, float], stamp: Any, frame_id: str) -> Any:
    vec = ts.types["geometry_msgs/msg/Vector3"]
    quat = ts.types["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0, w=1.0)
    cov = np.zeros(9)
    return ts.types["sensor_msgs/msg/Imu"](
        header=header(ts, stamp, frame_id),
        orientation=quat,
        orientation_covariance=np.r_[-1.0, np.zeros(8)],
        angular_velocity=vec(x=0.0, y=0.0, z=0.0),
        angular_velocity_covariance=cov,
        linear_acceleration=vec(x=accel[0], y=accel[1], z=accel[2]),
        linear_acceleration_covariance=cov,
    )


def tf_msg(ts: Any, stamp: Any, transforms: Sequence[tuple]) -> Any:
    """A TFMessage of (parent, child, quaternion xyzw[, translation xyz m]) transforms."""
    t = ts.types
    out = []
    for parent, child, (qx, qy, qz, qw), *rest in transforms:
        x, y, z = rest[0] if rest else (0.0, 0.0, 0.0)
        out.append(
            t["geometry_msgs/msg/TransformStamped"](
                header=header(ts, stamp, parent),
                child_frame_id=child,
                transform=t["geometry_msgs/msg/Transform"](
                    translation=t["geometry_msgs/msg/Vector3"](x=x, y=y, z=z),
                    rotation=t["geometry_msgs/msg/Quaternion"](x=qx, y=qy, z=qz, w=qw),
                ),
            )
        )
    return t["tf2_msgs/msg/TFMessage"](transforms=out)


class _Out:
    """One writer for either ROS version: connections, serialization."""

    def __init__(self, path: Path, kind: str) -> None:
        self.kind, self.ts = kind, _typestore(kind)
        if kind == "ros1":
            from rosbags.rosbag1 import Writer

            self.writer: Any = Writer(path)
        else:
            from rosbags.rosbag2 import StoragePlugin, Writer

            plugin = StoragePlugin.MCAP if kind == "mcap" else StoragePlugin.SQLITE3
            self.writer = Writer(path, version=9, storage_plugin=plugin)
        self.writer.open()
        self.conns: dict[str, Any] = {}

    def write(self, topic: str, msg: Any, t_ns: int) -> None:
        key = f"{topic} {msg.__msgtype__}"  # a topic may carry several types
        if key not in self.conns:
            self.conns[key] = self.writer.add_connection(topic, msg.__msgtype__, typestore=self.ts)
        if self.kind == "ros1":
            data = self.ts.serialize_ros1(msg, msg.__msgtype__)
        else:
            data = self.ts.serialize_cdr(msg, msg.__msgtype__)
        self.writer.write(self.conns[key], t_ns, data)


def write_bag(path: Path, frames: Sequence[Frame], spec: BagSpec) -> Path:
    """Write ``frames`` as a bag at ``path`` (a .bag file, or a ROS 2 folder); returns ``path``."""
    out = _Out(path, spec.kind)
    ts = out.ts
    stamp0 = ts.types["builtin_interfaces/msg/Time"](sec=T0_S, nanosec=0)
    if spec.tf_static:
        out.write("/tf_static", tf_msg(ts, stamp0, spec.tf_static), T0_S * 10**9)
    for frame in frames:
        t_ns = T0_S * 10**9 + round(frame.timestamp_s * 1e9)
        stamp = ts.types["builtin_interfaces/msg/Time"](sec=t_ns // 10**9, nanosec=t_ns % 10**9)
        if spec.imu_frame is not None and frame.accel_mps2 is not None:
            out.write(IMU_TOPIC, imu_msg(ts, frame.accel_mps2, stamp, spec.imu_frame), t_ns)
        if spec.info_on_depth:
            out.write(spec.depth_topic, info_msg(ts, frame, stamp, spec), t_ns)
        if spec.compress is not None:
            depth = compressed_msg(ts, stamp, *spec.compress(frame))
        else:
            depth = image_msg(ts, frame, stamp, spec, spec.encoding)
        out.write(spec.depth_topic, depth, t_ns + 1)
        for topic, encoding in spec.extra_images.items():
            out.write(topic, image_msg(ts, frame, stamp, spec, encoding), t_ns + 2)
        if spec.info:
            out.write(INFO_TOPIC, info_msg(ts, frame, stamp, spec), t_ns + 3)
    out.writer.close()
    return path


def bare_storage(folder: Path, dest: Path) -> Path:
    """Copy a ROS 2 folder's storage file out as a bare ``.mcap``/``.db3`` at ``dest``."""
    (storage,) = [p for p in folder.iterdir() if p.suffix in (".mcap", ".db3")]
    shutil.copyfile(storage, dest)
    return dest


def quat_x(angle_rad: float) -> tuple[float, float, float, float]:
    return (math.sin(angle_rad / 2), 0.0, 0.0, math.cos(angle_rad / 2))
