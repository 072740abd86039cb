"""``rerun``: stream every frame to the rerun viewer, or save it as an ``.rrd`` file.

Specs:
    ``rerun``                        spawn a native viewer (needs a display) and stream to it
    ``rerun+grpc://HOST:PORT``       connect to a running viewer (default 127.0.0.1:9876)
    ``rerun:FILE.rrd``               save to a file (``close()`` writes the footer: a complete .rrd)

Options: ``every=N`` logs every Nth frame (default 1; depth images are ~0.6 MB each at 640x480),
``image=0`` leaves out the depth image and its overlays.

Entities (the world is the level frame at the sensor's foot, x forward, y left, z up, floor z=0):
    /world                        ViewCoordinates RIGHT_HAND_Z_UP (static)
    /world/floor                  a 1 m grid on the floor (static)
    /world/sensor                 Transform3D: mount height, tilt (nose down) and roll
    /world/sensor/depth           Pinhole (camera_xyz=FLU) + DepthImage (mm, meter=1000)
    /world/sensor/depth/band      Boxes2D: the rows the scan uses
    /world/sensor/depth/obstacles SegmentationImage: pixels the scan counts as obstacles (class 1)
    /world/sensor/depth/cliffs    Boxes2D: detected cliff blocks
    /world/scan                   Points3D: scan hits, drawn on the floor
    /world/cliff/points           Points3D: cliff floor points
    /world/cliff/scan             Points3D: nearest drop-off per bearing
    /stats/pose/{height_m,tilt_deg,roll_deg}, /stats/timing/<stage>_ms   Scalars
    /log                          TextLog: per-frame warnings
Timelines: ``frame`` (= seq) and ``sensor_time`` (the frame timestamp, seconds, as a duration).
Every rerun call of depthnav lives in this module (the API moves between releases).
"""

from __future__ import annotations

import contextlib
import logging
import os
import queue
import shutil
import struct
import threading
import time
import uuid
from typing import TYPE_CHECKING, Any

import numpy as np

from depthnav_daemon.errors import ConfigError, SinkError
from depthnav_daemon.pipeline.geometry import rot_x, rot_y
from depthnav_daemon.sinks.base import (
    RateLimitedLog,
    SinkContext,
    SinkSpec,
    bool_option,
    check_options,
    number_option,
    parse_host_port,
)

if TYPE_CHECKING:
    from depthnav_daemon.pipeline import Result
    from depthnav_daemon.pipeline.scan import LaserScan
    from drivers.base import Frame, Intrinsics

log = logging.getLogger(__name__)

GRAMMAR = "rerun[?every=N&image=0|1], rerun+grpc://HOST:PORT[?...] or rerun:FILE.rrd[?...]"
APP_ID = "depthnav"
DEFAULT_GRPC = ("127.0.0.1", 9876)
SCAN_Z_M = 0.01  # scan hits are drawn just above the floor, like a footprint map
CLASS_OBSTACLE = 1
STATS = "/stats"
# A file sink's writer thread dies quietly when the disk fills: flush this often so the failure
# becomes a SinkError (the sink is dropped, the others go on) instead of frames silently lost.
FILE_CHECK_S = 1.0
FILE_CHECK_TIMEOUT_S = 10.0
LOW_SPACE_BYTES = 1 << 20
# A viewer (gRPC) that is gone or never came: once rerun's send quota is full, every rerun call
# (log, flush, disconnect) blocks until the viewer answers, which may be never. So viewer output
# is logged from its own thread through a short queue: the frame loop never waits for it, a full
# queue skips frames for the viewer, and shutdown waits VIEWER_JOIN_S at most (rerun itself then
# gives up on unsent data within 5 s at exit).
VIEWER_QUEUE_FRAMES = 30  # 1 s at 30 frames/s: bursts pass, a dead viewer costs <= 30 frames
VIEWER_JOIN_S = 1.5


def _xy_to_points3d(x: np.ndarray, y: np.ndarray, z: float) -> np.ndarray:
    return np.stack([x, y, np.full_like(x, z)], axis=1).astype(np.float32)


def scan_points(scan: LaserScan, z: float = SCAN_Z_M) -> np.ndarray:
    """(K, 3) float32 points of a scan's finite ranges, level frame at the sensor's foot."""
    r = np.asarray(scan.ranges, dtype=np.float64)
    ok = np.isfinite(r)
    a = scan.angles[ok]
    return _xy_to_points3d(r[ok] * np.cos(a), r[ok] * np.sin(a), z)


