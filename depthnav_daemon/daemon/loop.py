"""The frame loop: read a frame, decide the mount and run the stages (``frame_step``), fan the
result out to every sink. Data flows one way: driver -> loop -> stages -> sinks.

A device that stops delivering is reconnected with backoff and reported; a sink that fails is
dropped and reported while the others go on; a stop event (set by SIGINT/SIGTERM) ends the loop
within a second and every sink is closed (flushed). Under systemd, start-up is over (READY=1)
once the first frame went out: the wait for the device and the first frame are start-up steps
that ask systemd for more time while they last (notify.py).

What the several-sensor loop (multi.py) shares with this one lives apart, so neither imports the
other back: the run's report (report.py), the device's frames (frames.py) and the sinks' side
(outputs.py).
"""

from __future__ import annotations

import dataclasses
import logging
import threading
from collections.abc import Callable

from depthnav_daemon import __version__
from depthnav_daemon.config.loader import Config
from depthnav_daemon.daemon.frame_step import FrameStep
from depthnav_daemon.daemon.frames import frames_of
from depthnav_daemon.daemon.memory_keeper import MemoryKeeper, open_odometry
from depthnav_daemon.daemon.multi import run_sensors
from depthnav_daemon.daemon.notify import FIRST_FRAME_S, OPEN_MARGIN_S, ServiceNotifier
from depthnav_daemon.daemon.outputs import close_outputs, fan_out, open_sinks, with_memory
from depthnav_daemon.daemon.report import RunReport
from depthnav_daemon.daemon.source import DeviceSource
from depthnav_daemon.errors import ConfigError, FrameError
from depthnav_daemon.pipeline import Result, StageParams
from depthnav_daemon.pipeline.geometry import Mount
from depthnav_daemon.sinks import create_sink
from depthnav_daemon.sinks.base import Sink, SinkContext
from drivers import create_driver
from drivers.base import DeviceInfo, Driver
from drivers.errors import DriverError
from drivers.odometry import OdometrySource
from drivers.tilt import TiltSource

log = logging.getLogger(__name__)


def run(
    cfg: Config,
    stop: threading.Event,
    max_frames: int | None = None,
    driver_factory: Callable[[str], Driver] = create_driver,
    sink_factory: Callable[[str], Sink] = create_sink,
    serial_tilt: TiltSource | None = None,
    notifier: ServiceNotifier | None = None,
) -> RunReport:
    """Run the frame loop until the source ends, ``max_frames`` frames, or ``stop`` is set.

    Args:
        cfg: the effective configuration (cfg.device names the device; with [[sensor]] tables,
            cfg.sensors, the several-sensor loop of daemon/multi.py runs instead).
        stop: set it to stop the loop (signal handlers do).
        max_frames: stop after this many frames; None = no limit.
        driver_factory, sink_factory: how specs become drivers and sinks.
        serial_tilt: a started drivers.tilt.TiltSource, or None.
        notifier: tells systemd how start-up goes and the loop runs (default: from the
            environment).

    Raises:
        DepthnavError, DriverError: what ended the run; the message is fit for the user.
    """
    notifier = notifier or ServiceNotifier()
    if cfg.sensors:
        return run_sensors(cfg, stop, max_frames, driver_factory, sink_factory, notifier)
    report = RunReport()
    params = StageParams(scan=cfg.scan, cliff=cfg.cliff if cfg.daemon.cliff else None)
    step = FrameStep(cfg, params, serial_tilt)
    source = DeviceSource(cfg.device, cfg.daemon, stop, driver_factory)
    opened = _open_inputs(cfg, source, step, notifier, stop)
    if opened is None:  # stopped while waiting for the device
        report.stopped = True
        return report
    cfg, step, info, odometry = _with_device_mount(cfg, opened, step, params, serial_tilt)
    sinks: list[Sink] = []
    keeper = MemoryKeeper(cfg.memory, cfg.odometry, odometry)
    notifier.starting(f"opening the sinks, first frame of {info.name}", FIRST_FRAME_S)
    try:
        context = SinkContext(
            info, cfg.scan, cfg.cliff.block_size, __version__, cfg.mount, cfg.robot.footprint_m
        )
        sinks = open_sinks(cfg.sinks, context, sink_factory)
        # the obstacle mask costs a pass over the image: only when a sink draws it
        wanted = any(getattr(sink, "needs_obstacle_mask", False) for sink in sinks)
        step.params = dataclasses.replace(params, obstacle_mask=wanted)
        for frame, arrival_s in frames_of(source, cfg, stop, report):
            try:
                result = step.run(frame)
            except FrameError as exc:
                log.warning("frame %d skipped: %s", frame.seq, exc)
                if not notifier.is_ready:  # the stages ran: start-up is over all the same
                    notifier.ready(f"running on {info.name}")
                continue
            if not keeper.idle_for(frame):
                result = with_memory(keeper, frame, arrival_s, [(result, step.params)], result)
            if result.warning:
                log.debug("frame %d: %s", frame.seq, result.warning)
            fan_out(sinks, frame, result, report)
            report.frames += 1
            report.last_result = result
            if not notifier.is_ready:
                notifier.ready(f"running on {info.name}")
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
        keeper.refusals.flush()
        report.memory_resets = keeper.resets
        report.reconnects = source.reconnects
        report.rejected_pose_jumps = step.rejected_pose_jumps
    return report


