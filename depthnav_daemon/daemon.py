"""The frame loop: read a frame, run the pipeline, fan the result out to every sink.

A device that stops delivering is reconnected with backoff and reported; a sink that fails is
dropped and reported while the others go on; a stop event (set by SIGINT/SIGTERM) ends the loop
within a second and every sink is closed (flushed).
"""

from __future__ import annotations

import dataclasses
import logging
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from depthnav_daemon import __version__
from depthnav_daemon.config import Config
from depthnav_daemon.errors import DepthnavError, FrameError, SinkError
from depthnav_daemon.mount_tracker import MountTracker, TrackerParams
from depthnav_daemon.pipeline import Result, prepare, process
from depthnav_daemon.pipeline.geometry import Mount
from depthnav_daemon.pipeline.pose import PoseEstimate, PoseParams, tilt_roll_from_accel
from depthnav_daemon.sinks import create_sink
from depthnav_daemon.sinks.base import Sink, SinkContext
from depthnav_daemon.stage_tables import StageTables
from drivers import create_driver
from drivers.base import DeviceInfo, Driver, Frame, Intrinsics
from drivers.errors import DriverError, FrameTimeout, RecordingError

log = logging.getLogger(__name__)

POLL_S = 0.25  # longest a read blocks, so a stop request is seen within a second


@dataclass
class RunReport:
    """What a run did, for the CLI's summary and the tests."""

    frames: int = 0
    reconnects: int = 0
    dropped_sinks: list[str] = field(default_factory=list)
    rejected_pose_jumps: int = 0
    last_result: Result | None = None
    stopped: bool = False  # ended by the stop event rather than by the source


class _Source:
    """The driver plus reconnect-with-backoff when it is lost."""

    def __init__(
        self, spec: str, cfg: Config, stop: threading.Event, factory: Callable[[str], Driver]
    ) -> None:
        self.spec = spec
        self._cfg = cfg.daemon
        self._stop = stop
        self._factory = factory
        self.driver: Driver = factory(spec)
        self.info: DeviceInfo | None = None
        self.reconnects = 0

    def open(self) -> DeviceInfo:
        self.info = self.driver.open()
        return self.info

    def close(self) -> None:
        try:
            self.driver.close()
        except DriverError as exc:
            log.warning("closing %s: %s", self.spec, exc)

    def reconnect(self, why: str) -> bool:
        """Close and reopen the device with backoff; False when stopped meanwhile."""
        self.close()
        backoff = self._cfg.reconnect_backoff_s
        attempt = 0
        while not self._stop.is_set():
            attempt += 1
            limit = self._cfg.reconnect_attempts
            if limit and attempt > limit:
                raise DepthnavError(
                    f"device {self.spec} lost ({why}) and {limit} reconnect attempts failed",
                    hint="check the cable and power; depthnav devices lists what can be opened",
                )
            log.warning(
                "device %s lost (%s); reconnect attempt %d in %.1f s",
                self.spec,
                why,
                attempt,
                backoff,
            )
            if self._stop.wait(backoff):
                return False
            try:
                self.driver = self._factory(self.spec)
                self.open()
            except DriverError as exc:
                why = str(exc)
                backoff = min(max(backoff * 2, 0.1), self._cfg.reconnect_backoff_max_s)
                continue
            self.reconnects += 1
            log.warning("device %s reconnected", self.spec)
            return True
        return False


def _open_sinks(
    specs: tuple[str, ...], context: SinkContext, factory: Callable[[str], Sink]
) -> list[Sink]:
    sinks: list[Sink] = []
    for spec in specs:
        sink = factory(spec)
        try:
            sink.open(context)
        except (SinkError, OSError) as exc:
            log.error("sink %s could not start: %s; going on without it", spec, exc)
            continue
        sinks.append(sink)
    if not sinks:
        raise DepthnavError(
            "no output sink could start", hint="check the --sink specs (depthnav run --help)"
        )
    return sinks


def _fan_out(sinks: list[Sink], frame: Frame, result: Result, report: RunReport) -> None:
    for sink in list(sinks):
        try:
            sink.write(frame, result)
        except Exception as exc:
            msg = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
            log.error("sink %s failed: %s; dropped, the others go on", sink.name, msg)
            report.dropped_sinks.append(sink.name)
            sinks.remove(sink)
            try:
                sink.close()
            except Exception:
                log.debug("closing failed sink %s", sink.name, exc_info=True)
    if not sinks:
        raise DepthnavError("every output sink failed", hint="see the errors above")


