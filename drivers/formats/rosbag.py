"""ROS bags as depth recordings, read with the pure-Python ``rosbags`` library (no ROS needed).

Paths: a ROS 1 ``.bag``; a ROS 2 bag folder (``metadata.yaml`` with sqlite3 ``.db3`` or ``.mcap``
storage); a bare ROS 2 ``.mcap`` or ``.db3`` file.

What is read:
- depth from ``sensor_msgs/Image`` with encoding ``16UC1`` or ``mono16`` (millimetres) or
  ``32FC1`` (metres), big- or little-endian, rows ``step`` bytes apart (padding skipped); or from
  ``sensor_msgs/CompressedImage`` of image_transport's ``compressedDepth`` (png or rvl, see
  compressed_depth.py). With no ``topic`` the only such topic is used (the first message of each
  image topic tells its encoding); a mono16 topic only when no other depth topic is there (mono16
  is infrared's encoding too), and ``X`` rather than its own ``X/compressedDepth``. Of a topic
  with connections of several types, only the image connections are read.
- intrinsics from the first ``sensor_msgs/CameraInfo`` on ``info_topic`` (default: the
  ``camera_info`` beside the depth topic, or the bag's only CameraInfo topic): fx, fy, cx, cy
  from K, scaled when the info's size differs from the image's. The distortion model and
  coefficients are kept on :class:`CameraModel`, but lens distortion is not modelled yet: the
  image is treated as an ideal pinhole (a line in the log says so when D is not all zero).
- the accelerometer from the bag's only ``sensor_msgs/Imu`` topic (the latest message before
  each image), turned into the depth image's optical frame: used as is when the IMU's frame is
  the image's, else through the rotations of ``/tf_static``; an IMU the static transforms do not
  join to the camera is left out (the log says so).
- timestamps from the image headers (the bag's receive time where a header stamp is 0).

Known traps of ``rosbags``: a ROS 2 folder whose ``metadata.yaml`` QoS differs from its storage
file reads no message through the folder, so the storage files are then read directly.
Frames are streamed: one storage chunk is decompressed at a time, never the whole bag, and no
chunk beyond the bounds of bag_limits.py (installed into rosbags before a bag is opened; a ROS 2
folder's metadata.yaml is checked there first). An .mcap that rosbags cannot open (cut short:
no footer or summary) is read front to back by mcap_stream.py. A ``topic`` or ``info_topic``
the bag does not have is a DeviceSpecError (bad usage).
"""

from __future__ import annotations

import logging
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from drivers.base import SensorPlacement
from drivers.errors import DeviceSpecError, DriverError, RecordingError
from drivers.formats import bag_limits, realsense_layout, ros_tf
from drivers.formats.mcap_stream import StreamedMcap, open_cut_short
from drivers.formats.ros_decode import (
    HINT_BROKEN,
    CameraModel,
    camera_model,
    decode_image,
    image_kind,
    is_depth_kind,
    stamp_s,
)
from drivers.values import short_repr, short_text

log = logging.getLogger(__name__)

IMAGE = "sensor_msgs/msg/Image"
COMPRESSED = "sensor_msgs/msg/CompressedImage"
CAMERA_INFO = "sensor_msgs/msg/CameraInfo"
IMU = "sensor_msgs/msg/Imu"
TF_STATIC = ros_tf.TF_STATIC
SUFFIXES = (".bag", ".mcap", ".db3")

Item = tuple[float, npt.NDArray[np.uint16], tuple[float, float, float] | None]


def is_rosbag(path: Path) -> bool:
    """True for a ``.bag``/``.mcap``/``.db3`` file or a ROS 2 bag folder (``metadata.yaml``)."""
    if path.is_dir():
        return (path / "metadata.yaml").is_file()
    return path.suffix.lower() in SUFFIXES


@dataclass(frozen=True, slots=True)
class BagProbe:
    """What :meth:`DepthBag.probe` found.

    Attributes:
        depth_topic, info_topic, imu_topic: topics used (None: absent or not usable).
        shape: (height, width) of the depth images.
        camera: the CameraInfo's camera, or None when the bag has none.
        frames: number of depth images.
        imu_to_camera: (3, 3) rotation from the IMU's frame to the image's optical frame.
        units_um: micrometres per image count (1000: the images are millimetres; a RealSense
            recording's Depth_Units otherwise, see realsense_layout.py).
        placement: the depth camera on the robot from ``/tf_static`` (ros_tf.camera_placement),
            or None where the static transforms do not join a base frame to it.
    """

    depth_topic: str
    info_topic: str | None
    imu_topic: str | None
    shape: tuple[int, int]
    camera: CameraModel | None
    frames: int
    imu_to_camera: npt.NDArray[np.float64] | None
    units_um: int = realsense_layout.MM_UM
    placement: SensorPlacement | None = None  # the camera on the robot, from /tf_static


