"""The frame loop: read a frame, decide the mount and run the stages (``frame_step``), fan the
result out to every sink. Data flows one way: driver -> loop -> stages -> sinks.

A device that stops delivering is reconnected with backoff and reported; a sink that fails is
dropped and reported while the others go on; a stop event (set by SIGINT/SIGTERM) ends the loop
within a second and every sink is closed (flushed).
"""

from __future__ import annotations

import dataclasses
import logging
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field

from depthnav_daemon import __version__
from depthnav_daemon.config.loader import Config
from depthnav_daemon.daemon.frame_step import FrameStep
from depthnav_daemon.daemon.memory_keeper import MemoryKeeper, open_odometry
from depthnav_daemon.daemon.notify import ServiceNotifier
from depthnav_daemon.daemon.source import DeviceSource
from depthnav_daemon.errors import DepthnavError, FrameError, SinkError
from depthnav_daemon.pipeline import Result, StageParams
from depthnav_daemon.sinks import create_sink
from depthnav_daemon.sinks.base import Sink, SinkContext
from drivers import create_driver
from drivers.base import Driver, Frame
from drivers.errors import DriverError, FrameTimeout, RecordingError
from drivers.tilt import TiltSource

log = logging.getLogger(__name__)

POLL_S = 0.25  # longest a read blocks, so a stop request is seen within a second


@dataclass
class RunReport:
    """What a run did, for the CLI's summary and the tests."""

    frames: int = 0
    reconnects: int = 0
    dropped_sinks: list[str] = field(default_factory=list)
    rejected_pose_jumps: int = 0
    memory_resets: int = 0
    lost_sensors: list[str] = field(default_factory=list)
    last_result: Result | None = None
    stopped: bool = False  # ended by the stop event rather than by the source


def open_sinks(
    specs: tuple[str, ...], context: SinkContext, factory: Callable[[str], Sink]
) -> list[Sink]:
    """Open every sink; one that cannot start is reported and left out while others started.

    Raises:
        DepthnavError: no sink could start (each failure is named in the message, once).
    """
    sinks: list[Sink] = []
    failures: list[tuple[str, str | None]] = []  # (what failed, its hint)
    for spec in specs:
        sink = factory(spec)
        try:
            sink.open(context)
        except (SinkError, OSError) as exc:
            failures.append(
                (f"sink {spec} could not start: {_one_line(exc)}", getattr(exc, "hint", None))
            )
            continue
        sinks.append(sink)
    if not sinks:
        if len(failures) == 1:
            what, hint = failures[0]
            raise DepthnavError(
                f"{what}; no output sink could start", hint=hint or "check the --sink spec"
            )
        for what, hint in failures:
            log.error("%s%s", what, f" ({hint})" if hint else "")
        raise DepthnavError(
            f"no output sink could start ({len(failures)} tried, see above)",
            hint="check the --sink specs (depthnav run --help)",
        )
    for what, hint in failures:  # only now is "going on without it" true
        log.error("%s; going on without it%s", what, f" ({hint})" if hint else "")
    return sinks


def _one_line(exc: BaseException) -> str:
    text = str(exc)
    return text.splitlines()[0] if text else type(exc).__name__


