"""The frame loop: sinks that fail, devices that stop or go silent, the live mount from the
floor."""

from __future__ import annotations

import threading
from dataclasses import dataclass, field
from pathlib import Path

import pytest

from depthnav_daemon.config.loader import build_config
from depthnav_daemon.daemon.loop import run
from depthnav_daemon.daemon.mount_tracker import MountTracker, TrackerParams
from depthnav_daemon.errors import DepthnavError
from depthnav_daemon.pipeline import Result
from depthnav_daemon.pipeline.geometry import Mount
from depthnav_daemon.sinks.base import SinkContext
from drivers import create_driver
from drivers.base import DeviceInfo, Frame
from drivers.errors import DeviceLost, FrameTimeout

FIXTURE = Path(__file__).resolve().parents[2] / "fixtures" / "corridor_step"
SPEC = f"replay:{FIXTURE}?rate=max"


@dataclass
class CollectSink:
    """Keeps what it is given; optionally fails on its n-th write like a dying transport."""

    name: str = "collect"
    fail_on: int | None = None
    results: list[Result] = field(default_factory=list)
    closed: int = 0
    context: SinkContext | None = None

    def open(self, context: SinkContext) -> None:
        self.context = context

    def write(self, frame: Frame, result: Result) -> None:
        if self.fail_on is not None and len(self.results) + 1 == self.fail_on:
            raise BrokenPipeError("[Errno 32] Broken pipe")
        self.results.append(result)

    def close(self) -> None:
        self.closed += 1


class FlakyDriver:
    """The real replay driver, which the 'cable' drops once: lost after ``lose_after`` frames."""

    def __init__(self, lose_after: int | None, silent: bool = False) -> None:
        self.inner = create_driver(SPEC)
        self.lose_after = lose_after
        self.silent = silent
        self.count = 0

    def open(self) -> DeviceInfo:
        return self.inner.open()

    def read_frame(self, timeout_s: float = 1.0) -> Frame | None:
        if self.lose_after is not None and self.count >= self.lose_after:
            if self.silent:
                raise FrameTimeout("no frame within the timeout")
            raise DeviceLost("usb: [Errno 19] No such device (it may have been disconnected)")
        self.count += 1
        return self.inner.read_frame(timeout_s)

    def close(self) -> None:
        self.inner.close()


def config(*sets: str):
    return build_config([], ["daemon.reconnect_backoff_s=0.01", *sets], {"device": SPEC})


def test_a_failing_sink_is_dropped_and_the_others_go_on() -> None:
    good, bad = CollectSink("good"), CollectSink("bad", fail_on=3)
    sinks = iter([good, bad])
    cfg = build_config([], [], {"device": SPEC, "sinks": ["a", "b"]})
    report = run(cfg, threading.Event(), max_frames=8, sink_factory=lambda _spec: next(sinks))
    assert report.frames == 8
    assert len(good.results) == 8 and len(bad.results) == 2
    assert report.dropped_sinks == ["bad"]
    assert bad.closed == 1 and good.closed == 1


def test_every_sink_failing_ends_the_run_with_an_error() -> None:
    cfg = build_config([], [], {"device": SPEC, "sinks": ["a"]})
    with pytest.raises(DepthnavError, match="every output sink failed"):
        run(cfg, threading.Event(), sink_factory=lambda _spec: CollectSink("only", fail_on=2))


@pytest.mark.parametrize("silent", [False, True], ids=["lost", "silent"])
def test_a_device_that_stops_is_reconnected(silent: bool) -> None:
    drivers = iter([FlakyDriver(3, silent), FlakyDriver(None)])
    sink = CollectSink()
    cfg = config("daemon.frame_timeout_s=0.05", "daemon.max_consecutive_timeouts=2")
    report = run(
        cfg,
        threading.Event(),
        max_frames=10,
        driver_factory=lambda _s: next(drivers),
        sink_factory=lambda _s: sink,
    )
    assert report.reconnects == 1
    assert report.frames == 10
    assert [r.seq for r in sink.results][:3] == [0, 1, 2]


