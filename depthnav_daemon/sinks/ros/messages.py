"""ROS messages of a processed frame, shared by the ``rosbag`` and ``ros2`` sinks.

Messages are the ``rosbags`` library's classes (ROS 1 Noetic or ROS 2 Humble definitions), so one
builder serves ROS 1 bags, ROS 2 bags and live ROS 2 topics. Frames (names are options):

- ``base_frame`` (``base_link``): the robot, origin on the floor under its centre, x forward,
  y left, z up (REP 103); the sensor sits at ``[mount] x_m, y_m, height_m`` turned by ``yaw_deg``
  (:func:`sensor_placement`).
- ``scan_frame`` (``depthnav_scan``): the base frame's axes raised to the sensor's height
  (:func:`scan_origin`); the scans (ranges from the base origin, bearings from the robot's
  forward axis) are in it, the floor at z = -height.
- ``optical_frame`` (``depthnav_optical``): the depth camera's optical frame (x right, y down,
  z forward), tilted and rolled as the mount says.

Topics (names are options): ``/scan`` and ``/cliff/scan`` (sensor_msgs/LaserScan, REP 117
ranges: NaN no reading, +inf nothing within range_max, -inf closer than range_min),
``/cliff/points`` (sensor_msgs/PointCloud2, x y z float32 in the base frame: the drop-offs,
z = ``cliff_z`` exactly, :func:`cliff_xyz`), ``/tf`` (tf2_msgs/TFMessage: base -> scan frame
and base -> optical frame), and ``/depth_sensor_pose`` (geometry_msgs/PoseStamped in the base
frame: the sensor on the robot; orientation = the sensor body (x along the optical axis) as roll
about x = roll_deg (positive left side up), pitch about y = tilt_deg (positive nose down),
yaw = yaw_deg, ROS fixed-axis RPY; position = (x_m, y_m, height_m)).
With ``image=1`` also the depth image (sensor_msgs/Image 16UC1, optical frame) and its
CameraInfo, so ``replay:`` reads the bag back. With the obstacle memory on, the memory's topics
(``/memory/grid`` in ``odom_frame``, ``/memory/scan``, ``/memory/cliff/points``, odom -> base on
``/tf``): sinks/ros/memory_out.py.

Stamps: a ROS 2 ``builtin_interfaces/Time`` holds sec as int32 (up to 2038-01-19); a ROS 1 time
is uint32, but rosbags serialises it through the same int32 Time, so ROS 1 bags stop there too. A
frame time past that is a SinkError (:func:`check_stamp`), not a struct.error.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np
import numpy.typing as npt

from depthnav_daemon.errors import ConfigError, SinkError
from depthnav_daemon.pipeline.geometry import M_CAM_TO_FLU, rot_x, rot_y, rot_z
from depthnav_daemon.sinks.base import SinkSpec, bool_option, number_option

if TYPE_CHECKING:
    from depthnav_daemon.pipeline import Result
    from depthnav_daemon.pipeline.geometry import Mount
    from depthnav_daemon.pipeline.scan import LaserScan
    from drivers.base import Frame

F64 = npt.NDArray[np.float64]

NAME_OPTIONS = {  # option -> default frame id or topic name
    "base_frame": "base_link",
    "scan_frame": "depthnav_scan",
    "optical_frame": "depthnav_optical",
    "scan_topic": "/scan",
    "cliff_scan_topic": "/cliff/scan",
    "cliff_points_topic": "/cliff/points",
    "pose_topic": "/depth_sensor_pose",
    "tf_topic": "/tf",
    "image_topic": "/depthnav/depth/image_raw",
    "info_topic": "/depthnav/depth/camera_info",
    "odom_frame": "odom",  # the obstacle memory's (sinks/ros/memory_out.py)
    "memory_grid_topic": "/memory/grid",
    "memory_scan_topic": "/memory/scan",
    "memory_cliff_points_topic": "/memory/cliff/points",
}
OPTIONS = (*NAME_OPTIONS, "tf", "image", "cliff_z", "grid_rate", "odom_tf")
# z of the cliff points in the base frame (origin on the floor), metres: a clear distance below
# the floor, so Nav2's height filters (min_obstacle_height) keep or drop them by configuration,
# never by float rounding. At most -1 mm: 0 would sit exactly on the layer's default filter.
CLIFF_Z_DEFAULT = -0.05
CLIFF_Z_RANGE = (-1.0, -0.001)
# the memory's occupancy grid per second of frame time (0: none); a grid is the memory's size
GRID_RATE_DEFAULT = 2.0
GRID_RATE_RANGE = (0.0, 30.0)
TFMESSAGE_MSG = "geometry_msgs/TransformStamped[] transforms"
POINTFIELD_FLOAT32 = 7


def typestore(ros1: bool) -> Any:
    """The rosbags typestore for ROS 1 (Noetic, plus tf2_msgs/TFMessage) or ROS 2 (Humble)."""
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore

    if not ros1:
        return get_typestore(Stores.ROS2_HUMBLE)
    store = get_typestore(Stores.ROS1_NOETIC)
    store.register(get_types_from_msg(TFMESSAGE_MSG, "tf2_msgs/msg/TFMessage"))
    return store


@dataclass(frozen=True, slots=True)
class RosNames:
    """Frame ids and topic names (``NAME_OPTIONS``), which optional topics to write, the
    cliff points' z in the base frame (``cliff_z``, metres, negative: below the floor), the
    memory grid's rate (``grid_rate``, Hz of frame time, 0 = none) and whether ``/tf`` carries
    odom -> base (``odom_tf``: 0 when the robot's odometry publishes it)."""

    names: dict[str, str]
    tf: bool = True
    image: bool = False
    cliff_z: float = CLIFF_Z_DEFAULT
    grid_rate: float = GRID_RATE_DEFAULT
    odom_tf: bool = True

    @classmethod
    def from_spec(cls, spec: SinkSpec) -> RosNames:
        """From a sink spec's options. Raises ConfigError (one line) for a bad ``cliff_z``,
        ``grid_rate`` or flag, two topics of the same name, or an odometry frame named as the
        base frame."""
        names = {k: spec.options.get(k, v).strip() or v for k, v in NAME_OPTIONS.items()}
        topics: dict[str, str] = {}
        for key in (k for k in NAME_OPTIONS if k.endswith("_topic")):
            if names[key] in topics:
                raise ConfigError(
                    f"{topics[names[key]]} and {key} in sink spec {spec.text!r} are both "
                    f"{names[key]!r}",
                    hint="give each topic its own name",
                )
            topics[names[key]] = key
        if names["odom_frame"] == names["base_frame"]:
            raise ConfigError(
                f"odom_frame and base_frame in sink spec {spec.text!r} are both "
                f"{names['base_frame']!r}",
                hint="the odometry frame is the fixed one the robot moves in, e.g. odom",
            )
        cliff_z = float(number_option(spec, "cliff_z", CLIFF_Z_DEFAULT, *CLIFF_Z_RANGE))
        rate = float(number_option(spec, "grid_rate", GRID_RATE_DEFAULT, *GRID_RATE_RANGE))
        return cls(
            names,
            bool_option(spec, "tf", True),
            bool_option(spec, "image", False),
            cliff_z,
            rate,
            bool_option(spec, "odom_tf", True),
        )

    def __getitem__(self, key: str) -> str:
        return self.names[key]


def sensor_placement(mount: Mount) -> tuple[F64, F64]:
    """Where the sensor sits on the robot: (translation (3,) metres, rotation (3, 3)) in the base
    frame, the rotation taking sensor-body (x forward along the optical axis, y left, z up)
    vectors to the base frame: at (x_m, y_m, height_m), turned by yaw, pitched and rolled (ROS
    roll-pitch-yaw)."""
    translation = np.array([mount.x_m, mount.y_m, mount.height_m])
    return translation, rot_z(mount.yaw_rad) @ rot_y(mount.tilt_rad) @ rot_x(mount.roll_rad)


def scan_origin(mount: Mount) -> F64:
    """Origin of the scan frame in the base frame, (3,) metres: above the base origin at the
    sensor's height. The scans and cliff points are in the base frame's axes, ranges from the
    base origin (pipeline/placement.py), so only the height separates the two frames."""
    return np.array([0.0, 0.0, mount.height_m])


def quaternion(rot: F64) -> tuple[float, float, float, float]:
    """(x, y, z, w) of a (3, 3) rotation matrix, w >= 0."""
    m = rot
    w = math.sqrt(max(0.0, 1.0 + m[0, 0] + m[1, 1] + m[2, 2])) / 2.0
    x = math.copysign(
        math.sqrt(max(0.0, 1.0 + m[0, 0] - m[1, 1] - m[2, 2])) / 2.0, m[2, 1] - m[1, 2]
    )
    y = math.copysign(
        math.sqrt(max(0.0, 1.0 - m[0, 0] + m[1, 1] - m[2, 2])) / 2.0, m[0, 2] - m[2, 0]
    )
    z = math.copysign(
        math.sqrt(max(0.0, 1.0 - m[0, 0] - m[1, 1] + m[2, 2])) / 2.0, m[1, 0] - m[0, 1]
    )
    return x, y, z, w


def cliff_xyz(points_m: Any, cliff_z: float) -> npt.NDArray[np.float32]:
    """The cliff points as (K, 3) little-endian float32 in the base frame: x, y (metres) of the
    finite points, z = ``cliff_z`` exactly. In the base frame, not the scan frame, so no
    transform adds the height back (float32(-h) + h came out +-1e-8, either side of Nav2's
    0.0 filter)."""
    xy = np.asarray(points_m, dtype=np.float32).reshape(-1, 2)
    if not np.isfinite(xy).all():
        xy = xy[np.isfinite(xy).all(axis=1)]
    xyz = np.empty((len(xy), 3), dtype="<f4")
    xyz[:, :2] = xy
    xyz[:, 2] = np.float32(cliff_z)
    return xyz


def stamp_ns(t_s: float) -> int:
    """A frame time in whole nanoseconds (0 for negative or non-finite times)."""
    return max(0, round(t_s * 1e9)) if math.isfinite(t_s) else 0


INT32_SEC_MAX = 2**31 - 1  # builtin_interfaces/Time.sec: 2038-01-19T03:14:07Z
UINT32_SEC_MAX = 2**32 - 1  # foxglove.Timestamp.sec: 2106-02-07T06:28:15Z


def check_stamp(t_ns: int, sec_max: int, what: str) -> int:
    """``t_ns`` (a stamp in ns) when its whole seconds fit ``sec_max``.

    Raises:
        SinkError: one line naming the time and the type's limit, with a hint.
    """
    if t_ns // 10**9 > sec_max:
        raise SinkError(
            f"frame time {t_ns / 1e9:.3f} s is past what {what} holds (sec at most {sec_max})",
            hint="the source's timestamps are not a time ROS can carry; check the recording's "
            "stamps (a looped replay goes on from the recording's own first stamp)",
        )
    return t_ns


class MessageBuilder:
    """Builds the ROS messages of one frame for a typestore (see the module docstring)."""

    def __init__(self, store: Any, names: RosNames) -> None:
        self.store = store
        self.names = names
        self.t = store.types
        self._header_has_seq = "seq" in self.t["std_msgs/msg/Header"].__dataclass_fields__
        # ROS 1 (its Header has seq) time is uint32 seconds, but rosbags packs it as int32
        self.sec_max = INT32_SEC_MAX
        self.time_type = (
            "a ROS 1 time as rosbags writes it (int32 sec)"
            if self._header_has_seq
            else "a ROS 2 builtin_interfaces/Time (int32 sec)"
        )

    def msgtypes(self) -> dict[str, str]:
        """topic -> message type of every topic this builder may write."""
        n = self.names
        out = {
            n["scan_topic"]: "sensor_msgs/msg/LaserScan",
            n["cliff_scan_topic"]: "sensor_msgs/msg/LaserScan",
            n["cliff_points_topic"]: "sensor_msgs/msg/PointCloud2",
            n["pose_topic"]: "geometry_msgs/msg/PoseStamped",
        }
        if n.tf:
            out[n["tf_topic"]] = "tf2_msgs/msg/TFMessage"
        if n.image:
            out[n["image_topic"]] = "sensor_msgs/msg/Image"
            out[n["info_topic"]] = "sensor_msgs/msg/CameraInfo"
        return out

    def header(self, t_ns: int, frame_id: str) -> Any:
        stamp = self.t["builtin_interfaces/msg/Time"](sec=t_ns // 10**9, nanosec=t_ns % 10**9)
        if self._header_has_seq:
            return self.t["std_msgs/msg/Header"](seq=0, stamp=stamp, frame_id=frame_id)
        return self.t["std_msgs/msg/Header"](stamp=stamp, frame_id=frame_id)

    def laser_scan(self, scan: LaserScan, t_ns: int) -> Any:
        return self.t["sensor_msgs/msg/LaserScan"](
            header=self.header(t_ns, self.names["scan_frame"]),
            angle_min=float(scan.angle_min),
            angle_max=float(scan.angle_max),
            angle_increment=float(scan.angle_increment),
            time_increment=0.0,
            scan_time=0.0,
            range_min=float(scan.range_min),
            range_max=float(scan.range_max),
            ranges=np.asarray(scan.ranges, dtype=np.float32),
            intensities=np.zeros(0, dtype=np.float32),
        )

    def points(self, xyz: npt.NDArray[np.float32], t_ns: int) -> Any:
        """A PointCloud2 of (K, 3) float32 points in the base frame (the cliff points)."""
        field = self.t["sensor_msgs/msg/PointField"]
        fields = [
            field(name=c, offset=4 * i, datatype=POINTFIELD_FLOAT32, count=1)
            for i, c in enumerate("xyz")
        ]
        data = np.ascontiguousarray(xyz, dtype="<f4")
        return self.t["sensor_msgs/msg/PointCloud2"](
            header=self.header(t_ns, self.names["base_frame"]),
            height=1,
            width=int(data.shape[0]),
            fields=fields,
            is_bigendian=False,
            point_step=12,
            row_step=12 * int(data.shape[0]),
            data=data.reshape(-1).view(np.uint8),
            is_dense=True,
        )

    def _vector(self, v: F64) -> Any:
        return self.t["geometry_msgs/msg/Vector3"](x=float(v[0]), y=float(v[1]), z=float(v[2]))

    def _quat(self, rot: F64) -> Any:
        x, y, z, w = quaternion(rot)
        return self.t["geometry_msgs/msg/Quaternion"](x=x, y=y, z=z, w=w)

    def transforms(self, mount: Mount, t_ns: int) -> Any:
        """/tf: base -> scan frame (level) and base -> optical frame."""
        translation, body = sensor_placement(mount)
        level = np.eye(3)  # the scan frame keeps the base frame's axes
        optical = body @ M_CAM_TO_FLU
        out = []
        for child, origin, rot in (
            (self.names["scan_frame"], scan_origin(mount), level),
            (self.names["optical_frame"], translation, optical),
        ):
            out.append(
                self.t["geometry_msgs/msg/TransformStamped"](
                    header=self.header(t_ns, self.names["base_frame"]),
                    child_frame_id=child,
                    transform=self.t["geometry_msgs/msg/Transform"](
                        translation=self._vector(origin), rotation=self._quat(rot)
                    ),
                )
            )
        return self.t["tf2_msgs/msg/TFMessage"](transforms=out)

    def pose(self, mount: Mount, t_ns: int) -> Any:
        translation, body = sensor_placement(mount)
        point = self.t["geometry_msgs/msg/Point"](
            x=float(translation[0]), y=float(translation[1]), z=float(translation[2])
        )
        return self.t["geometry_msgs/msg/PoseStamped"](
            header=self.header(t_ns, self.names["base_frame"]),
            pose=self.t["geometry_msgs/msg/Pose"](position=point, orientation=self._quat(body)),
        )

    def image(self, frame: Frame, t_ns: int) -> tuple[Any, Any]:
        """The depth image (16UC1, little-endian) and its CameraInfo."""
        depth = np.ascontiguousarray(frame.depth_mm, dtype="<u2")
        h, w = depth.shape
        header = self.header(t_ns, self.names["optical_frame"])
        img = self.t["sensor_msgs/msg/Image"](
            header=header, height=h, width=w, encoding="16UC1", is_bigendian=0, step=2 * w,
            data=depth.reshape(-1).view(np.uint8),
        )  # fmt: skip
        i = frame.intrinsics
        k = np.array([i.fx, 0.0, i.cx, 0.0, i.fy, i.cy, 0.0, 0.0, 1.0])
        p = np.array([i.fx, 0.0, i.cx, 0.0, 0.0, i.fy, i.cy, 0.0, 0.0, 0.0, 1.0, 0.0])
        arrays = dict(
            zip(
                ("d", "k", "r", "p"),
                (np.array(i.distortion, np.float64), k, np.eye(3).reshape(-1), p),
                strict=True,
            )
        )
        if self._header_has_seq:  # ROS 1 spells them in capitals
            arrays = {key.upper(): value for key, value in arrays.items()}
        roi = self.t["sensor_msgs/msg/RegionOfInterest"](
            x_offset=0, y_offset=0, height=0, width=0, do_rectify=False
        )
        info = self.t["sensor_msgs/msg/CameraInfo"](
            header=header, height=h, width=w, distortion_model=i.distortion_model, binning_x=0,
            binning_y=0, roi=roi, **arrays,
        )  # fmt: skip
        return img, info

    def messages(
        self, frame: Frame, result: Result, t_ns: int | None = None
    ) -> tuple[int, list[tuple[str, Any]]]:
        """(stamp ns, [(topic, message)]) of one frame: only what the frame has. The stamp is
        ``t_ns`` when given (live topics: the wall clock), else the frame's own time."""
        if t_ns is None:
            t_ns = stamp_ns(result.timestamp_s)
        check_stamp(t_ns, self.sec_max, self.time_type)
        n = self.names
        out: list[tuple[str, Any]] = [(n["scan_topic"], self.laser_scan(result.scan, t_ns))]
        if result.cliff is not None:
            out.append((n["cliff_scan_topic"], self.laser_scan(result.cliff.scan, t_ns)))
            xyz = cliff_xyz(result.cliff.points_m, n.cliff_z)
            out.append((n["cliff_points_topic"], self.points(xyz, t_ns)))
        out.append((n["pose_topic"], self.pose(result.mount, t_ns)))
        if n.tf:
            out.append((n["tf_topic"], self.transforms(result.mount, t_ns)))
        if n.image:
            img, info = self.image(frame, t_ns)
            out += [(n["image_topic"], img), (n["info_topic"], info)]
        return t_ns, out
