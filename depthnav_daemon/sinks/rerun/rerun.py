"""``rerun``: stream every frame to the rerun viewer, or save it as an ``.rrd`` file.

Specs:
    ``rerun``                        spawn a native viewer (needs a display) and stream to it
    ``rerun+grpc://HOST:PORT``       connect to a running viewer (default 127.0.0.1:9876)
    ``rerun:FILE.rrd``               save to a file (``close()`` writes the footer: a complete .rrd)

Options: ``every=N`` logs every Nth frame (default 1; depth images are ~0.6 MB each at 640x480),
``image=0`` leaves out the depth image and its overlays, ``robot_length_m`` and ``robot_width_m``
size the robot drawn behind the sensor (default 0.45 x 0.40 m).

Entities (the world is the robot's base frame, x forward, y left, z up, floor z=0):
    /world                        ViewCoordinates RIGHT_HAND_Z_UP (static)
    /world/floor                  a 1 m grid on the floor (static)
    /world/robot                  Boxes3D: the robot up to the configured sensor height (static)
    /world/sensor                 Transform3D: the mount (x, y, height; yaw, tilt nose down, roll)
    /world/sensor/fov             LineStrips3D: the sensor's frustum, 0.5 m deep (static)
    /world/sensor/depth           Pinhole (camera_xyz=FLU) + DepthImage (mm, meter=1000; the
                                  figures' palette: near light, far dark)
    /world/sensor/depth/band      Boxes2D: the rows the scan uses (none when it reads every row)
    /world/sensor/depth/obstacles SegmentationImage: obstacle pixels (1), the drop-offs' lower
                                  floor (2; 3 while the mount is not trusted), no reading (4)
    /world/sensor/depth/scan_pixels  Points2D: the pixel each scan reading came from
    /world/sensor/depth/cliffs    Boxes2D: the detector's cliff blocks, outlined
    /world/scan, /world/scan/line Points3D, LineStrips3D: scan hits, drawn on the floor
    /world/cliff/points           Points3D: the drop-offs' edge points
    /world/cliff/area             Mesh3D: each drop-off's lower floor seen, from its edge
    /world/cliff/scan             LineStrips3D: the cliff scan (nearest drop-off edge per bearing)
    /world/memory/{obstacles,cliffs,scan}   Boxes3D, LineStrips3D: the memory's cells, its scan
    /topdown/...                  2-D top-down view, robot frame (u = -y, v = -x metres): scan
                                  (+ /points, /too_close), cliff (edge points; /area, /scan),
                                  memory (/obstacles, /cliffs, /scan), robot, sensor, fov, rings
                                  (+ /labels), legend; see rerun_topdown
    /odom/...                     2-D top-down view, odometry frame (with odometry): memory
                                  (/obstacles, /cliffs, /scan), path, robot, scan, cliff/scan
    /stats/pose/{height_m,tilt_deg,roll_deg}   Scalars: the mount in use
    /stats/pose/{height,tilt,roll}_floor_{m,deg}, ..._config_{m,deg}   Scalars: floor estimates
                                  (frames that ran the pose stage), the configured mount
    /stats/timing/<stage>_ms      Scalars; /stats/timing_after_warmup/<stage>_ms: without each
                                  stage's first run
    /log                          TextLog: per-frame warnings, each change of the mount's trust
Timelines: ``frame`` (= seq) and ``sensor_time`` (the frame timestamp, seconds, as a duration).
The default layout and what is logged per frame live in ``rerun_layout`` (with ``rerun_depth``
and ``rerun_topdown``); every rerun call of depthnav lives in these modules (the API moves between
releases).
"""

from __future__ import annotations

import contextlib
import logging
import os
import queue
import threading
import time
import uuid
from typing import TYPE_CHECKING, Any

from depthnav_daemon.errors import ConfigError, SinkError
from depthnav_daemon.sinks.base import (
    RateLimitedLog,
    SinkContext,
    SinkSpec,
    bool_option,
    check_options,
    number_option,
    parse_host_port,
)
from depthnav_daemon.sinks.rerun.file import (
    disconnect,
    file_problem,
    lock_rrd,
    trim_partial_message,
)
from depthnav_daemon.sinks.rerun.layout import (
    LayoutState,
    blueprint,
    log_frame,
    log_static,
)
from depthnav_daemon.sinks.rerun.topdown import DEFAULT_FOOTPRINT_M
from depthnav_daemon.sinks.rerun.viewer import DEFAULT_GRPC, check_viewer
from depthnav_daemon.sinks.rerun.world import scan_points