def test_a_device_that_never_comes_back_gives_up_with_a_hint() -> None:
    cfg = config("daemon.reconnect_attempts=2")
    made = []

    def factory(_s: str) -> FlakyDriver:
        made.append(FlakyDriver(2 if not made else 0))
        if len(made) > 1:

            def never_opens() -> None:
                raise DeviceLost("no Kinect found")

            made[-1].open = never_opens  # type: ignore[method-assign]
        return made[-1]

    with pytest.raises(DepthnavError, match="2 reconnect attempts failed") as info:
        run(cfg, threading.Event(), driver_factory=factory, sink_factory=lambda _s: CollectSink())
    assert info.value.hint


def test_stop_event_ends_the_loop_and_closes_sinks() -> None:
    stop = threading.Event()
    sink = CollectSink()

    class Stopper(CollectSink):
        def write(self, frame: Frame, result: Result) -> None:
            super().write(frame, result)
            if len(self.results) == 4:
                stop.set()

    stopper = Stopper("stopper")
    sinks = iter([sink, stopper])
    cfg = build_config([], [], {"device": f"replay:{FIXTURE}?rate=max&loop=1", "sinks": ["a", "b"]})
    report = run(cfg, stop, sink_factory=lambda _s: next(sinks))
    assert report.stopped and report.frames == 4
    assert sink.closed == 1 and stopper.closed == 1


def test_the_floor_pose_feeds_the_scan() -> None:
    """Configured badly (1.0 m, level), the floor estimate corrects the mount the stages use."""
    sink = CollectSink()
    cfg = build_config(
        [],
        ["daemon.tilt_source=floor", "daemon.pose_every_frames=2"],
        {"device": SPEC, "mount": {"height_m": 1.0, "tilt_deg": 0.0}},
    )
    run(cfg, threading.Event(), max_frames=6, sink_factory=lambda _s: sink)
    first, last = sink.results[0], sink.results[-1]
    # estimated on frame 0 and already used for frame 0's scan and cliffs (no false drop-offs from
    # a wrong configured height on the first frame)
    assert first.pose is not None and first.pose.ok
    assert first.mount_source == "floor" and first.mount.height_m == pytest.approx(0.55, abs=0.01)
    assert last.mount_source == "floor"
    assert last.mount.height_m == pytest.approx(0.55, abs=0.01)
    assert last.mount.tilt_deg == pytest.approx(15.0, abs=0.5)


def test_the_accelerometer_gives_the_first_tilt() -> None:
    sink = CollectSink()
    cfg = build_config(
        [], ["daemon.pose_every_frames=0"], {"device": SPEC, "mount": {"tilt_deg": 0.0}}
    )
    run(cfg, threading.Event(), max_frames=3, sink_factory=lambda _s: sink)
    assert sink.results[0].mount_source == "accel"
    assert sink.results[0].mount.tilt_deg == pytest.approx(
        15.0, abs=0.5
    )  # the fixture's accel says 15 deg


def test_mount_tracker_holds_back_a_jump_until_it_is_confirmed() -> None:
    t = MountTracker(
        Mount(0.5, 10.0, 0.0),
        TrackerParams(smoothing=0.5, max_jump_m=0.05, max_jump_deg=3.0, confirmations=3),
    )
    assert "from the floor" in (t.from_floor(0.55, 15.0, 0.0) or "")
    assert t.mount == Mount(0.55, 15.0, 0.0)
    assert t.from_floor(0.56, 15.4, 0.2) is None  # small: smoothed in halfway
    assert t.mount.height_m == pytest.approx(0.555) and t.mount.tilt_deg == pytest.approx(15.2)
    before = t.mount
    assert "not applied" in (t.from_floor(0.80, 30.0, 0.0) or "")  # a jump: held back
    assert "not applied" in (
        t.from_floor(0.20, 5.0, 0.0) or ""
    )  # disagrees with the first: restart
    assert t.mount == before and t.rejected == 2
    t.from_floor(0.80, 30.0, 0.0)
    t.from_floor(0.80, 30.1, 0.0)
    assert "accepted" in (t.from_floor(0.81, 30.0, 0.0) or "")  # three agreeing: the sensor moved
    assert t.mount.height_m == pytest.approx(0.81)


