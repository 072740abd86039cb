"""Several sensors in one daemon ([[sensor]] tables): each reads, estimates its mount and runs its
stages on its own thread; the frame loop merges their base-frame scans and fans the result out.

Every time a sensor delivers a frame, one Result goes out: its scan and cliff scan are the merge of
every sensor whose latest result is younger than ``[daemon] sensor_max_age_s`` (pipeline/merge.py),
its cliff points those sensors' points, and ``sensors`` lists each sensor with its status and its
own latest Result. A sensor that falls silent is reported and left out until it delivers again; one
that is lost for good (reconnects exhausted, a bad recording) is reported and the others go on;
nothing one sensor does blocks another. The memory is updated with each sensor's view as it comes.

A sensor whose device cannot be opened at start-up (within ``daemon.wait_for_device_s``) ends the
start-up with one line naming it, exit 1, before any output: until a device has opened its field of
view is not known, so the merged scan could not say that its bearings are unknown, and a robot
configured with it would take their absence for "no data" rather than a fault.
"""

from __future__ import annotations

import dataclasses
import logging
import queue
import threading
import time
from collections.abc import Callable

import numpy as np

from depthnav_daemon import __version__
from depthnav_daemon.config.loader import Config, SensorConfig
from depthnav_daemon.daemon.frame_step import FrameStep
from depthnav_daemon.daemon.frames import frames_of
from depthnav_daemon.daemon.memory_keeper import MemoryKeeper, open_odometry
from depthnav_daemon.daemon.notify import FIRST_FRAME_S, OPEN_MARGIN_S, ServiceNotifier
from depthnav_daemon.daemon.outputs import close_outputs, fan_out, open_sinks, with_memory
from depthnav_daemon.daemon.report import RunReport
from depthnav_daemon.daemon.source import DeviceSource
from depthnav_daemon.errors import DepthnavError, FrameError
from depthnav_daemon.pipeline import Result, StageParams
from depthnav_daemon.pipeline.cliff import CliffResult
from depthnav_daemon.pipeline.merge import SensorState, merge_scans
from depthnav_daemon.sinks.base import Sink, SinkContext
from drivers.base import DeviceInfo, Driver, Frame
from drivers.errors import DriverError
from drivers.values import short_repr

log = logging.getLogger(__name__)

POLL_S = 0.25
Item = tuple[str, Frame | None, float, Result | None]


class SensorWorker:
    """One sensor: its device, mount tracker and stages, run on its own thread.

    Results go to ``inbox`` as (name, frame, arrival_s, result); a final (name, None, 0, None)
    says the thread ended (``status`` says why: "ended" or "lost").
    """

    def __init__(
        self,
        sc: SensorConfig,
        cfg: Config,
        halt: threading.Event,
        factory: Callable[[str], Driver],
        inbox: queue.Queue[Item],
    ) -> None:
        self.name = sc.name
        self.cfg = dataclasses.replace(cfg, device=sc.device, mount=sc.mount, sensors=())
        self.params = StageParams(scan=cfg.scan, cliff=cfg.cliff if cfg.daemon.cliff else None)
        self.step = FrameStep(self.cfg, self.params, None)
        self.source = DeviceSource(sc.device, cfg.daemon, halt, factory)
        self.halt = halt
        self.inbox = inbox
        self.status = "starting"
        self.frames = 0
        self.thread = threading.Thread(target=self._run, name=f"sensor {sc.name}", daemon=True)

    def open(self) -> DeviceInfo:
        """Open the device.

        Raises:
            DepthnavError: it cannot be opened (the driver's reason and hint, naming the sensor).
        """
        try:
            return self.source.open()
        except DriverError as exc:
            self.status = "lost"
            raise DepthnavError(
                f"sensor {short_repr(self.name)}: {exc}",
                hint=exc.hint or "check the [[sensor]] device spec and its cable",
            ) from exc

    def _run(self) -> None:
        report = RunReport()
        try:
            for frame, arrival in frames_of(self.source, self.cfg, self.halt, report):
                try:
                    result = self.step.run(frame)
                except FrameError as exc:
                    log.warning("sensor %s: frame %d skipped: %s", self.name, frame.seq, exc)
                    continue
                report.frames += 1
                self.frames += 1
                self._put((self.name, frame, arrival, result))
            self.status = "ended"
        except (DepthnavError, DriverError) as exc:
            self.status = "lost"
            log.error("sensor %s lost: %s; the other sensors go on", self.name, exc)
        finally:
            self._put((self.name, None, 0.0, None))

    def _put(self, item: Item) -> None:
        while not self.halt.is_set():
            try:
                self.inbox.put(item, timeout=POLL_S)
                return
            except queue.Full:
                continue

    def close(self) -> None:
        if self.thread.ident is not None:  # a worker that never started has no thread to join
            self.thread.join(timeout=5.0)
        self.source.close()
        self.step.close()