def fan_out(sinks: list[Sink], frame: Frame, result: Result, report: RunReport) -> None:
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
    serial_tilt: TiltSource | None = None,
) -> RunReport:
    """Run the frame loop until the source ends, ``max_frames`` frames, or ``stop`` is set.

    Args:
        cfg: the effective configuration (cfg.device names the device; with [[sensor]] tables,
            cfg.sensors, the several-sensor loop of daemon/multi.py runs instead).
        stop: set it to stop the loop (signal handlers do).
        max_frames: stop after this many frames; None = no limit.
        driver_factory, sink_factory: how specs become drivers and sinks.
        serial_tilt: a started drivers.tilt.TiltSource, or None.

    Raises:
        DepthnavError, DriverError: what ended the run; the message is fit for the user.
    """
    if cfg.sensors:
        from depthnav_daemon.daemon.multi import run_sensors

        return run_sensors(cfg, stop, max_frames, driver_factory, sink_factory)  # type: ignore[return-value]
    report = RunReport()
    params = StageParams(scan=cfg.scan, cliff=cfg.cliff if cfg.daemon.cliff else None)
    step = FrameStep(cfg, params, serial_tilt)
    source = DeviceSource(cfg.device, cfg.daemon, stop, driver_factory)
    info = source.open()
    sinks: list[Sink] = []
    odometry = open_odometry(cfg.odometry) if cfg.memory.enabled is not False else None
    keeper = MemoryKeeper(cfg.memory, cfg.odometry, odometry)
    notifier = ServiceNotifier()
    try:
        context = SinkContext(info, cfg.scan, cfg.cliff.block_size, __version__, cfg.mount)
        sinks = open_sinks(cfg.sinks, context, sink_factory)
        # the obstacle mask costs a pass over the image: only when a sink draws it
        wanted = any(getattr(sink, "needs_obstacle_mask", False) for sink in sinks)
        step.params = dataclasses.replace(params, obstacle_mask=wanted)
        notifier.ready(f"running on {info.name}")
        for frame, arrival_s in frames_of(source, cfg, stop, report):
            try:
                result = step.run(frame)
            except FrameError as exc:
                log.warning("frame %d skipped: %s", frame.seq, exc)
                continue
            if not keeper.idle_for(frame):
                result = with_memory(keeper, frame, arrival_s, [(result, step.params)], result)
            if result.warning:
                log.debug("frame %d: %s", frame.seq, result.warning)
            fan_out(sinks, frame, result, report)
            report.frames += 1
            report.last_result = result
            notifier.frame(report.frames, lambda fps, r=result: _status(fps, r))
            if max_frames is not None and report.frames >= max_frames:
                break
        report.stopped = stop.is_set()
    finally:
        close_outputs(sinks, notifier, report)
        source.close()
        step.close()
        if odometry is not None:
            odometry.stop()
        report.memory_resets = keeper.resets
        report.reconnects = source.reconnects
        report.rejected_pose_jumps = step.rejected_pose_jumps
    return report


def with_memory(
    keeper: MemoryKeeper,
    frame: Frame,
    arrival_s: float,
    results: list[tuple[Result, StageParams]],
    out: Result,
) -> Result:
    """``out`` with the memory updated by ``results`` (and its time in timings_s["memory"])."""
    if not keeper.enabled:
        return out
    t0 = time.perf_counter()
    memory = keeper.step(frame, arrival_s, results)
    if memory is None:
        return out
    out.timings_s["memory"] = time.perf_counter() - t0
    return dataclasses.replace(out, memory=memory)


def frames_of(
    source: DeviceSource, cfg: Config, stop: threading.Event, report: RunReport
) -> Iterator[tuple[Frame, float]]:
    """The device's frames, each with its host arrival time (monotonic seconds), until it ends or
    ``stop`` is set; reconnects a silent or lost device."""
    d = cfg.daemon
    last_frame_wall = time.monotonic()
    while not stop.is_set():
        try:
            frame = source.driver.read_frame(timeout_s=min(d.frame_timeout_s, POLL_S))
        except FrameTimeout:
            silent = time.monotonic() - last_frame_wall
            if silent > d.frame_timeout_s * d.max_consecutive_timeouts:
                if not source.reconnect(f"no frame for {silent:.1f} s"):
                    return
                last_frame_wall = time.monotonic()
            continue
        except RecordingError:
            # a bad file does not heal by reopening it: replaying it again would repeat the
            # frames before the bad one forever, so a damaged recording ends the run
            raise
        except DriverError as exc:
            if not source.reconnect(str(exc)):
                return
            last_frame_wall = time.monotonic()
            continue
        if frame is None:
            log.info("end of %s after %d frames", cfg.device, report.frames)
            return
        last_frame_wall = time.monotonic()
        yield frame, last_frame_wall


def _status(fps: float, result: Result) -> str:
    """The one-line STATUS systemd shows: frame rate, the mount in use and how far it is
    trusted."""
    m, trust = result.mount, result.mount_trust
    origin = (
        result.mount_source
        if trust is None
        else f"{trust.source}{', pinned' if trust.pinned else ''}, floor {trust.floor}"
    )
    line = (
        f"{fps:.1f} frames/s, mount {m.height_m:.3f} m, tilt {m.tilt_deg:.1f} deg, "
        f"roll {m.roll_deg:.1f} deg ({origin})"
    )
    if trust is not None and not trust.dropoffs_trusted:
        line += "; drop-offs NOT trusted"
    return line


def close_outputs(sinks: list[Sink], notifier: ServiceNotifier, report: RunReport) -> None:
    """At the end of a run: tell systemd it stops, then close (flush) every sink."""
    notifier.stopping(f"stopping after {report.frames} frames")
    notifier.close()
    for sink in sinks:
        try:
            sink.close()
        except Exception as exc:
            log.error("sink %s did not close cleanly: %s", sink.name, exc)