if TYPE_CHECKING:
    from depthnav_daemon.pipeline import Result
    from drivers.base import Frame

log = logging.getLogger(__name__)

GRAMMAR = (
    "rerun[?every=N&image=0|1&robot_length_m=L&robot_width_m=W], rerun+grpc://HOST:PORT[?...] "
    "or rerun:FILE.rrd[?...]"
)
OPTIONS = ("every", "image", "robot_length_m", "robot_width_m")
__all__ = ["RerunSink", "abandoned_viewers", "blueprint", "scan_points", "trim_partial_message"]
APP_ID = "depthnav"
# A file sink's writer thread dies quietly when the disk fills: flush this often so the failure
# becomes a SinkError (the sink is dropped, the others go on) instead of frames silently lost.
# The flush stays in the frame loop: flushed from a thread of its own while the loop went on
# logging, a stuck writer's queue filled and rerun's log() then blocked for ever (3 runs of 10 on
# a full disk under load); here a stuck writer costs the loop FILE_CHECK_TIMEOUT_S once.
FILE_CHECK_S = 1.0
FILE_CHECK_TIMEOUT_S = 10.0
# A viewer (gRPC) that is gone or never came: once rerun's send quota is full, every rerun call
# (log, flush, disconnect) blocks until the viewer answers, which may be never. So viewer output
# is logged from its own thread through a short queue: the frame loop never waits for it, a full
# queue skips frames for the viewer, and shutdown waits VIEWER_JOIN_S at most (rerun itself then
# gives up on unsent data within 5 s at exit).
VIEWER_QUEUE_FRAMES = 30  # 1 s at 30 frames/s: bursts pass, a dead viewer costs <= 30 frames
VIEWER_JOIN_S = 1.5
# rerun's disconnect() waits for its sink's writer thread without a timeout. A file writer stuck
# on a full disk (seen under load: its flushes time out instead of failing) never answers, and the
# daemon hung at shutdown. So disconnect runs in a thread of its own, waited for this long; one
# left blocked marks the sink abandoned (the CLI then skips rerun's exit hook, which would wait
# too).
DISCONNECT_S = 5.0
FAILED_DISCONNECT_S = 0.5  # a file that failed: its writer is gone (at once) or stuck (never)


_abandoned: list[str] = []  # sinks whose thread was left blocked inside rerun


def abandoned_viewers() -> list[str]:
    """Sinks with a thread still blocked inside rerun after close(): a viewer that is gone, or a
    file whose writer is stuck (DISCONNECT_S).

    The CLI then ends the process without the interpreter's teardown: rerun's exit hook waits for
    them too (5 s for a viewer, for ever for a stuck file), and tearing down under a thread blocked
    in native code can abort (SIGABRT).
    """
    return list(_abandoned)


def _import_rerun() -> Any:
    """The rerun SDK, its Rust log lines off unless -v or the user's RUST_LOG asks for them.

    rerun's Rust side prints coloured lines of its own (failed flushes, lost connections) on
    stderr; this sink reports those in one line of its own. RUST_LOG is read once, when the
    bindings load, and is set only for that moment: processes depthnav starts (a viewer) keep
    theirs.
    """
    quiet = "RUST_LOG" not in os.environ and not log.isEnabledFor(logging.DEBUG)
    if quiet:
        os.environ["RUST_LOG"] = "off"
    try:
        import rerun as rr  # absolute: this module is depthnav_daemon.sinks.rerun.rerun, not rerun
    finally:
        if quiet:
            os.environ.pop("RUST_LOG", None)
    return rr


def _one_line(exc: BaseException) -> str:
    text = str(exc)
    return text.splitlines()[0] if text else type(exc).__name__


def _discard(rec: Any, what: str) -> None:
    """Disconnect a recording whose sink could not be set up (bounded: see DISCONNECT_S)."""
    if not disconnect(rec, what, FAILED_DISCONNECT_S):
        _abandoned.append(what)


