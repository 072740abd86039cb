"""The ros2 sink's per-frame CDR, made from templates: the bytes rosbags serialises, without
building and serialising every message anew.

A frame's messages differ from the last frame's in little: the stamps, the two scans' ranges
and the cliff points. The pose and the transforms change only with the mount, the scans'
geometry and frame ids never. So each message is serialised once by rosbags (from
``MessageBuilder``, the messages the bags hold) with a sentinel stamp, the places that vary
are found in those bytes, and each frame copies the template and writes its stamp, ranges or
points there. Building and serialising them anew cost ~0.25 ms a frame (issue 13's budget for
the whole encoding: 0.22 ms).

A template is used only when its bytes hold what it is assumed to (the sentinel stamp exactly
once per header, the ranges and the point data where CDR puts them); otherwise, and for the
depth image and its CameraInfo, the message is serialised by rosbags as before.
tests/sinks/test_ros_cdr.py compares every message with rosbags' bytes.
"""

from __future__ import annotations

import math
import struct
from typing import TYPE_CHECKING, Any

import numpy as np

from depthnav_daemon.sinks.ros.messages import (
    MessageBuilder,
    check_stamp,
    cliff_xyz,
    sensor_placement,
    stamp_ns,
)

if TYPE_CHECKING:
    from depthnav_daemon.pipeline import Result
    from depthnav_daemon.pipeline.geometry import Mount
    from depthnav_daemon.pipeline.scan import LaserScan
    from drivers.base import Frame

# a stamp no frame has (sec 0x5A17C0DE, nanosec 987654321): where it lands, the stamp goes
SENTINEL_NS = 0x5A17C0DE * 10**9 + 987_654_321
_STAMP = struct.Struct("<iI")
_U32 = struct.Struct("<I")
CDR_LE = b"\x00\x01"  # the encapsulation header of little-endian plain CDR
TEMPLATES = 16  # cached templates (scan geometries, mounts) before the oldest is dropped


def dds_bytes(cdr: bytes | bytearray | memoryview) -> bytearray:
    """CDR padded to whole 4-byte words, the padding named in the header's options (as DDS
    wants it)."""
    data = bytearray(cdr)
    pad = -len(data) % 4
    data += bytes(pad)
    data[3] |= pad
    return data


class _Stamped:
    """A message's DDS bytes with the places of its header stamps."""

    __slots__ = ("data", "stamps")

    def __init__(self, data: bytearray, stamps: tuple[int, ...]) -> None:
        self.data = data
        self.stamps = stamps

    def stamped(self, sec: int, nanosec: int) -> bytearray:
        out = bytearray(self.data)
        for at in self.stamps:
            _STAMP.pack_into(out, at, sec, nanosec)
        return out