class Merger:
    """The latest result of each sensor, who is in the merge, and the merged Result."""

    def __init__(self, names: list[str], max_age_s: float) -> None:
        self.names = names
        self.max_age_s = max_age_s
        self.latest: dict[str, tuple[Result, float]] = {}
        self._in: dict[str, bool] = {}
        self.seq = 0

    def states(self, now: float, status: dict[str, str]) -> list[SensorState]:
        """Every sensor's state at ``now`` (``status``: the workers' own, "lost" / "ended" / other);
        says who leaves the merge for being silent and who comes back."""
        out = []
        for name in self.names:
            got = self.latest.get(name)
            age = None if got is None else now - got[1]
            st = status.get(name, "")
            if st not in ("lost", "ended"):
                st = "ok" if age is not None and age <= self.max_age_s else "stale"
            was = self._in.get(name)
            if was and st == "stale":
                log.warning(
                    "sensor %s: no frame for %.1f s; left out of the merged scan", name, age
                )
            elif was is False and st == "ok":
                log.info("sensor %s delivers again; back in the merged scan", name)
            if got is not None:
                self._in[name] = st == "ok"
            out.append(SensorState(name, st, age, None if got is None else got[0]))
        return out

    def merged(self, arriving: Result, states: list[SensorState]) -> Result:
        """``arriving`` with the merged scan and cliff of the sensors in the merge."""
        live = [s.result for s in states if s.status == "ok" and s.result is not None]
        live = live or [arriving]
        scan = merge_scans([r.scan for r in live])
        cliffs = [r.cliff for r in live if r.cliff is not None]
        cliff = None
        if cliffs:
            cliff = CliffResult(
                np.concatenate([np.asarray(c.points_m).reshape(-1, 2) for c in cliffs]),
                arriving.cliff.blocks if arriving.cliff is not None else cliffs[0].blocks,
                cliffs[0].block_size,
                merge_scans([c.scan for c in cliffs]),
            )
        self.seq += 1
        # the merged drop-offs are as trustworthy as the least trusted sensor's
        doubtful = [
            r.mount_trust
            for r in live
            if r.mount_trust is not None and not r.mount_trust.dropoffs_trusted
        ]
        trust = doubtful[0] if doubtful else arriving.mount_trust
        return dataclasses.replace(
            arriving,
            mount_state=dataclasses.replace(arriving.mount_state, trust=trust),
            seq=self.seq - 1,
            scan=scan,
            cliff=cliff,
            sensors=tuple(states),
            timings_s=dict(arriving.timings_s),
        )


def run_sensors(
    cfg: Config,
    stop: threading.Event,
    max_frames: int | None,
    driver_factory: Callable[[str], Driver],
    sink_factory: Callable[[str], Sink],
    notifier: ServiceNotifier | None = None,
) -> RunReport:
    """The frame loop for several sensors (module docstring); returns the loop's RunReport.
    Start-up is over (READY=1) once the first merged frame went out."""
    notifier = notifier or ServiceNotifier()
    report = RunReport()
    halt = threading.Event()
    inbox: queue.Queue[Item] = queue.Queue(maxsize=4 * len(cfg.sensors))
    workers = _make_workers(cfg, halt, driver_factory, inbox)
    # a stop ends the workers' wait for their devices too (they watch ``halt``)
    threading.Thread(target=_follow, args=(stop, halt), name="stop to halt", daemon=True).start()
    notifier.starting(
        f"opening {len(workers)} sensors",
        len(workers) * (cfg.daemon.wait_for_device_s + OPEN_MARGIN_S),
    )
    try:
        opened = _open_all(workers, halt)
    except DepthnavError:
        notifier.give_up("a sensor could not be opened")
        raise
    if opened is None:  # stopped while waiting for a device
        notifier.give_up("stopped while waiting for the sensors")
        report.stopped = True
        return report
    sinks: list[Sink] = []
    try:
        odometry = open_odometry(cfg.odometry) if cfg.memory.enabled is not False else None
    except BaseException:  # it cannot open: nothing else is left open (no thread started yet)
        halt.set()
        notifier.give_up("the odometry could not be opened")
        for w in workers:
            w.source.close()
            w.step.close()
        raise
    keeper = MemoryKeeper(cfg.memory, cfg.odometry, odometry)
    notifier.starting("opening the sinks, first merged frame", FIRST_FRAME_S)
    try:
        context = SinkContext(
            opened[0], cfg.scan, cfg.cliff.block_size, __version__, body_m=cfg.robot.footprint_m
        )
        sinks = open_sinks(cfg.sinks, context, sink_factory)
        for w in workers:
            w.thread.start()
        merger = Merger([w.name for w in workers], cfg.daemon.sensor_max_age_s)
        _serve(workers, workers, inbox, merger, keeper, sinks, stop, max_frames, report, notifier)
        report.stopped = stop.is_set()
    finally:
        halt.set()
        close_outputs(sinks, notifier, report)
        for w in workers:
            w.close()
        if odometry is not None:
            odometry.stop()
        keeper.refusals.flush()
        report.lost_sensors = [w.name for w in workers if w.status == "lost"]
        report.memory_resets = keeper.resets
        report.reconnects = sum(w.source.reconnects for w in workers)
    return report