class RerunSink:
    """Logs frames to an explicit ``rr.RecordingStream`` (no global rerun state).

    Args:
        name: the spec, for messages.
        mode: "spawn", "connect" or "save".
        target: the gRPC URL (connect) or the file path (save); "" for spawn.
        every: log every Nth frame.
        image: log the depth image and its overlays.
        footprint_m: length and width of the robot drawn behind the sensor, metres.
    """

    def __init__(
        self,
        name: str,
        mode: str,
        target: str = "",
        every: int = 1,
        image: bool = True,
        footprint_m: tuple[float, float] = DEFAULT_FOOTPRINT_M,
    ) -> None:
        self.name, self.mode, self.target, self.every, self.image = name, mode, target, every, image
        self.needs_obstacle_mask = image  # drawn over the depth image (Sink protocol)
        self._rec: Any = None
        self._stream: Any = None
        self._rr: Any = None
        self._context: SinkContext | None = None
        self._state = LayoutState(footprint_m=footprint_m)
        self._frames = 0
        self._next_check = 0.0
        self._file_failed = False
        self._lock_fd: int | None = None  # the .rrd's lock (rerun_file.lock_rrd) while saving
        self._queue: queue.Queue[tuple[Frame, Result] | None] | None = None
        self._thread: threading.Thread | None = None
        self._error: BaseException | None = None
        self._skipped = RateLimitedLog(log)
        self.logged = 0

    @classmethod
    def from_spec(cls, spec: SinkSpec) -> RerunSink:
        """Build from a parsed spec (no I/O). Raises ConfigError for a bad target or option."""
        check_options(spec, OPTIONS, GRAMMAR)
        every = int(number_option(spec, "every", 1, 1, 10000, integer=True))
        image = bool_option(spec, "image", True)
        length, width = DEFAULT_FOOTPRINT_M
        foot = (
            number_option(spec, "robot_length_m", length, 0.05, 5.0),
            number_option(spec, "robot_width_m", width, 0.05, 5.0),
        )
        if spec.scheme == "rerun+grpc":
            host, port = parse_host_port(spec, DEFAULT_GRPC[0], DEFAULT_GRPC[1])
            host = f"[{host}]" if ":" in host else host
            url = f"rerun+http://{host}:{port}/proxy"
            return cls(spec.text, "connect", url, every, image, foot)
        if not spec.target:
            return cls(spec.text, "spawn", "", every, image, foot)
        if not spec.target.endswith(".rrd"):
            raise ConfigError(
                f"rerun sink target {spec.target!r} is not an .rrd file",
                hint="write rerun:FILE.rrd to save, rerun+grpc://HOST:PORT to connect, "
                "rerun to spawn",
            )
        return cls(spec.text, "save", spec.target, every, image, foot)

    def open(self, context: SinkContext) -> None:
        """Create the recording, attach the viewer/file, log the static scene.

        Raises:
            SinkError: rerun-sdk missing, no display to spawn on, or the file cannot be written.
        """
        try:
            rr = _import_rerun()
        except ModuleNotFoundError as exc:
            raise SinkError(
                "the rerun sink needs the 'rerun-sdk' package",
                hint="pip install 'rerun-sdk>=0.41,<0.42'",
            ) from exc
        self._rr, self._context = rr, context
        st = self._state
        st.reach_m, st.block_size = context.scan_params.range_max_m, context.cliff_block_size
        st.configured, st.context = context.mount, context
        rec = rr.RecordingStream(APP_ID, recording_id=uuid.uuid4())
        try:
            self._attach(rec, blueprint(context))
        except Exception as exc:  # rerun raises plain RuntimeError/OSError subclasses
            _discard(rec, self.name)
            self._unlock_file()
            if isinstance(exc, SinkError):
                raise
            raise SinkError(
                f"rerun sink ({self.mode} {self.target or 'viewer'}) failed: {exc}"
            ) from exc
        self._rec = self._stream = rec  # _rec: open; _stream: what the logging calls use
        log_static(rr, rec, context, self._state)
        if self.mode != "save":  # a file is written in the frame loop: it must not skip frames
            self._queue = queue.Queue(maxsize=VIEWER_QUEUE_FRAMES)
            self._thread = threading.Thread(
                target=self._pump, args=(rec,), name=f"sink {self.name}", daemon=True
            )
            self._thread.start()
        log.info("rerun sink: %s %s", self.mode, self.target or "viewer")

    def _attach(self, rec: Any, layout: Any) -> None:
        """Send the recording (with its default layout) to the file, the viewer or a new one."""
        if self.mode == "save":
            parent = os.path.dirname(os.path.abspath(self.target))
            if not os.path.isdir(parent):
                raise SinkError(f"rerun sink: folder {parent!r} does not exist")
            self._lock_fd = lock_rrd(self.target)
            rec.save(self.target, default_blueprint=layout)
        elif self.mode == "connect":
            check_viewer(self.target)
            rec.connect_grpc(self.target, default_blueprint=layout)
        else:
            # without a display the viewer dies and spawn() blocks ~11 s, then drops data
            if not (os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY")):
                raise SinkError(
                    "rerun sink: no display to spawn a viewer on",
                    hint="use --sink rerun:FILE.rrd or --sink rerun+grpc://HOST:PORT "
                    "on a headless robot",
                )
            rec.spawn(default_blueprint=layout)

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

    def _check_file(self) -> None:
        """Flush to the file; a dead writer thread (disk full, file-size limit) is a SinkError."""
        try:
            self._rec.flush(timeout_sec=FILE_CHECK_TIMEOUT_S)
        except Exception as exc:  # rerun raises RuntimeError("File-writer thread shut down ...")
            self._file_failed = True
            raise SinkError(
                f"rerun sink: writing {self.target} failed: {file_problem(self.target, exc)}; "
                f"{self.logged} frames logged, the last ones may be lost",
                hint="free disk space; what was written reads back with rerun (the footer is "
                "missing)",
            ) from exc

    def _log_frame(self, frame: Frame, result: Result) -> None:
        rec = self._stream
        rec.set_time("frame", sequence=int(result.seq))
        rec.set_time("sensor_time", duration=float(result.timestamp_s))
        log_frame(self._rr, rec, frame, result, self._state, self.image)

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

    def _unlock_file(self) -> None:
        fd, self._lock_fd = self._lock_fd, None
        if fd is not None:
            os.close(fd)  # releases the lock

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
                "(%d frames sent, not confirmed delivered)",
                self.target or "(spawned)",
                self.logged,
            )

    def _finish(self, rec: Any) -> None:
        # a file that already failed is not flushed again: its writer is gone or stuck, and a
        # flush would only hold the frame loop for its timeout
        delivered = not self._file_failed and self._flush(rec)
        # a viewer's is waited for as long as it takes: this runs on the viewer's own thread,
        # which close() waits for VIEWER_JOIN_S only
        wait_s = None if self.mode != "save" else DISCONNECT_S
        if self._file_failed:
            wait_s = FAILED_DISCONNECT_S
        if not disconnect(rec, self.target or "viewer", wait_s):
            _abandoned.append(self.name)
            log.warning(
                "rerun sink: %s does not close (rerun's writer is stuck); not waiting for it",
                self.target or "the viewer",
            )
        if self._file_failed:
            size = trim_partial_message(self.target)
            if size is not None:
                log.warning(
                    "rerun sink: %s cut back to its last complete message (%d bytes), "
                    "readable without a footer",
                    self.target,
                    size,
                )
        self._unlock_file()
        if delivered:
            log.info("rerun sink: %d frames logged to %s", self.logged, self.target or "viewer")

    def _flush(self, rec: Any) -> bool:
        """Flush before closing; whether everything logged was delivered."""
        try:
            # a file must be complete, and writing it is fast; a viewer that went away must not
            # hold the daemon's shutdown (rerun's gRPC sink itself gives up after a few seconds)
            rec.flush(timeout_sec=30.0 if self.mode == "save" else 1.0)
        except Exception as exc:  # one line; the traceback only with -v
            self._file_failed = self.mode == "save"
            if self.mode == "save":
                log.warning(
                    "rerun sink: flushing %s failed: %s",
                    self.target,
                    file_problem(self.target, exc),
                )
            else:
                log.warning(
                    "rerun sink: the viewer at %s did not take the frames (%s): %d frames sent, "
                    "not confirmed delivered",
                    self.target or "(spawned)",
                    _one_line(exc),
                    self.logged,
                )
            log.debug("flush failure", exc_info=True)
            return False
        return True
