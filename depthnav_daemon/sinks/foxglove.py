"""``foxglove``: a live Foxglove WebSocket server, or the same channels in an MCAP file.

Specs:
    ``foxglove`` / ``foxglove://HOST:PORT``   serve on HOST:PORT (default 127.0.0.1:8765: this
                                              machine only; give another address to open it)
    ``foxglove:FILE.mcap``                    write the channels to FILE.mcap (Foxglove opens it)

Options: ``image=0`` leaves out the depth image and its overlays; ``tf=0`` the transforms; the
frame and topic names of the ROS sinks (sinks/ros/messages.py: ``base_frame``, ``scan_topic`` ...)
and their ``cliff_z``, ``grid_rate`` and ``odom_tf``.

Channels (Foxglove's own protobuf schemas unless said):
    /depthnav/depth/image_raw     RawImage 16UC1 (mm), optical frame
    /depthnav/depth/camera_info   CameraCalibration (the 3D panel projects the image with it)
    /depthnav/depth/annotations   ImageAnnotations: the scan's row band (yellow), obstacle
                                  pixels (red, at most 1000 drawn), cliff blocks (magenta)
    /scan, /cliff/scan            LaserScan in the level scan frame (NaN/+inf/-inf as computed)
    /cliff/points                 PointCloud x y z float32, the drop-offs in the base frame at
                                  z = cliff_z (as the ROS sinks)
    /tf                           FrameTransforms: base -> scan frame, base -> optical frame
    /depth_sensor_pose            PoseInFrame: the mount in the base frame (see ros_messages)
    /depthnav/timings             JSON: stage timings (ms), mount, its source and trust (the
                                  JSON sinks' "mount" object), warning
With the obstacle memory on (odometry), from its first frame (sinks/ros/memory_out.py):
    /memory/grid                  Grid in the odom frame at grid_rate (2 Hz): int8 field
                                  ``occupancy`` (100 / 0 / -1, as nav_msgs/OccupancyGrid) and
                                  red, green, blue, alpha (3D panel: color mode RGBA): obstacles
                                  red, drop-offs magenta, known free faint green, unknown clear
    /memory/scan                  LaserScan, 360 deg, in the scan frame (NaN unknown, +inf free)
    /memory/cliff/points          PointCloud: the remembered drop-off cells, base frame, cliff_z
    /tf                           also odom -> base, the robot at the memory's odometry pose

Served by the foxglove-sdk (its Rust server runs on its own threads): logging a message never
waits for a client; each client has a bounded backlog (oldest data dropped when it fills, a
client too slow for even control messages is disconnected), and closing waits at most 2 s for
clients that stopped reading. A channel nobody subscribes to builds no message, so an idle
server costs almost nothing.
"""

from __future__ import annotations

import dataclasses
import logging
import threading
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from depthnav_daemon.errors import ConfigError, SinkError
from depthnav_daemon.sinks.base import (
    RateLimitFilter,
    SinkContext,
    SinkSpec,
    check_options,
    parse_host_port,
)
from depthnav_daemon.sinks.json.message import mount_trust_to_json
from depthnav_daemon.sinks.ros.memory_out import (
    GridClock,
    cliff_cells_xy,
    live_memory,
    occupancy,
    occupancy_rgba,
    yaw_quaternion,
)
from depthnav_daemon.sinks.ros.messages import (
    OPTIONS,
    UINT32_SEC_MAX,
    RosNames,
    check_stamp,
    cliff_xyz,
    quaternion,
    scan_origin,
    sensor_placement,
)
from depthnav_daemon.sinks.ros.messages import stamp_ns as to_ns

if TYPE_CHECKING:
    from depthnav_daemon.pipeline import Result
    from depthnav_daemon.pipeline.memory_io import MemoryResult
    from depthnav_daemon.pipeline.scan import LaserScan
    from drivers.base import Frame

log = logging.getLogger(__name__)