def test_mount_tracker_uses_tilt_sensor_only_until_the_floor_speaks() -> None:
    t = MountTracker(Mount(0.5, 0.0, 0.0), TrackerParams())
    t.from_tilt_sensor(14.0, 1.0, "accel")
    assert t.source == "accel" and t.mount.tilt_deg == 14.0 and t.mount.height_m == 0.5
    t.from_floor(0.6, 15.0, 0.0)
    t.from_tilt_sensor(40.0, 0.0, "accel")
    assert t.source == "floor" and t.mount.tilt_deg == 15.0


def test_mount_tracker_deadband_keeps_the_applied_mount_through_wobble() -> None:
    """Sub-millimetre wobble of the estimates must not move the mount (each move rebuilds
    tables)."""
    t = MountTracker(
        Mount(0.5, 10.0, 0.0), TrackerParams(smoothing=0.5, deadband_m=0.002, deadband_deg=0.1)
    )
    t.from_floor(0.55, 15.0, 0.0)
    applied = t.mount
    for k in range(20):
        t.from_floor(0.55 + (0.0005 if k % 2 else -0.0005), 15.0 + (0.02 if k % 2 else -0.02), 0.0)
    assert t.mount is applied
    for _ in range(10):  # a real drift of 1 cm gets through
        t.from_floor(0.56, 15.0, 0.0)
    assert t.mount.height_m == pytest.approx(0.56, abs=0.002)


def test_tilt_sensor_narrows_the_floor_search_window() -> None:
    from depthnav_daemon.daemon.frame_step import pose_prior
    from depthnav_daemon.pipeline.pose import PoseParams

    base = PoseParams(tilt_min_deg=-10.0, tilt_max_deg=60.0)
    t = MountTracker(Mount(0.55, 5.0, 0.0), TrackerParams())
    assert pose_prior(base, t) is base  # configured mount: the configured window
    t.from_tilt_sensor(15.3, 0.0, "accel")
    p = pose_prior(base, t)
    assert (p.tilt_min_deg, p.tilt_max_deg) == (5.0, 25.0)  # 15 +- 10, whole degrees
    assert (p.height_min_m, p.height_max_m) == (base.height_min_m, base.height_max_m)
    t.from_floor(0.5, 15.0, 0.0)
    assert pose_prior(base, t) is base  # the floor speaks for itself
    # the built-in mount nobody configured: the tilt sensor's +-10 deg at any height (calibrate's
    # search, tests/daemon/test_unconfigured_mount.py)
    t = MountTracker(Mount(), TrackerParams())
    t.from_tilt_sensor(71.6, -4.2, "accel")
    p = pose_prior(PoseParams(), t)
    assert (p.tilt_min_deg, p.tilt_max_deg, p.roll_max_deg) == (62.0, 82.0, 14.0)
    assert (p.height_min_m, p.height_max_m) == (0.05, 3.0)


def test_serial_tilt_source_gives_the_mount_through_a_pty() -> None:
    """An IMU on a serial port (a pty pair, a simulator thread writing $TILT lines) sets tilt and
    roll."""
    import os
    import time as _time

    from drivers.tilt.serialtilt import SerialTiltSource, format_line

    master, slave = os.openpty()
    stop = threading.Event()

    def imu() -> None:
        while not stop.is_set():
            os.write(master, format_line(21.5, -3.0))
            _time.sleep(0.02)

    feeder = threading.Thread(target=imu, daemon=True)
    feeder.start()
    source = SerialTiltSource.from_spec(f"serialtilt:{os.ttyname(slave)}?protocol=line")
    source.start()
    try:
        deadline = _time.monotonic() + 20
        while source.latest() is None and _time.monotonic() < deadline:
            _time.sleep(0.02)
        sink = CollectSink()
        cfg = build_config(
            [], ["daemon.tilt_source=serial", "daemon.pose_every_frames=0"], {"device": SPEC}
        )
        run(cfg, threading.Event(), max_frames=3, sink_factory=lambda _s: sink, serial_tilt=source)
    finally:
        stop.set()
        source.stop()
        feeder.join(2)
        os.close(master)
        os.close(slave)
    assert sink.results[0].mount_source == "serial"
    assert sink.results[0].mount.tilt_deg == pytest.approx(21.5)
    assert sink.results[0].mount.roll_deg == pytest.approx(-3.0)