def _with_device_mount(
    cfg: Config,
    opened: tuple[DeviceInfo, OdometrySource | None],
    step: FrameStep,
    params: StageParams,
    tilt: TiltSource | None,
) -> tuple[Config, FrameStep, DeviceInfo, OdometrySource | None]:
    """``cfg`` and ``step`` with the recording's mount (:func:`mount_from_device`) when it
    gives one nobody configured, else as they are; and what was opened."""
    info, odometry = opened
    placed = mount_from_device(cfg, info)
    if placed is None:
        return cfg, step, info, odometry
    cfg = dataclasses.replace(cfg, mount=placed)
    step.close()
    return cfg, FrameStep(cfg, params, tilt), info, odometry


def mount_from_device(cfg: Config, info: DeviceInfo) -> Mount | None:
    """The mount a recording gives (a bag's ``/tf_static``: base frame -> the depth camera),
    when the configuration gives none (the built-in mount, not pinned): said in the log; a
    configured mount wins, and one the recording's disagrees with is said too. None otherwise
    (then the configured mount, or the floor search, as without it)."""
    p = info.placement
    if p is None:
        return None
    try:
        placed = Mount(p.height_m, p.tilt_deg, p.roll_deg, p.x_m, p.y_m, p.yaw_deg)
    except ConfigError as exc:
        log.warning("%s: the sensor's placement is not usable (%s): not used", p.source, exc)
        return None
    said = (
        f"{placed.height_m:.3f} m high, tilt {placed.tilt_deg:.1f} deg, roll "
        f"{placed.roll_deg:.1f} deg, at x {placed.x_m:.3f} m, y {placed.y_m:.3f} m, yaw "
        f"{placed.yaw_deg:.1f} deg"
    )
    if cfg.mount != Mount() or cfg.daemon.tilt_source == "config":
        if cfg.mount != placed:
            log.info(
                "the recording's %s places the sensor %s; the configured mount is used",
                p.source,
                said,
            )
        return None
    log.info("mount from the recording's %s: %s (a [mount] in the config wins)", p.source, said)
    return placed


def _open_inputs(
    cfg: Config,
    source: DeviceSource,
    step: FrameStep,
    notifier: ServiceNotifier,
    stop: threading.Event,
) -> tuple[DeviceInfo, OdometrySource | None] | None:
    """Open the device (waiting for it, a start-up step) and the odometry; None when stopped
    meanwhile. When either fails, what is open is closed and systemd is told."""
    notifier.starting(f"opening {cfg.device}", cfg.daemon.wait_for_device_s + OPEN_MARGIN_S)
    try:
        info = source.open()
    except BaseException as exc:
        step.close()
        if stop.is_set() and isinstance(exc, DriverError):  # a stop, not a failure
            notifier.give_up("stopped while waiting for the device")
            return None
        notifier.give_up("the device could not be opened")
        raise
    try:
        odometry = open_odometry(cfg.odometry) if cfg.memory.enabled is not False else None
    except BaseException:  # it cannot open: nothing else is left open
        notifier.give_up("the odometry could not be opened")
        source.close()
        step.close()
        raise
    return info, odometry


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