def _stamps(data: bytes | bytearray, headers: int) -> tuple[int, ...] | None:
    """Offsets of the sentinel stamp in ``data``: None unless little-endian CDR holding it
    exactly ``headers`` times."""
    if bytes(data[:2]) != CDR_LE:
        return None
    mark = _STAMP.pack(SENTINEL_NS // 10**9, SENTINEL_NS % 10**9)
    found, at = [], data.find(mark)
    while at >= 0:
        found.append(at)
        at = data.find(mark, at + 1)
    return tuple(found) if len(found) == headers else None


class CdrEncoder:
    """A frame's messages as padded CDR, per topic: what ``MessageBuilder.messages`` gives,
    serialised by rosbags, byte for byte (see the module docstring).

    Args:
        builder: the message builder (its store is a ROS 2 typestore).
    """

    def __init__(self, builder: MessageBuilder) -> None:
        self.builder = builder
        self.store = builder.store
        self._scans: dict[tuple[Any, ...], tuple[_Stamped, int] | None] = {}
        self._mounts: dict[Mount, tuple[_Stamped, _Stamped | None] | None] = {}
        self._points: tuple[bytearray, int, int, int] | None = None
        self._points_made = False

    def serialize(self, msg: Any) -> bytearray:
        """One message by rosbags, padded."""
        return dds_bytes(self.store.serialize_cdr(msg, msg.__msgtype__))

    def encode(
        self, frame: Frame, result: Result, t_ns: int | None = None
    ) -> list[tuple[str, bytearray]]:
        """[(topic, padded CDR)] of one frame, in ``MessageBuilder.messages``' order. The stamp
        is ``t_ns`` when given, else the frame's own time."""
        if t_ns is None:
            t_ns = stamp_ns(result.timestamp_s)
        b = self.builder
        check_stamp(t_ns, b.sec_max, b.time_type)  # before _STAMP packs it: no struct.error
        sec, nanosec = t_ns // 10**9, t_ns % 10**9
        n = b.names
        out = [(n["scan_topic"], self._scan(result.scan, t_ns, sec, nanosec))]
        if result.cliff is not None:
            out.append((n["cliff_scan_topic"], self._scan(result.cliff.scan, t_ns, sec, nanosec)))
            xyz = cliff_xyz(result.cliff.points_m, n.cliff_z)  # as MessageBuilder
            out.append((n["cliff_points_topic"], self._cloud(xyz, t_ns, sec, nanosec)))
        mount = self._mount(result.mount)
        if mount is None:
            out.append((n["pose_topic"], self.serialize(b.pose(result.mount, t_ns))))
            if n.tf:
                out.append((n["tf_topic"], self.serialize(b.transforms(result.mount, t_ns))))
        else:
            pose, tf = mount
            out.append((n["pose_topic"], pose.stamped(sec, nanosec)))
            if tf is not None:
                out.append((n["tf_topic"], tf.stamped(sec, nanosec)))
        if n.image:
            img, info = b.image(frame, t_ns)
            out += [
                (n["image_topic"], self.serialize(img)),
                (n["info_topic"], self.serialize(info)),
            ]
        return out

    # --- the templates -------------------------------------------------------------------------

    def _scan(self, scan: LaserScan, t_ns: int, sec: int, nanosec: int) -> bytearray:
        ranges = np.asarray(scan.ranges, dtype="<f4")
        key = (
            float(scan.angle_min), float(scan.angle_max), float(scan.angle_increment),
            float(scan.range_min), float(scan.range_max), ranges.shape,
        )  # fmt: skip
        if key not in self._scans:
            _bounded(self._scans)
            self._scans[key] = self._scan_template(scan, ranges)
        made = self._scans[key]
        if made is None or ranges.ndim != 1:
            return self.serialize(self.builder.laser_scan(scan, t_ns))
        template, at = made
        out = template.stamped(sec, nanosec)
        out[at : at + 4 * ranges.size] = ranges.tobytes()
        return out

    def _scan_template(self, scan: LaserScan, ranges: np.ndarray) -> tuple[_Stamped, int] | None:
        """The scan's bytes with zero ranges, and where its ranges start."""
        if ranges.ndim != 1:
            return None
        zero = np.zeros(ranges.size, np.float32)
        msg = self.builder.laser_scan(_with_ranges(scan, zero), SENTINEL_NS)
        data = self.serialize(msg)
        stamps = _stamps(data, 1)
        # CDR: ... uint32 count, the float32 ranges, uint32 0 (no intensities), then padding
        pad = data[3] & 3
        end = len(data) - pad - 4
        at = end - 4 * ranges.size
        if (
            stamps is None
            or data[end:] != bytes(4 + pad)
            or data[at - 4 : at] != _U32.pack(ranges.size)
        ):
            return None
        if data[at:end] != bytes(4 * ranges.size):
            return None
        return _Stamped(data, stamps), at

    def _mount(self, mount: Mount) -> tuple[_Stamped, _Stamped | None] | None:
        if mount not in self._mounts:
            _bounded(self._mounts)
            self._mounts[mount] = self._mount_templates(mount)
        return self._mounts[mount]

    def _mount_templates(self, mount: Mount) -> tuple[_Stamped, _Stamped | None] | None:
        """The pose and /tf of a mount (they change with nothing else)."""
        if not all(math.isfinite(v) for v in sensor_placement(mount)[0]):
            return None
        pose = self.serialize(self.builder.pose(mount, SENTINEL_NS))
        pose_at = _stamps(pose, 1)
        if pose_at is None:
            return None
        if not self.builder.names.tf:
            return _Stamped(pose, pose_at), None
        tf = self.serialize(self.builder.transforms(mount, SENTINEL_NS))
        tf_at = _stamps(tf, 2)
        if tf_at is None:
            return None
        return _Stamped(pose, pose_at), _Stamped(tf, tf_at)

    def _cloud(self, xyz: np.ndarray, t_ns: int, sec: int, nanosec: int) -> bytearray:
        if not self._points_made:
            self._points, self._points_made = self._cloud_template(), True
        if self._points is None:
            return self.serialize(self.builder.points(xyz, t_ns))
        head, stamp_at, width_at, row_at = self._points
        data = xyz.reshape(-1).view(np.uint8)
        k = len(xyz)
        out = bytearray(head)
        _STAMP.pack_into(out, stamp_at, sec, nanosec)
        _U32.pack_into(out, width_at, k)
        _U32.pack_into(out, row_at, 12 * k)
        out += _U32.pack(data.size)
        out += data.tobytes()
        out.append(1)  # is_dense
        return dds_bytes(out)

    def _cloud_template(self) -> tuple[bytearray, int, int, int] | None:
        """The PointCloud2 up to its data: the bytes, and where the stamp, width and row_step
        are. Found by serialising two empty clouds whose width and row_step differ."""
        a = bytes(self.store.serialize_cdr(*_cloud(self.builder, 0x0A0B0C0D)))
        b = bytes(self.store.serialize_cdr(*_cloud(self.builder, 0x0D0C0B0A)))
        stamps = _stamps(a, 1)
        # CDR: ... uint32 row_step, uint32 0 (no data), bool is_dense (True)
        if stamps is None or len(a) != len(b) or a[-5:] != b"\x00\x00\x00\x00\x01":
            return None
        width_at = a.find(_U32.pack(0x0A0B0C0D))
        row_at = a.find(_U32.pack(12 * 0x0A0B0C0D & 0xFFFFFFFF))
        diff = [i for i in range(len(a)) if a[i] != b[i]]
        where = [*range(width_at, width_at + 4), *range(row_at, row_at + 4)]
        if width_at < 0 or row_at < 0 or diff != where:
            return None
        return bytearray(a[:-5]), stamps[0], width_at, row_at


def _cloud(builder: MessageBuilder, width: int) -> tuple[Any, str]:
    """An empty PointCloud2 that says it is ``width`` points wide (to find where width goes)."""
    msg = builder.points(np.zeros((0, 3), np.float32), SENTINEL_NS)
    msg.width, msg.row_step = width, 12 * width & 0xFFFFFFFF
    return msg, msg.__msgtype__


def _with_ranges(scan: LaserScan, ranges: np.ndarray) -> LaserScan:
    import dataclasses

    return dataclasses.replace(scan, ranges=ranges)


def _bounded(cache: dict[Any, Any]) -> None:
    """Room for one more entry: the oldest goes when TEMPLATES are held."""
    while len(cache) >= TEMPLATES:
        cache.pop(next(iter(cache)))