def blueprint() -> Any:
    """The default layout: depth + overlays and time series left, the 3-D view right."""
    import rerun.blueprint as rrb

    return rrb.Blueprint(
        rrb.Horizontal(
            rrb.Vertical(
                rrb.Spatial2DView(name="Depth", origin="/world/sensor/depth"),
                # metres and degrees on separate plots: 0.5 m next to 12 deg would be a flat line
                rrb.TimeSeriesView(name="Height [m]", origin=f"{STATS}/pose/height_m"),
                rrb.TimeSeriesView(
                    name="Tilt, roll [deg]",
                    origin=f"{STATS}/pose",
                    contents=["+ $origin/tilt_deg", "+ $origin/roll_deg"],
                ),
                rrb.TimeSeriesView(name="Timing [ms]", origin=f"{STATS}/timing"),
                row_shares=[3, 1, 1, 1],
            ),
            rrb.Vertical(
                rrb.Spatial3DView(name="3D", origin="/world"),
                rrb.TextLogView(name="Log", origin="/log"),
                row_shares=[4, 1],
            ),
            column_shares=[2, 3],
        ),
        rrb.BlueprintPanel(state="collapsed"),
        rrb.SelectionPanel(state="collapsed"),
        rrb.TimePanel(timeline="frame"),
    )


RRD_MAGIC = b"RRF2"
RRD_FILE_HEADER = 12  # magic, version, options
RRD_MESSAGE_HEADER = struct.Struct("<QQ")  # message kind, payload length
MAX_MESSAGE_KIND = 255


def trim_partial_message(path: str) -> int | None:
    """Cut an ``.rrd`` whose writing stopped mid-message (disk full) back to its last whole message.

    rerun's reader refuses a file whose last message is cut short, which would make every frame
    written before the disk filled unreadable. The result has no footer, which rerun reads
    (``RrdReader.stream()``, the viewer). Nothing is changed unless the file walks cleanly.

    Returns:
        The new size in bytes, or None when the file was left as it was.
    """
    try:
        with open(path, "r+b") as fh:
            size = os.fstat(fh.fileno()).st_size
            if fh.read(4) != RRD_MAGIC:
                return None
            pos = RRD_FILE_HEADER
            while pos + RRD_MESSAGE_HEADER.size <= size:
                fh.seek(pos)
                kind, length = RRD_MESSAGE_HEADER.unpack(fh.read(RRD_MESSAGE_HEADER.size))
                if kind > MAX_MESSAGE_KIND:  # not a message header: an unknown layout, leave it
                    return None
                if pos + RRD_MESSAGE_HEADER.size + length > size:
                    break
                pos += RRD_MESSAGE_HEADER.size + length
            if pos == size:
                return None
            fh.truncate(pos)
            return pos
    except OSError as exc:
        log.warning("rerun sink: could not trim %s: %s", path, exc.strerror or exc)
        return None


_abandoned: list[str] = []  # viewer sinks whose thread was left blocked inside rerun


def abandoned_viewers() -> list[str]:
    """Sinks whose viewer thread is still blocked inside rerun after close() (the viewer is gone).

    The CLI then ends the process without the interpreter's teardown: rerun's exit hook waits 5 s
    for the viewer, and tearing down under a thread blocked in native code can abort (SIGABRT).
    """
    return list(_abandoned)


def _discard(rec: Any) -> None:
    """Disconnect a recording whose sink could not be set up."""
    try:
        rec.disconnect()
    except Exception:  # best effort on an already failing path
        log.debug("discarding the rerun recording failed", exc_info=True)