def _make_workers(
    cfg: Config,
    halt: threading.Event,
    factory: Callable[[str], Driver],
    inbox: queue.Queue[Item],
) -> list[SensorWorker]:
    """One worker per [[sensor]]; a spec no driver takes is one line naming the sensor."""
    workers: list[SensorWorker] = []
    for sc in cfg.sensors:
        try:
            workers.append(SensorWorker(sc, cfg, halt, factory, inbox))
        except DriverError as exc:  # nothing opened or started yet
            for w in workers:
                w.step.close()
            raise DepthnavError(f"sensor {short_repr(sc.name)}: {exc}", hint=exc.hint) from exc
    return workers


def _open_all(workers: list[SensorWorker], halt: threading.Event) -> list[DeviceInfo] | None:
    """Every sensor's device opened, in order; None when a stop came while waiting for one.

    Raises:
        DepthnavError: one cannot be opened (module docstring); every worker is closed then.
    """
    infos: list[DeviceInfo] = []
    try:
        for w in workers:
            infos.append(w.open())
    except DepthnavError:
        stopped = halt.is_set()
        halt.set()
        for w in workers:
            w.close()
        if stopped:
            return None
        raise
    return infos


def _follow(stop: threading.Event, halt: threading.Event) -> None:
    """Set ``halt`` once ``stop`` is set; ends with ``halt`` either way."""
    while not halt.is_set():
        if stop.wait(POLL_S):
            halt.set()


def _serve(
    started: list[SensorWorker],
    workers: list[SensorWorker],
    inbox: queue.Queue[Item],
    merger: Merger,
    keeper: MemoryKeeper,
    sinks: list[Sink],
    stop: threading.Event,
    max_frames: int | None,
    report: RunReport,
    notifier: ServiceNotifier,
) -> None:
    """Merge and fan out every sensor result until every sensor ends, ``max_frames`` or ``stop``."""
    by_name = {w.name: w for w in workers}
    running = {w.name for w in started}

    def statuses() -> dict[str, str]:
        return {w.name: w.status for w in workers}

    while running and not stop.is_set():
        try:
            name, frame, arrival, result = inbox.get(timeout=POLL_S)
        except queue.Empty:
            merger.states(time.monotonic(), statuses())  # says who fell silent
            continue
        if frame is None or result is None:
            running.discard(name)
            continue
        merger.latest[name] = (result, arrival)
        t0 = time.perf_counter()
        out = merger.merged(result, merger.states(time.monotonic(), statuses()))
        out.timings_s["merge"] = time.perf_counter() - t0
        if not keeper.idle_for(frame):
            out = with_memory(keeper, frame, arrival, [(result, by_name[name].params)], out)
        fan_out(sinks, frame, out, report)
        report.frames += 1
        report.last_result = out
        sensors = len(running)
        if not notifier.is_ready:
            notifier.ready(f"running on {len(started)} of {len(workers)} sensors")
        notifier.frame(
            report.frames,
            lambda fps, n=sensors: f"{fps:.1f} frames/s from {n} sensors",
        )
        if max_frames is not None and report.frames >= max_frames:
            return