GRAMMAR = (
    "foxglove://HOST:PORT | foxglove:FILE.mcap "
    "[?image=0|1&tf=0|1&cliff_z=-0.05&grid_rate=2&odom_tf=0|1&<names>]"
)
DEFAULT_HOST, DEFAULT_PORT = "127.0.0.1", 8765
BACKLOG = 64  # messages queued per client before the oldest are dropped
MAX_OBSTACLE_POINTS = 1000  # ~7 us each to build
STOP_WAIT_S = 2.0  # longest close() waits for the server to say goodbye to its clients
ANNOTATIONS = "/depthnav/depth/annotations"
# the SDK's server logs each invalid client message and failed handshake (its Rust log records
# reach Python's logging under these names): each kind once per 10 s, with a count
SDK_LOGGERS = ("foxglove", "foxglove.websocket.server", "foxglove.websocket.connected_client")
_SDK_LOG = RateLimitFilter(period_s=10.0)
TIMINGS = "/depthnav/timings"


class FoxgloveSink:
    """Serves or records the Foxglove channels (see the module docstring)."""

    def __init__(
        self, name: str, *, file: Path | None, host: str, port: int, names: RosNames
    ) -> None:
        self.name = name
        self.file = file
        self.host, self.port = host, port
        self.names = names
        self.needs_obstacle_mask = names.image
        self._ctx: Any = None
        self._out: Any = None  # the WebSocketServer or the MCAP writer
        self._ch: dict[str, Any] = {}
        self._intr: Any = None
        self._grid_clock = GridClock(names.grid_rate)

    @classmethod
    def from_spec(cls, spec: SinkSpec) -> FoxgloveSink:
        """Build from a parsed spec (no I/O). Raises ConfigError for a bad address or option."""
        check_options(spec, OPTIONS, GRAMMAR)
        names = RosNames.from_spec(spec)
        if "image" not in spec.options:  # the image is on by default here
            names = dataclasses.replace(names, image=True)
        if spec.target.lower().endswith(".mcap"):
            return cls(spec.text, file=Path(spec.target), host="", port=0, names=names)
        if "/" in spec.target.strip("/"):
            raise ConfigError(
                f"sink {spec.text!r}: a file must end in .mcap", hint=f"the spec is {GRAMMAR}"
            )
        host, port = parse_host_port(spec, DEFAULT_HOST, DEFAULT_PORT)
        return cls(spec.text, file=None, host=host, port=port, names=names)

    @property
    def bound_port(self) -> int:
        """The port the server listens on (useful with port 0), 0 for a file."""
        return int(self._out.port) if self.file is None and self._out is not None else 0

    def open(self, context: SinkContext) -> None:
        """Start the server or create the file, and declare the channels.

        Raises:
            SinkError: foxglove-sdk missing, the port is in use, the file exists.
        """
        try:
            import foxglove
        except ImportError as exc:
            raise SinkError(
                f"the foxglove sink needs the foxglove-sdk package ({exc})",
                hint="pip install foxglove-sdk",
            ) from None
        for name in SDK_LOGGERS:
            if _SDK_LOG not in logging.getLogger(name).filters:
                logging.getLogger(name).addFilter(_SDK_LOG)
        self._intr = context.device.intrinsics
        self._ctx = foxglove.Context()
        self._channels(foxglove)
        try:
            if self.file is not None:
                self._out = foxglove.open_mcap(str(self.file), context=self._ctx)
            else:
                self._out = foxglove.start_server(
                    name=f"depthnav {context.version}",
                    host=self.host,
                    port=self.port,
                    context=self._ctx,
                    message_backlog_size=BACKLOG,
                )
        except (
            Exception
        ) as exc:  # foxglove raises its own FoxgloveError (a RuntimeError) or OSError
            text = str(exc).splitlines()[0].removeprefix("FoxgloveError: ")
            if self.file is not None:
                raise SinkError(f"foxglove sink: cannot write {self.file}: {text}") from None
            raise SinkError(
                f"foxglove sink: cannot serve on {self.host}:{self.port}: {text}",
                hint=f"another program uses the port: pick another, foxglove://{self.host}:"
                f"{self.port + 1}",
            ) from None
        where = self.file or f"ws://{self.host}:{self.bound_port}"
        log.info("foxglove sink: %s (open it in Foxglove)", where)

    def _channels(self, foxglove: Any) -> None:
        from foxglove import channels as c

        n, ctx = self.names, self._ctx
        ch = {
            n["scan_topic"]: c.LaserScanChannel(n["scan_topic"], context=ctx),
            n["cliff_scan_topic"]: c.LaserScanChannel(n["cliff_scan_topic"], context=ctx),
            n["cliff_points_topic"]: c.PointCloudChannel(n["cliff_points_topic"], context=ctx),
            n["pose_topic"]: c.PoseInFrameChannel(n["pose_topic"], context=ctx),
            TIMINGS: foxglove.Channel(TIMINGS, context=ctx),
        }
        if n.tf:
            ch[n["tf_topic"]] = c.FrameTransformsChannel(n["tf_topic"], context=ctx)
        if n.image:
            ch[n["image_topic"]] = c.RawImageChannel(n["image_topic"], context=ctx)
            ch[n["info_topic"]] = c.CameraCalibrationChannel(n["info_topic"], context=ctx)
            ch[ANNOTATIONS] = c.ImageAnnotationsChannel(ANNOTATIONS, context=ctx)
        self._ch = ch

    def _memory_channels(self) -> None:
        """The memory's channels, made with its first frame (advertised to clients then)."""
        from foxglove import channels as c

        n, ctx = self.names, self._ctx
        if n.grid_rate > 0:
            self._ch[n["memory_grid_topic"]] = c.GridChannel(n["memory_grid_topic"], context=ctx)
        for key, kind in (
            ("memory_scan_topic", c.LaserScanChannel),
            ("memory_cliff_points_topic", c.PointCloudChannel),
        ):
            self._ch[n[key]] = kind(n[key], context=ctx)

    def write(self, frame: Frame, result: Result) -> None:
        """Log the frame on every channel somebody listens to; never waits for a client."""
        if self._out is None:
            raise SinkError(f"sink {self.name!r} is not open")
        from foxglove import messages as m

        # foxglove.Timestamp's sec is uint32: past it the SDK raises OverflowError
        t_ns = check_stamp(to_ns(result.timestamp_s), UINT32_SEC_MAX, "a foxglove Timestamp")
        stamp = m.Timestamp(t_ns // 10**9, t_ns % 10**9)
        n = self.names
        mem = live_memory(result)
        if mem is not None and n["memory_scan_topic"] not in self._ch:
            self._memory_channels()
        for topic, build in (
            (n["scan_topic"], lambda: self._scan(m, stamp, result.scan)),
            (
                n["cliff_scan_topic"],
                lambda: result.cliff and self._scan(m, stamp, result.cliff.scan),
            ),
            (n["cliff_points_topic"], lambda: result.cliff and self._points(m, stamp, result)),
            (n["pose_topic"], lambda: self._pose(m, stamp, result)),
            (n["tf_topic"], lambda: self._tf(m, stamp, result, mem)),
            (n["memory_grid_topic"], lambda: mem and self._grid(m, stamp, mem, result)),
            (n["memory_scan_topic"], lambda: mem and self._scan(m, stamp, mem.scan)),
            (
                n["memory_cliff_points_topic"],
                lambda: mem and self._cloud(m, stamp, cliff_cells_xy(mem)),
            ),
            (n["image_topic"], lambda: self._image(m, stamp, frame)),
            (n["info_topic"], lambda: self._calibration(m, stamp, frame)),
            (ANNOTATIONS, lambda: self._annotations(m, stamp, result)),
            (TIMINGS, lambda: self._timings(result)),
        ):
            ch = self._ch.get(topic)
            if ch is not None and ch.has_sinks():
                msg = build()
                if msg:
                    ch.log(msg, log_time=t_ns)

    # --- messages ----------------------------------------------------------------------
    def _identity(self, m: Any) -> Any:
        return m.Pose(position=m.Vector3(), orientation=m.Quaternion(w=1.0))

    def _scan(self, m: Any, stamp: Any, scan: LaserScan) -> Any:
        return m.LaserScan(
            timestamp=stamp, frame_id=self.names["scan_frame"], pose=self._identity(m),
            start_angle=float(scan.angle_min), end_angle=float(scan.angle_max),
            ranges=np.asarray(scan.ranges, dtype=np.float64).tolist(),
        )  # fmt: skip

    def _points(self, m: Any, stamp: Any, result: Result) -> Any:
        assert result.cliff is not None
        return self._cloud(m, stamp, result.cliff.points_m)

    def _cloud(self, m: Any, stamp: Any, points_m: Any) -> Any:
        """Drop-offs (K, 2) x, y in the base frame as a PointCloud at z = cliff_z."""
        xyz = cliff_xyz(points_m, self.names.cliff_z)
        f32 = m.PackedElementFieldNumericType.Float32
        fields = [m.PackedElementField(name=c, offset=4 * i, type=f32) for i, c in enumerate("xyz")]
        return m.PointCloud(
            timestamp=stamp, frame_id=self.names["base_frame"], pose=self._identity(m),
            point_stride=12, fields=fields, data=xyz.tobytes(),
        )  # fmt: skip

    def _quat(self, m: Any, rot: np.ndarray) -> Any:
        x, y, z, w = quaternion(rot)
        return m.Quaternion(x=x, y=y, z=z, w=w)

    def _pose(self, m: Any, stamp: Any, result: Result) -> Any:
        t, body = sensor_placement(result.mount)
        pose = m.Pose(position=m.Vector3(x=t[0], y=t[1], z=t[2]), orientation=self._quat(m, body))
        return m.PoseInFrame(timestamp=stamp, frame_id=self.names["base_frame"], pose=pose)

    def _tf(self, m: Any, stamp: Any, result: Result, mem: MemoryResult | None) -> Any:
        """base -> scan and optical frames; odom -> base too with the memory (and odom_tf)."""
        from depthnav_daemon.pipeline.geometry import M_CAM_TO_FLU

        t, body = sensor_placement(result.mount)
        n = self.names
        out = [
            m.FrameTransform(
                timestamp=stamp,
                parent_frame_id=n["base_frame"],
                child_frame_id=child,
                translation=m.Vector3(x=o[0], y=o[1], z=o[2]),
                rotation=self._quat(m, rot),
            )
            for child, o, rot in (
                (n["scan_frame"], scan_origin(result.mount), np.eye(3)),
                (n["optical_frame"], t, body @ M_CAM_TO_FLU),
            )
        ]
        if mem is not None and mem.pose is not None and n.odom_tf:
            x, y, yaw = mem.pose
            qx, qy, qz, qw = yaw_quaternion(yaw)
            out.append(
                m.FrameTransform(
                    timestamp=stamp,
                    parent_frame_id=n["odom_frame"],
                    child_frame_id=n["base_frame"],
                    translation=m.Vector3(x=x, y=y, z=0.0),
                    rotation=m.Quaternion(x=qx, y=qy, z=qz, w=qw),
                )
            )
        return m.FrameTransforms(transforms=out)

    def _grid(self, m: Any, stamp: Any, mem: MemoryResult, result: Result) -> Any:
        """The memory grid as a Grid in the odom frame when one is due (grid_rate), else None:
        per cell the int8 ``occupancy`` then red, green, blue, alpha (5 bytes)."""
        if mem.grid is None or not self._grid_clock.due(result.timestamp_s):
            return None
        occ = occupancy(mem.grid)
        cols = occ.cells.shape[1]
        t = m.PackedElementFieldNumericType
        fields = [m.PackedElementField(name="occupancy", offset=0, type=t.Int8)]
        fields += [
            m.PackedElementField(name=c, offset=1 + i, type=t.Uint8)
            for i, c in enumerate(("red", "green", "blue", "alpha"))
        ]
        ox, oy = occ.origin_m
        return m.Grid(
            timestamp=stamp, frame_id=self.names["odom_frame"],
            pose=m.Pose(position=m.Vector3(x=ox, y=oy, z=0.0), orientation=m.Quaternion(w=1.0)),
            column_count=cols, cell_size=m.Vector2(x=occ.cell_m, y=occ.cell_m),
            row_stride=5 * cols, cell_stride=5, fields=fields, data=occupancy_rgba(occ).tobytes(),
        )  # fmt: skip

    def _image(self, m: Any, stamp: Any, frame: Frame) -> Any:
        h, w = frame.depth_mm.shape
        return m.RawImage(
            timestamp=stamp, frame_id=self.names["optical_frame"], width=w, height=h,
            encoding="16UC1", step=2 * w, data=frame.depth_mm.astype("<u2").tobytes(),
        )  # fmt: skip

    def _calibration(self, m: Any, stamp: Any, frame: Frame) -> Any:
        i = frame.intrinsics
        return m.CameraCalibration(
            timestamp=stamp, frame_id=self.names["optical_frame"], width=i.width,
            height=i.height, distortion_model=i.distortion_model if i.has_distortion else "",
            D=list(i.distortion) if i.has_distortion else [],
            K=[i.fx, 0.0, i.cx, 0.0, i.fy, i.cy, 0.0, 0.0, 1.0],
            R=[1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0],
            P=[i.fx, 0.0, i.cx, 0.0, 0.0, i.fy, i.cy, 0.0, 0.0, 0.0, 1.0, 0.0],
        )  # fmt: skip

    def _annotations(self, m: Any, stamp: Any, result: Result) -> Any:
        kind = m.PointsAnnotationType
        w = result.intrinsics.width
        top, stop = result.scan_band
        band = [m.Point2(x=x, y=y) for x, y in ((0, top), (w, top), (w, stop), (0, stop))]
        out = [self._annotation(m, stamp, kind.LineLoop, band, (1.0, 0.9, 0.1), 2.0)]
        if result.obstacle_mask is not None and result.obstacle_mask.any():
            rows, cols = np.nonzero(result.obstacle_mask)
            keep = slice(None, None, -(-rows.size // MAX_OBSTACLE_POINTS))
            xs, ys = cols[keep].astype(float).tolist(), rows[keep].astype(float).tolist()
            pts = [m.Point2(x=x, y=y) for x, y in zip(xs, ys, strict=True)]
            out.append(self._annotation(m, stamp, kind.Points, pts, (1.0, 0.15, 0.1), 2.0))
        if result.cliff is not None and len(result.cliff.blocks):
            s = result.cliff.block_size
            seg = []
            for r, c in np.asarray(result.cliff.blocks).reshape(-1, 2):
                a, b, d, e = (c, r), (c + s, r), (c + s, r + s), (c, r + s)
                seg += [m.Point2(x=float(x), y=float(y)) for x, y in (a, b, b, d, d, e, e, a)]
            out.append(self._annotation(m, stamp, kind.LineList, seg, (1.0, 0.2, 1.0), 2.0))
        return m.ImageAnnotations(timestamp=stamp, points=out)

    @staticmethod
    def _annotation(m: Any, stamp: Any, kind: Any, pts: list, rgb: tuple, width: float) -> Any:
        color = m.Color(r=rgb[0], g=rgb[1], b=rgb[2], a=1.0)
        return m.PointsAnnotation(
            timestamp=stamp, type=kind, points=pts, outline_color=color, thickness=width
        )

    @staticmethod
    def _timings(result: Result) -> dict[str, Any]:
        mount = result.mount
        return {
            "seq": int(result.seq),
            "timings_ms": {k: round(v * 1000.0, 3) for k, v in sorted(result.timings_s.items())},
            "mount": {
                "height_m": mount.height_m,
                "tilt_deg": mount.tilt_deg,
                "roll_deg": mount.roll_deg,
            },
            "mount_source": result.mount_source,
            "mount_trust": mount_trust_to_json(result),
            "warning": result.warning,
        }

    def close(self) -> None:
        """Stop the server or finish the file. Safe to call twice."""
        out, self._out = self._out, None
        if out is None:
            return
        for ch in self._ch.values():
            ch.close()
        if self.file is not None:
            out.close()
            return
        # stop() waits for every client to take its close (~50 s for one that stopped reading):
        # a stalled viewer must not hold up the daemon's exit
        stopper = threading.Thread(target=out.stop, name="foxglove-stop", daemon=True)
        stopper.start()
        stopper.join(STOP_WAIT_S)
        if stopper.is_alive():
            log.warning("foxglove sink: a client is not reading; not waiting for it to close")
        for (_name, _level, head), count in _SDK_LOG.held_back().items():
            log.warning("foxglove sink: %d more '%s...' from clients were not shown", count, head)