class DepthBag:
    """Depth frames of one image topic of a ROS bag; nothing stays open between calls.

    Args:
        path: the bag (see the module docstring).
        topic: the depth image topic, or None for the bag's only depth topic.
        info_topic: the CameraInfo topic, or None to find it.
    """

    def __init__(
        self,
        path: Path,
        topic: str | None = None,
        info_topic: str | None = None,
        base_frame: str | None = None,
    ) -> None:
        self.path = path
        self.topic = topic
        self.info_topic = info_topic
        self.base_frame = base_frame  # the robot's frame the camera's placement is taken in
        self._paths: list[Path] = [path]
        self._probe: BagProbe | None = None
        self._tf: dict[tuple[str, str], npt.NDArray[np.float64]] | None = None
        self._warned_streamed = False

    # --- opening -----------------------------------------------------------------------
    def _reader(self) -> Any:
        """An opened rosbags AnyReader over ``self._paths``, or a StreamedMcap for an .mcap
        that rosbags cannot open (cut short: no footer or summary)."""
        from rosbags.highlevel import AnyReader
        from rosbags.typesys import Stores, get_typestore

        bag_limits.install()  # bounded decompression (before rosbags inflates anything)
        if self._paths == [self.path] and self.path.is_dir():
            bag_limits.check_metadata(self.path)  # small and shallow before rosbags parses it
        try:
            reader = AnyReader(self._paths, default_typestore=get_typestore(Stores.ROS2_HUMBLE))
            reader.open()
        except bag_limits.StoppedError:
            raise
        except RecordingError as exc:  # bag_limits' refusal, raised inside rosbags
            raise self._broken(exc, "cannot be opened") from None
        except Exception as exc:  # a third-party parser on a damaged file: many exception types
            streamed = self._streamed()
            if streamed is None:
                raise self._broken(exc, "cannot be opened") from None
            return streamed
        return reader

    def _streamed(self) -> StreamedMcap | None:
        """The bag's one .mcap file read front to back when it is cut short, else None."""
        reader = open_cut_short(self.path)
        if reader is not None and not self._warned_streamed:
            self._warned_streamed = True
            log.warning(
                "%s: no readable summary or footer (cut short?): read front to back, %d messages%s",
                reader.path,
                sum(c.msgcount for c in reader.connections),
                ", the last record cut" if reader.cut else "",
            )
        return reader

    def _broken(self, exc: BaseException, what: str) -> DriverError:
        if isinstance(exc, bag_limits.StoppedError):
            return exc  # a stop, not a damaged bag
        text = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        if isinstance(exc, RecordingError):  # bag_limits' bounds, the streamed reader's cut
            return RecordingError(
                f"{self.path}: not a readable ROS bag, {what} ({short_text(text, 160)})",
                hint=exc.hint or HINT_BROKEN,
            )
        suffix = self.path.suffix.lower()
        hint = HINT_BROKEN
        if suffix == ".bag":
            hint = "the bag is truncated or damaged: `rosbag reindex` may repair it"
            if "index" in text.lower():
                hint = "the ROS 1 bag has no index (recording cut short?): run `rosbag reindex`"
        elif suffix == ".mcap":
            hint = "the bag is truncated or damaged: `mcap recover` (the mcap CLI) may save it"
        return RecordingError(
            f"{self.path}: not a readable ROS bag, {what} ({short_text(text, 120)})", hint=hint
        )

    def _first(self, reader: Any, conns: list[Any]) -> tuple[Any, int] | None:
        """The first message (deserialized) and its log time on ``conns``, or None."""
        try:
            for conn, t_ns, raw in reader.messages(connections=conns):
                return reader.deserialize(raw, conn.msgtype), t_ns
        except Exception as exc:  # see _reader
            raise self._broken(exc, "reading failed") from None
        return None

    def probe(self, intrinsics_given: bool = False) -> BagProbe:
        """Open the bag, choose the topics, read the camera; close it again.

        Args:
            intrinsics_given: the caller has fx, fy, cx, cy, so a bag without CameraInfo is fine.

        Raises:
            RecordingError: not a readable bag, no depth topic or several (listed), an encoding
                that is not depth, compressed depth, no CameraInfo (unless ``intrinsics_given``).
        """
        with bag_limits.stoppable():  # a stop ends the probing between two pieces of a chunk
            return self._probe_bag(intrinsics_given)

    def _probe_bag(self, intrinsics_given: bool) -> BagProbe:
        reader = self._reader()
        try:
            topics = self._topics(reader)
            if self.path.is_dir() and self._reads_nothing(reader, topics):
                reader = self._storage_fallback(reader)
                topics = self._topics(reader)
            depth = self._depth_topic(reader, topics)
            first = self._first(reader, topics[depth][1])
            if first is None:
                raise RecordingError(
                    f"{self.path}: topic {short_repr(depth)} holds no message",
                    hint="the recording stopped before the first image? pick another ?topic=",
                )
            image = first[0]
            depth_mm = decode_image(image, f"{self.path} {depth}")  # checks encoding and size
            shape = (int(depth_mm.shape[0]), int(depth_mm.shape[1]))
            if image_kind(image) == "mono16":
                log.info("%s %s: mono16 images read as depth in millimetres", self.path, depth)
            rs = realsense_layout.probe_bag(  # librealsense's own layout, else None
                depth, topics, lambda conns: self._first(reader, conns), shape, str(self.path)
            )
            if rs is not None and rs.intrinsics is not None and self.info_topic is None:
                info_topic, camera = None, CameraModel(rs.intrinsics, rs.model, (), "")
            else:
                info_topic, camera = self._camera(reader, topics, depth, shape, intrinsics_given)
            if rs is not None and rs.accel_topic is not None:  # in the depth axes already
                imu_topic, imu_rot = rs.accel_topic, np.eye(3)
            else:
                imu_topic, imu_rot = self._imu(reader, topics, str(image.header.frame_id))
            placement = ros_tf.camera_placement(
                self._static(reader, topics), str(image.header.frame_id), self.base_frame
            )
            self._probe = BagProbe(
                depth, info_topic, imu_topic, shape, camera, topics[depth][2], imu_rot,
                rs.units_um if rs is not None else realsense_layout.MM_UM, placement,
            )  # fmt: skip
            return self._probe
        finally:
            reader.close()

    def _reads_nothing(self, reader: Any, topics: dict[str, tuple[str, list[Any], int]]) -> bool:
        """True when an image topic with messages in metadata.yaml yields none (the QoS trap)."""
        return any(
            msgtype in (IMAGE, COMPRESSED) and count > 0 and self._first(reader, conns) is None
            for msgtype, conns, count in topics.values()
        )

    def _storage_fallback(self, reader: Any) -> Any:
        """Reopen a ROS 2 folder through its storage files (metadata QoS != storage QoS)."""
        files = sorted(
            p for p in self.path.iterdir() if p.suffix in (".mcap", ".db3") and p.is_file()
        )
        reader.close()
        if not files:
            raise RecordingError(
                f"{self.path}: images read no message through metadata.yaml and the folder "
                "has no plain .mcap/.db3 storage file",
                hint=HINT_BROKEN,
            )
        log.warning(
            "%s: metadata.yaml does not match its storage file (QoS differs): reading %s directly",
            self.path,
            ", ".join(p.name for p in files),
        )
        self._paths = files
        return self._reader()

    def _topics(self, reader: Any) -> dict[str, tuple[str, list[Any], int]]:
        """topic -> (message type, its connections, message count).

        A topic with connections of several types (a CameraInfo published on the depth topic)
        keeps its image connections (Image, else CompressedImage), else its busiest type's.
        """
        by_type: dict[str, dict[str, tuple[list[Any], int]]] = {}
        for conn in reader.connections:
            types = by_type.setdefault(conn.topic, {})
            conns, count = types.get(conn.msgtype, ([], 0))
            n = conn.msgcount  # from metadata.yaml in a ROS 2 bag: anything YAML can hold
            if isinstance(n, bool) or not isinstance(n, int):
                raise RecordingError(
                    f"{self.path}: not a readable ROS bag, topic {short_repr(conn.topic)} has "
                    f"a message count of {short_repr(n)} (not a whole number)",
                    hint=HINT_BROKEN,
                )
            types[conn.msgtype] = ([*conns, conn], count + max(n, 0))
        out: dict[str, tuple[str, list[Any], int]] = {}
        for topic, types in by_type.items():
            images = [t for t in (IMAGE, COMPRESSED) if t in types]
            msgtype = images[0] if images else max(types, key=lambda t: types[t][1])
            out[topic] = (msgtype, *types[msgtype])
        return out

    def _depth_topic(self, reader: Any, topics: dict[str, tuple[str, list[Any], int]]) -> str:
        if self.topic is not None:  # the user's ?topic=: a wrong one is bad usage (exit 2)
            images = sorted(t for t, v in topics.items() if v[0] in (IMAGE, COMPRESSED))
            listed = short_text(", ".join(images) or "none", 200)
            if self.topic not in topics:
                raise DeviceSpecError(
                    f"{self.path}: no topic {short_repr(self.topic)}",
                    hint=f"image topics: {listed}",
                )
            msgtype = topics[self.topic][0]
            if msgtype not in (IMAGE, COMPRESSED):
                raise DeviceSpecError(
                    f"{self.path}: {short_repr(self.topic)} is a {msgtype}, not an {IMAGE}",
                    hint=f"image topics: {listed}",
                )
            return self.topic
        kinds: dict[str, str] = {}  # image topic -> what its first message holds
        empty: list[str] = []  # image topics without a message
        for name, (msgtype, conns, count) in sorted(topics.items()):
            if msgtype in (IMAGE, COMPRESSED):
                first = self._first(reader, conns) if count > 0 else None
                if first is None:
                    empty.append(name)
                else:
                    kinds[name] = image_kind(first[0])
        depth = [t for t, k in kinds.items() if is_depth_kind(k)]
        # a bag recorded with every transport: X and X/compressedDepth are the same images
        suffix = "/compressedDepth"
        depth = [t for t in depth if not (t.endswith(suffix) and t[: -len(suffix)] in depth)]
        if len(depth) > 1 and any(kinds[t] != "mono16" for t in depth):
            depth = [t for t in depth if kinds[t] != "mono16"]  # mono16: infrared's encoding too
        if len(depth) == 1:
            return depth[0]
        if len(depth) > 1:
            listed = short_text(", ".join(f"{t} ({kinds[t]})" for t in depth), 300)
            raise RecordingError(  # topic names come from the bag: cut to a line
                f"{self.path}: {len(depth)} depth image topics: {listed}",
                hint=f"choose one with ?topic={short_text(depth[0], 100)}",
            )
        others = ", ".join([f"{t} ({k or 'empty'})" for t, k in kinds.items()] +
                           [f"{t} (no messages)" for t in empty])  # fmt: skip
        if empty and not kinds:  # image topics there are, but not one message on them
            names = short_text(", ".join(empty), 200)
            raise RecordingError(
                f"{self.path}: no depth images: the image "
                f"{'topic ' + names + ' holds' if len(empty) == 1 else 'topics ' + names + ' hold'}"
                " no message",
                hint=short_text(f"image topics: {others}", 300),
            )
        raise RecordingError(
            f"{self.path}: no depth image topic (Image 16UC1, mono16 or 32FC1; CompressedImage "
            "compressedDepth)",
            hint=short_text(
                f"image topics: {others}" if others else f"topics: {', '.join(sorted(topics))}",
                300,
            ),
        )

    def _camera(
        self,
        reader: Any,
        topics: dict[str, tuple[str, list[Any], int]],
        depth: str,
        shape: tuple[int, int],
        intrinsics_given: bool,
    ) -> tuple[str | None, CameraModel | None]:
        infos = sorted(t for t, v in topics.items() if v[0] == CAMERA_INFO and v[2] > 0)
        sibling = depth.rsplit("/", 1)[0] + "/camera_info"
        name = self.info_topic or (
            sibling if sibling in infos else infos[0] if len(infos) == 1 else None
        )
        if self.info_topic is not None and self.info_topic not in infos:
            raise DeviceSpecError(  # the user's ?info_topic=: bad usage (exit 2)
                f"{self.path}: no CameraInfo messages on {short_repr(self.info_topic)}",
                hint=f"CameraInfo topics: {short_text(', '.join(infos) or 'none', 200)}",
            )
        conns = [] if name is None else topics[name][1]
        if name is None and not infos:  # a CameraInfo published on the depth topic itself
            conns = [c for c in reader.connections if c.topic == depth and c.msgtype == CAMERA_INFO]
            name = depth if conns else None
        first = self._first(reader, conns) if conns else None
        camera = None if first is None else camera_model(first[0], shape, f"{self.path} {name}")
        if camera is None and not intrinsics_given:
            why = (
                f"several CameraInfo topics ({', '.join(infos)}) and none beside it"
                if len(infos) > 1 and name is None
                else f"{name} has K = 0 (uncalibrated)"
                if name is not None
                else "no CameraInfo"
            )
            raise RecordingError(
                f"{self.path}: no intrinsics for {short_text(depth, 100)}: {short_text(why, 300)}",
                hint="give them: replay:BAG?fx=..&fy=..&cx=..&cy=.. (pixels)"
                + (", or pick one with ?info_topic=" if len(infos) > 1 else ""),
            )
        return (name if camera is not None else None), camera

    def _static(
        self, reader: Any, topics: dict[str, tuple[str, list[Any], int]]
    ) -> dict[tuple[str, str], npt.NDArray[np.float64]]:
        """The bag's static transforms (ros_tf.read_static), read once per probe."""
        if self._tf is None:
            self._tf = {}
            if TF_STATIC in topics:
                conns = topics[TF_STATIC][1]
                try:
                    self._tf = ros_tf.read_static(
                        (raw for _, _, raw in reader.messages(connections=conns)),
                        lambda raw: reader.deserialize(raw, conns[0].msgtype),
                    )
                except Exception as exc:  # see _reader
                    raise self._broken(exc, "reading /tf_static failed") from None
        return self._tf

    def _imu(
        self, reader: Any, topics: dict[str, tuple[str, list[Any], int]], camera_frame: str
    ) -> tuple[str | None, npt.NDArray[np.float64] | None]:
        imus = sorted(t for t, v in topics.items() if v[0] == IMU and v[2] > 0)
        if len(imus) != 1:
            if imus:
                log.warning(
                    "%s: %d Imu topics (%s): none used", self.path, len(imus), short_repr(imus, 200)
                )
            return None, None
        first = self._first(reader, topics[imus[0]][1])
        imu_frame = "" if first is None else str(first[0].header.frame_id)
        if imu_frame.lstrip("/") == camera_frame.lstrip("/"):
            return imus[0], np.eye(3)
        t = ros_tf.frame_transform(self._static(reader, topics), imu_frame, camera_frame)
        rot = None if t is None else t[:3, :3]
        if rot is None:
            log.warning(
                "%s: %s is in frame %s, which /tf_static does not join to the depth frame %s: "
                "accelerometer not used", self.path, short_text(imus[0], 100),
                short_repr(imu_frame), short_repr(camera_frame),
            )  # fmt: skip
            return None, None
        return imus[0], rot

    # --- frames ------------------------------------------------------------------------
    def frames(self) -> Iterator[Item]:
        """(timestamp_s, depth_mm (H, W), accel_mps2 in the optical frame or None) per image.

        Raises:
            RecordingError: a damaged bag (after the frames before the damage), an image whose
                size or encoding differs from the first.
        """
        probe = self._probe or self.probe(intrinsics_given=True)
        reader = self._reader()
        try:
            topics = self._topics(reader)
            wanted = list(topics[probe.depth_topic][1])
            if probe.imu_topic is not None:
                wanted += topics[probe.imu_topic][1]
            accel: tuple[float, float, float] | None = None
            count = 0
            where = f"{self.path} {probe.depth_topic}"
            messages = reader.messages(connections=wanted)
            while True:
                try:
                    item = next(messages, None)
                    if item is None:
                        return
                    conn, t_ns, raw = item
                    msg = reader.deserialize(raw, conn.msgtype)
                except Exception as exc:  # see _reader
                    raise self._broken(exc, f"damaged after {count} frames") from None
                if conn.topic != probe.depth_topic:
                    accel = self._accel(msg, probe)
                    continue
                depth = realsense_layout.counts_to_mm(decode_image(msg, where), probe.units_um)
                if depth.shape != probe.shape:
                    raise RecordingError(
                        f"{where}: image {count} is {depth.shape[1]}x{depth.shape[0]}, "
                        f"the first was {probe.shape[1]}x{probe.shape[0]}"
                    )
                count += 1
                yield stamp_s(msg, t_ns), depth, accel
        finally:
            reader.close()

    @staticmethod
    def _accel(msg: Any, probe: BagProbe) -> tuple[float, float, float] | None:
        """An Imu's specific force in the depth image's optical frame (m/s^2), or None."""
        cov = np.asarray(msg.linear_acceleration_covariance, dtype=np.float64)
        if cov.size and cov[0] == -1.0:  # REP 145: no estimate of this quantity
            return None
        a = msg.linear_acceleration
        vec = np.array([float(a.x), float(a.y), float(a.z)])
        assert probe.imu_to_camera is not None
        out = probe.imu_to_camera @ vec
        if not np.all(np.isfinite(out)):
            return None
        return float(out[0]), float(out[1]), float(out[2])