class RerunSink:
    """Logs frames to an explicit ``rr.RecordingStream`` (no global rerun state).

    Args:
        name: the spec, for messages.
        mode: "spawn", "connect" or "save".
        target: the gRPC URL (connect) or the file path (save); "" for spawn.
        every: log every Nth frame.
        image: log the depth image and its overlays.
    """

    def __init__(
        self, name: str, mode: str, target: str = "", every: int = 1, image: bool = True
    ) -> None:
        self.name, self.mode, self.target, self.every, self.image = name, mode, target, every, image
        self.needs_obstacle_mask = image  # drawn over the depth image (Sink protocol)
        self._rec: Any = None
        self._stream: Any = None
        self._rr: Any = None
        self._context: SinkContext | None = None
        self._pinhole: Intrinsics | None = None
        self._frames = 0
        self._next_check = 0.0
        self._file_failed = False
        self._queue: queue.Queue[tuple[Frame, Result] | None] | None = None
        self._thread: threading.Thread | None = None
        self._error: BaseException | None = None
        self._skipped = RateLimitedLog(log)
        self.logged = 0

    @classmethod
    def from_spec(cls, spec: SinkSpec) -> RerunSink:
        """Build from a parsed spec (no I/O). Raises ConfigError for a bad target or option."""
        check_options(spec, ("every", "image"), GRAMMAR)
        every = int(number_option(spec, "every", 1, 1, 10000, integer=True))
        image = bool_option(spec, "image", True)
        if spec.scheme == "rerun+grpc":
            host, port = parse_host_port(spec, DEFAULT_GRPC[0], DEFAULT_GRPC[1])
            host = f"[{host}]" if ":" in host else host
            return cls(spec.text, "connect", f"rerun+http://{host}:{port}/proxy", every, image)
        if not spec.target:
            return cls(spec.text, "spawn", "", every, image)
        if not spec.target.endswith(".rrd"):
            raise ConfigError(
                f"rerun sink target {spec.target!r} is not an .rrd file",
                hint="write rerun:FILE.rrd to save, rerun+grpc://HOST:PORT to connect, "
                "rerun to spawn",
            )
        return cls(spec.text, "save", spec.target, every, image)

    def open(self, context: SinkContext) -> None:
        """Create the recording, attach the viewer/file, log the static scene.

        Raises:
            SinkError: rerun-sdk missing, no display to spawn on, or the file cannot be written.
        """
        try:
            import rerun as rr  # absolute: this module is depthnav_daemon.sinks.rerun, not rerun
        except ModuleNotFoundError as exc:
            raise SinkError(
                "the rerun sink needs the 'rerun-sdk' package",
                hint="pip install 'rerun-sdk>=0.41,<0.42'",
            ) from exc
        self._rr, self._context = rr, context
        rec = rr.RecordingStream(APP_ID, recording_id=uuid.uuid4())
        try:
            if self.mode == "save":
                parent = os.path.dirname(os.path.abspath(self.target))
                if not os.path.isdir(parent):
                    raise SinkError(f"rerun sink: folder {parent!r} does not exist")
                try:  # fail with a plain message before rerun does (it also warns about lost data)
                    with open(self.target, "ab"):
                        pass
                except OSError as exc:
                    raise SinkError(
                        f"rerun sink: cannot write {self.target!r}: {exc.strerror}"
                    ) from exc
                rec.save(self.target, default_blueprint=blueprint())
            elif self.mode == "connect":
                rec.connect_grpc(self.target, default_blueprint=blueprint())
            else:
                # without a display the viewer dies and spawn() blocks ~11 s, then drops data
                if not (os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY")):
                    raise SinkError(
                        "rerun sink: no display to spawn a viewer on",
                        hint="use --sink rerun:FILE.rrd or --sink rerun+grpc://HOST:PORT "
                        "on a headless robot",
                    )
                rec.spawn(default_blueprint=blueprint())
        except Exception as exc:  # rerun raises plain RuntimeError/OSError subclasses
            _discard(rec)
            if isinstance(exc, SinkError):
                raise
            raise SinkError(
                f"rerun sink ({self.mode} {self.target or 'viewer'}) failed: {exc}"
            ) from exc
        self._rec = self._stream = rec  # _rec: open; _stream: what the logging calls use
        self._log_static()
        if self.mode != "save":  # a file is written in the frame loop: it must not skip frames
            self._queue = queue.Queue(maxsize=VIEWER_QUEUE_FRAMES)
            self._thread = threading.Thread(
                target=self._pump, args=(rec,), name=f"sink {self.name}", daemon=True
            )
            self._thread.start()
        log.info("rerun sink: %s %s", self.mode, self.target or "viewer")

    def _log_static(self) -> None:
        rr, rec = self._rr, self._stream
        rec.log("/world", rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)
        lines = [[[x, -4.0, 0.0], [x, 4.0, 0.0]] for x in range(0, 7)]
        lines += [[[0.0, y, 0.0], [6.0, y, 0.0]] for y in range(-4, 5)]
        rec.log(
            "/world/floor", rr.LineStrips3D(lines, radii=0.004, colors=[110, 110, 110]), static=True
        )
        rec.log(
            "/world/sensor/depth/obstacles",
            # class 0 must be transparent explicitly, or rerun tints the whole depth image
            rr.AnnotationContext(
                [(0, "", (0, 0, 0, 0)), (CLASS_OBSTACLE, "obstacle", (255, 40, 40, 220))]
            ),
            static=True,
        )
        series = {"height_m": (255, 128, 0), "tilt_deg": (0, 160, 255), "roll_deg": (160, 80, 255)}
        for key, color in series.items():
            rec.log(
                f"{STATS}/pose/{key}",
                rr.SeriesLines(colors=[color], names=key, widths=2),
                static=True,
            )
        rec.log(
            "/meta",
            rr.AnyValues(
                version=self._context.version,
                device=self._context.device.name,
                spec=self._context.device.spec,
            ),
            static=True,
        )

    def write(self, frame: Frame, result: Result) -> None:
        """Log one frame (every Nth).

        Raises:
            SinkError: rerun failed to log (e.g. the file became unwritable).
        """
        if self._rec is None:
            raise SinkError(f"sink {self.name!r} is not open")
        if self._error is not None:
            raise SinkError(
                f"rerun sink: logging to {self.target or 'the viewer'} failed: {self._error}"
            )
        self._frames += 1
        if (self._frames - 1) % self.every:
            return
        if self._queue is not None:
            try:
                self._queue.put_nowait((frame, result))
            except queue.Full:
                self._skipped.failed(
                    "rerun sink: the viewer at %s is not keeping up (gone?); frames skipped for it",
                    self.target or "(spawned)",
                )
            return
        try:
            self._log_frame(frame, result)
        except Exception as exc:
            raise SinkError(f"rerun sink: logging frame {result.seq} failed: {exc}") from exc
        self.logged += 1
        if self.mode == "save" and time.monotonic() >= self._next_check:
            self._check_file()
            self._next_check = time.monotonic() + FILE_CHECK_S

    def _file_problem(self, exc: BaseException) -> str:
        """Why writing the .rrd failed, in words: a full disk is the usual cause."""
        try:
            folder = os.path.dirname(os.path.abspath(self.target))
            if shutil.disk_usage(folder).free < LOW_SPACE_BYTES:
                return "no space left on the disk"
        except OSError:
            pass
        return str(exc).splitlines()[0] if str(exc) else type(exc).__name__

    def _check_file(self) -> None:
        """Flush to the file; a dead writer thread (disk full, file-size limit) is a SinkError."""
        try:
            self._rec.flush(timeout_sec=FILE_CHECK_TIMEOUT_S)
        except Exception as exc:  # rerun raises RuntimeError("File-writer thread shut down ...")
            self._file_failed = True
            raise SinkError(
                f"rerun sink: writing {self.target} failed: {self._file_problem(exc)}; "
                f"{self.logged} frames logged, the last ones may be lost",
                hint="free disk space; what was written reads back with rerun (the footer is "
                "missing)",
            ) from exc

    def _log_frame(self, frame: Frame, result: Result) -> None:
        rr, rec = self._rr, self._stream
        rec.set_time("frame", sequence=int(result.seq))
        rec.set_time("sensor_time", duration=float(result.timestamp_s))
        m = result.mount
        rot = rot_y(m.tilt_rad) @ rot_x(
            m.roll_rad
        )  # sensor body (FLU) -> level, geometry.py's order
        rec.log("/world/sensor", rr.Transform3D(translation=[0.0, 0.0, m.height_m], mat3x3=rot))
        if self.image:
            self._log_image(frame, result)
        rec.log(
            "/world/scan", rr.Points3D(scan_points(result.scan), radii=0.02, colors=[0, 220, 0])
        )
        cliff = result.cliff
        if cliff is not None:
            pts = np.asarray(cliff.points_m, dtype=np.float32).reshape(-1, 2)
            rec.log(
                "/world/cliff/points",
                rr.Points3D(
                    _xy_to_points3d(pts[:, 0], pts[:, 1], 0.0), radii=0.015, colors=[255, 0, 200]
                ),
            )
            rec.log(
                "/world/cliff/scan",
                rr.Points3D(scan_points(cliff.scan, 0.02), radii=0.025, colors=[255, 60, 60]),
            )
        rec.log(f"{STATS}/pose/height_m", rr.Scalars(m.height_m))
        rec.log(f"{STATS}/pose/tilt_deg", rr.Scalars(m.tilt_deg))
        rec.log(f"{STATS}/pose/roll_deg", rr.Scalars(m.roll_deg))
        for stage, seconds in result.timings_s.items():
            rec.log(f"{STATS}/timing/{stage}_ms", rr.Scalars(seconds * 1000.0))
        if result.warning:
            rec.log("/log", rr.TextLog(f"frame {result.seq}: {result.warning}", level="WARN"))
        if result.pose is not None and not result.pose.ok:
            rec.log(
                "/log",
                rr.TextLog(
                    f"frame {result.seq}: floor estimate rejected: {result.pose.reason}",
                    level="INFO",
                ),
            )

    def _log_image(self, frame: Frame, result: Result) -> None:
        rr, rec, ctx = self._rr, self._stream, self._context
        intr = frame.intrinsics
        if intr != self._pinhole:  # intrinsics rarely change: log the pinhole again only then
            rec.log(
                "/world/sensor/depth",
                rr.Pinhole(
                    focal_length=[intr.fx, intr.fy],
                    principal_point=[intr.cx, intr.cy],
                    width=intr.width,
                    height=intr.height,
                    camera_xyz=rr.ViewCoordinates.FLU,
                    image_plane_distance=0.3,
                ),
                static=True,
            )
            self._pinhole = intr
        far_mm = max(1000.0, ctx.scan_params.range_max_m * 1000.0)
        rec.log(
            "/world/sensor/depth",
            rr.DepthImage(
                frame.depth_mm, meter=1000.0, colormap="turbo", depth_range=[0.0, far_mm]
            ),
        )
        first, stop = result.scan_band
        rec.log(
            "/world/sensor/depth/band",
            rr.Boxes2D(
                mins=[[-0.5, first - 0.5]],
                sizes=[[intr.width, stop - first]],
                colors=[[255, 220, 0]],
                labels=["scan rows"],
            ),
        )
        if result.obstacle_mask is not None:
            rec.log(
                "/world/sensor/depth/obstacles",
                rr.SegmentationImage(
                    result.obstacle_mask.astype(np.uint8) * CLASS_OBSTACLE, opacity=0.6
                ),
            )
        blocks = (
            np.empty((0, 2))
            if result.cliff is None
            else np.asarray(result.cliff.blocks).reshape(-1, 2)
        )
        # the cliff stage reports its own block size; the context's is the configured fallback
        size = float(getattr(result.cliff, "block_size", None) or ctx.cliff_block_size)
        # blocks are (row, col) of the top-left pixel; Boxes2D wants (x, y) = (col, row) pixel edges
        rec.log(
            "/world/sensor/depth/cliffs",
            rr.Boxes2D(
                mins=blocks[:, ::-1].astype(np.float32) - 0.5,
                sizes=np.full((len(blocks), 2), size, np.float32),
                colors=[[255, 0, 200]],
            ),
        )

    def _pump(self, rec: Any) -> None:
        """The viewer thread: log queued frames until the None that close() sends, then finish."""
        assert self._queue is not None
        while True:
            item = self._queue.get()
            if item is None:
                break
            try:
                self._log_frame(*item)
            except Exception as exc:  # reported by the next write()
                log.debug("rerun viewer thread failed", exc_info=True)
                self._error = exc
                return
            self.logged += 1
        self._finish(rec)

    def close(self) -> None:
        """Flush and disconnect (which writes the .rrd footer). Safe to call twice.

        A viewer is given VIEWER_JOIN_S to take what is queued; one that does not answer is left
        behind (its thread is a daemon thread), so it never holds the daemon's shutdown.
        """
        rec, self._rec = self._rec, None
        if rec is None:
            return
        thread, self._thread = self._thread, None
        if thread is None:
            self._finish(rec)
            return
        assert self._queue is not None
        while True:  # make room for the stop marker: a queued frame may be dropped for it
            try:
                self._queue.put_nowait(None)
                break
            except queue.Full:
                with contextlib.suppress(queue.Empty):
                    self._queue.get_nowait()
        thread.join(VIEWER_JOIN_S)
        if thread.is_alive():
            _abandoned.append(self.name)
            log.warning(
                "rerun sink: the viewer at %s does not answer; not waiting for it "
                "(%d frames logged)",
                self.target or "(spawned)",
                self.logged,
            )

    def _finish(self, rec: Any) -> None:
        try:
            # a file must be complete, and writing it is fast; a viewer that went away must not
            # hold the daemon's shutdown (rerun's gRPC sink itself gives up after a few seconds)
            rec.flush(timeout_sec=30.0 if self.mode == "save" else 1.0)
        except Exception as exc:  # one line; the traceback only with -v
            self._file_failed = self.mode == "save"
            log.warning(
                "rerun sink: flushing %s failed: %s",
                self.target or "viewer",
                self._file_problem(exc) if self.mode == "save" else exc,
            )
            log.debug("flush failure", exc_info=True)
        try:
            rec.disconnect()
        except Exception as exc:
            log.warning("rerun sink: disconnecting %s failed: %s", self.target or "viewer", exc)
            log.debug("disconnect failure", exc_info=True)
        if self._file_failed:
            size = trim_partial_message(self.target)
            if size is not None:
                log.warning(
                    "rerun sink: %s cut back to its last complete message (%d bytes), "
                    "readable without a footer",
                    self.target,
                    size,
                )
        log.info("rerun sink: %d frames logged to %s", self.logged, self.target or "viewer")