def run(
    cfg: Config,
    stop: threading.Event,
    max_frames: int | None = None,
    driver_factory: Callable[[str], Driver] = create_driver,
    sink_factory: Callable[[str], Sink] = create_sink,
    serial_tilt: object | None = None,
) -> RunReport:
    """Run the frame loop until the source ends, ``max_frames`` frames, or ``stop`` is set.

    Args:
        cfg: the effective configuration (cfg.device names the device).
        stop: set it to stop the loop (signal handlers do).
        max_frames: stop after this many frames; None = no limit.
        driver_factory, sink_factory: how specs become drivers and sinks.
        serial_tilt: a started drivers.serial_tilt.SerialTiltSource, or None.

    Raises:
        DepthnavError, DriverError: what ended the run; the message is fit for the user.
    """
    report = RunReport()
    d = cfg.daemon
    tracker = MountTracker(
        cfg.mount,
        TrackerParams(d.pose_smoothing, d.max_jump_m, d.max_jump_deg, d.jump_confirmations),
    )
    cliff_params = cfg.cliff if d.cliff else None
    tables = StageTables(lambda intr, mount: prepare(intr, mount, cfg.scan, cliff_params))
    source = _Source(cfg.device, cfg, stop, driver_factory)
    info = source.open()
    sinks: list[Sink] = []
    try:
        context = SinkContext(info, cfg.scan, cfg.cliff.block_size, __version__)
        sinks = _open_sinks(cfg.sinks, context, sink_factory)
        rng = np.random.default_rng(d.seed)
        since_pose = d.pose_every_frames  # estimate on the first frame
        last_pose_t: float | None = None
        last_frame_wall = time.monotonic()
        while not stop.is_set():
            try:
                frame = source.driver.read_frame(timeout_s=min(d.frame_timeout_s, POLL_S))
            except FrameTimeout:
                silent = time.monotonic() - last_frame_wall
                if silent > d.frame_timeout_s * d.max_consecutive_timeouts:
                    if not source.reconnect(f"no frame for {silent:.1f} s"):
                        break
                    last_frame_wall = time.monotonic()
                continue
            except RecordingError:
                # a bad file does not heal by reopening it: replaying it again would repeat the
                # frames before the bad one forever, so a damaged recording ends the run
                raise
            except DriverError as exc:
                if not source.reconnect(str(exc)):
                    break
                last_frame_wall = time.monotonic()
                continue
            if frame is None:
                log.info("end of %s after %d frames", cfg.device, report.frames)
                break
            last_frame_wall = time.monotonic()
            try:
                _update_tilt_prior(tracker, frame, d.tilt_source, serial_tilt)
            except DriverError as exc:
                # the IMU only refines the mount: losing it must not blind the robot, so say so
                # once and go on with the floor estimate and the last mount
                log.error("%s; going on without the serial tilt source", exc)
                serial_tilt = None
            want_pose = d.pose_every_frames > 0 and since_pose >= d.pose_every_frames
            if d.pose_every_s > 0 and (
                last_pose_t is None or frame.timestamp_s - last_pose_t >= d.pose_every_s
            ):
                want_pose = True

            def on_pose(
                est: PoseEstimate, intr: Intrinsics = frame.intrinsics
            ) -> tuple[Mount, str]:
                _apply_pose(tracker, est, d.tilt_source)
                return tables.mount_for(intr, tracker.mount), tracker.source

            try:
                result = process(
                    frame,
                    tables.mount_for(frame.intrinsics, tracker.mount),
                    cfg.scan,
                    cliff_params,
                    pose_prior(cfg.pose, tracker) if want_pose else None,
                    rng,
                    tracker.source,
                    time.perf_counter,
                    on_pose,
                )
            except FrameError as exc:
                log.warning("frame %d skipped: %s", frame.seq, exc)
                continue
            if want_pose:
                since_pose, last_pose_t = 0, frame.timestamp_s
            since_pose += 1
            if result.warning:
                log.debug("frame %d: %s", frame.seq, result.warning)
            _fan_out(sinks, frame, result, report)
            report.frames += 1
            report.last_result = result
            if max_frames is not None and report.frames >= max_frames:
                break
        report.stopped = stop.is_set()
    finally:
        for sink in sinks:
            try:
                sink.close()
            except Exception as exc:
                log.error("sink %s did not close cleanly: %s", sink.name, exc)
        source.close()
        tables.close()
        report.reconnects = source.reconnects
        report.rejected_pose_jumps = tracker.rejected
    return report


PRIOR_HALF_WIDTH_DEG = 10.0


def pose_prior(params: PoseParams, tracker: MountTracker) -> PoseParams:
    """The floor search's tilt window: centred on a tilt sensor's reading while one gives the mount.

    Rounded to whole degrees, so the pose stage's per-prior tables are reused frame after frame.
    """
    if tracker.source not in ("accel", "serial"):
        return params
    t = round(tracker.mount.tilt_deg)
    lo = max(params.tilt_min_deg, t - PRIOR_HALF_WIDTH_DEG)
    hi = min(params.tilt_max_deg, t + PRIOR_HALF_WIDTH_DEG)
    if lo >= hi:  # the sensor disagrees with the configured window: trust the configured window
        return params
    return dataclasses.replace(params, tilt_min_deg=lo, tilt_max_deg=hi)


def _update_tilt_prior(
    tracker: MountTracker, frame: Frame, tilt_source: str, serial_tilt: object | None
) -> None:
    if tilt_source in ("auto", "accel") and frame.accel_mps2 is not None:
        try:
            tilt, roll = tilt_roll_from_accel(frame.accel_mps2)
        except ValueError as exc:
            log.debug("accelerometer reading ignored: %s", exc)
            return
        tracker.from_tilt_sensor(tilt, roll, "accel")
    elif tilt_source in ("auto", "serial") and serial_tilt is not None:
        reading = serial_tilt.latest(max_age_s=2.0)  # type: ignore[attr-defined]
        if reading is not None:
            tracker.from_tilt_sensor(reading.tilt_deg, reading.roll_deg, "serial")


def _apply_pose(tracker: MountTracker, est: PoseEstimate, tilt_source: str) -> None:
    if not est.ok:
        log.debug("floor pose not confident: %s", est.reason)
        return
    if tilt_source == "config":
        return  # the user pinned the mount
    note = tracker.from_floor(est.height_m, est.tilt_deg, est.roll_deg)
    if note:
        (log.warning if "not applied" in note else log.info)("%s", note)
