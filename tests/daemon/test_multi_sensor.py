"""Several sensors in one daemon: two wide sensors yawed +-40 deg at different places on the robot,
replayed from recordings of one base-frame scene; the merged scan, nearest-wins, a sensor
unplugged mid-run, and bad [[sensor]] tables."""

from __future__ import annotations

import math
import threading
from pathlib import Path

import numpy as np
import pytest

from depthnav_daemon.config.loader import build_config
from depthnav_daemon.daemon.loop import run
from depthnav_daemon.errors import ConfigError
from depthnav_daemon.pipeline.geometry import Mount
from depthnav_daemon.pipeline.merge import layout_of, merge_scans, merged_layout
from depthnav_daemon.sim.synthetic import Box, Scene, render, truth_obstacle_interval
from drivers import create_driver
from drivers.base import DeviceInfo, Frame, Intrinsics
from drivers.errors import DeviceLost, DeviceOpenError
from drivers.formats.recording_writer import write_recording
from tests.daemon.test_loop import CollectSink

WIDE = Intrinsics(424, 240, 178.0, 178.0, 211.75, 119.75)  # 100 deg across (a wide ToF camera)
LEFT = Mount(0.5, 12.0, 0.0, x_m=0.3, y_m=0.12, yaw_deg=40.0)
RIGHT = Mount(0.45, 10.0, 0.0, x_m=0.1, y_m=-0.2, yaw_deg=-40.0)
A = Box(1.0, 1.6, 0.3, 0.3, 0.5)  # ~58 deg left: only the left sensor sees it
B = Box(1.8, -0.05, 0.3, 0.6, 0.5)  # ahead: both see it
C = Box(0.9, -1.4, 0.3, 0.3, 0.5)  # ~-57 deg: only the right sensor sees it
SCENE = Scene(boxes=(A, B, C))


@pytest.fixture(scope="module")
def recordings(tmp_path_factory) -> dict[str, Path]:
    out = {}
    for name, mount in (("left", LEFT), ("right", RIGHT)):
        depth = render(SCENE, WIDE, mount).depth_mm
        path = tmp_path_factory.mktemp("rec") / name
        write_recording(path, [Frame(i, i / 10.0, depth, WIDE) for i in range(3)])
        out[name] = path
    return out


def _config(recordings, *sets: str, right: str | None = None):
    text = ""
    for name, mount in (("left", LEFT), ("right", RIGHT)):
        device = right if name == "right" and right else f"replay:{recordings[name]}?loop=1"
        device = device.replace("loop=1", "loop=1&rate=max")
        text += f'[[sensor]]\nname = "{name}"\ndevice = "{device}"\n[sensor.mount]\n'
        for key in ("height_m", "tilt_deg", "x_m", "y_m", "yaw_deg"):
            text += f"{key} = {getattr(mount, key)}\n"
    path = recordings["left"].parent / f"robot{len(sets)}{bool(right)}.toml"
    path.write_text(text)
    return build_config(
        [path], ["daemon.tilt_source=config", "daemon.reconnect_backoff_s=0.01", *sets]
    )


class UntilSink(CollectSink):
    """Keeps results; sets ``stop`` once ``enough`` of them satisfy ``want`` (no timing: the run
    lasts as long as the machine needs)."""

    def __init__(self, want, enough: int) -> None:
        super().__init__()
        self.want, self.enough, self.stop = want, enough, threading.Event()

    def write(self, frame: Frame, result) -> None:
        super().write(frame, result)
        if sum(map(self.want, self.results)) >= self.enough:
            self.stop.set()


def _bins(scan, box: Box) -> np.ndarray:
    """Bins whose bearing points into the box (from the base origin)."""
    lo, _ = truth_obstacle_interval(Scene(boxes=(box,)), scan.angles, 0.0, 0.05, 2.0)
    return np.isfinite(lo)


def test_merged_scan_is_the_union_in_the_base_frame_and_the_nearest_wins(recordings) -> None:
    both_ok = lambda r: all(s.status == "ok" for s in r.sensors)  # noqa: E731
    sink = UntilSink(both_ok, 3)
    cfg = _config(recordings, "daemon.sensor_max_age_s=600")
    run(cfg, sink.stop, max_frames=2000, sink_factory=lambda _s: sink)
    last = next(r for r in reversed(sink.results) if both_ok(r))
    scan = last.scan
    assert [s.name for s in last.sensors] == ["left", "right"]
    # the union of the two fields of view: 40 + 50 deg either side, and a little more for near
    # points seen from off the origin
    assert math.degrees(scan.angle_min) < -90 and math.degrees(scan.angle_max) > 90
    # every finite bin is the true base-frame range on its bearing, within 1 cm
    half = scan.angle_increment * 1.5
    lo, hi = truth_obstacle_interval(SCENE, scan.angles, half, 0.05, 2.0)
    fin = np.isfinite(scan.ranges)
    assert not (fin & ~np.isfinite(lo)).any()
    assert np.all(scan.ranges[fin] >= lo[fin] - 0.01)
    assert np.all(scan.ranges[fin] <= np.minimum(hi[fin], 99) + 0.01)
    # A only in the left sensor's scan, C only in the right one's: both in the merge
    left, right = (s.result.scan for s in last.sensors)
    assert np.isfinite(scan.ranges[_bins(scan, A)]).sum() > 10
    assert np.isfinite(scan.ranges[_bins(scan, C)]).sum() > 10
    assert not np.isfinite(right.ranges[_bins(right, A)]).any()
    assert not np.isfinite(left.ranges[_bins(left, C)]).any()
    # where both see B, each merged bin is the nearer of the two
    lay = layout_of(scan)
    one = merge_scans([left], lay).ranges
    two = merge_scans([right], lay).ranges
    both = np.isfinite(one) & np.isfinite(two)
    assert both.sum() > 5
    np.testing.assert_array_equal(scan.ranges[both], np.minimum(one, two)[both])
    assert (one[both] != two[both]).any()  # they do differ: the test can fail


class Unplugged:
    """The real replay driver for 3 frames, then the cable is pulled: DeviceLost, and the device
    cannot be opened again."""

    opened = 0

    def __init__(self, spec: str) -> None:
        self.inner = create_driver(spec)
        self.count = 0

    def open(self) -> DeviceInfo:
        Unplugged.opened += 1
        if Unplugged.opened > 1:
            raise DeviceOpenError("usb: no such device")
        return self.inner.open()

    def read_frame(self, timeout_s: float = 1.0) -> Frame | None:
        if self.count >= 3:
            raise DeviceLost("usb: [Errno 19] No such device (it may have been disconnected)")
        self.count += 1
        return self.inner.read_frame(timeout_s)

    def close(self) -> None:
        self.inner.close()


def test_one_sensor_unplugged_leaves_the_other_flowing_and_is_reported(recordings, caplog) -> None:
    Unplugged.opened = 0
    right_spec = f"pulled:replay:{recordings['right']}?loop=1"

    def factory(spec: str):
        if spec.startswith("pulled:"):
            return Unplugged(spec.removeprefix("pulled:"))
        return create_driver(spec)

    right_lost = lambda r: r.sensors[1].status == "lost"  # noqa: E731
    sink = UntilSink(right_lost, 10)
    cfg = _config(
        recordings, "daemon.sensor_max_age_s=600", "daemon.reconnect_attempts=2", right=right_spec
    )
    with caplog.at_level("WARNING"):
        report = run(cfg, sink.stop, 2000, driver_factory=factory, sink_factory=lambda _s: sink)
    assert report.lost_sensors == ["right"]
    lost = [r for r in sink.results if right_lost(r)]
    assert len(lost) >= 10  # the left sensor went on
    assert all(r.sensors[0].status == "ok" for r in lost)
    # the merge is the left sensor's alone: A is there, C (right only) is gone
    scan = lost[-1].scan
    assert np.isfinite(scan.ranges[_bins(scan, A)]).any()
    assert not np.isfinite(scan.ranges[_bins(scan, C)]).any()
    said = [r.getMessage() for r in caplog.records if "sensor right lost" in r.getMessage()]
    assert len(said) == 1 and "the other sensors go on" in said[0]


@pytest.mark.parametrize(
    ("text", "why"),
    [
        (
            '[[sensor]]\nname = "a"\ndevice = "kinect"\n[[sensor]]\nname = "a"\ndevice = "x"\n',
            "two sensors are named 'a'",
        ),
        (
            '[[sensor]]\nname = "a"\ndevice = "kinect"\n[sensor.mount]\nx_m = 12.0\n',
            r"sensor 'a': mount x_m=12.0 is out of range \(accepted: -10..10 m\)",
        ),
        (
            '[[sensor]]\nname = "a"\ndevice = "kinect"\n[sensor.mount]\nyaw_deg = -200\n',
            r"sensor 'a': mount yaw_deg=-200.0 is out of range",
        ),
        ('[[sensor]]\nname = "a"\n', "sensor 'a': needs a device spec"),
        ('[[sensor]]\ndevice = "kinect"\n', "sensor 1: needs a name"),
        ('[[sensor]]\nname = "a"\ndevice = "k"\nfps = 3\n', "sensor 1: unknown key 'fps'"),
        (
            'device = "kinect"\n[[sensor]]\nname = "a"\ndevice = "k"\n',
            "both device and \\[\\[sensor\\]\\] tables are given",
        ),
    ],
)
def test_bad_sensor_tables_are_one_line(tmp_path, text: str, why: str) -> None:
    path = tmp_path / "bad.toml"
    path.write_text(text)
    with pytest.raises(ConfigError, match=why) as info:
        build_config([path])
    assert "\n" not in str(info.value)


def test_merged_layout_covers_the_union_and_a_full_turn() -> None:
    d = math.radians
    inc = d(0.25)
    left = (d(11), inc, 232)  # 11 .. 68.75 deg
    back = (d(150), inc, 400)  # 150 .. 249.75 deg: across +-180
    a0, w, n = merged_layout((left, back))
    assert w == inc and math.degrees(a0) == pytest.approx(11.0)
    assert math.degrees(a0 + (n - 1) * w) == pytest.approx(249.75)
    around = tuple((d(k), inc, 400) for k in (0, 90, 180, 270))
    assert merged_layout(around) == (-math.pi, inc, 1440)


def test_a_silent_sensor_is_left_out_reported_once_and_taken_back(recordings, caplog) -> None:
    from depthnav_daemon.daemon.multi import Merger
    from depthnav_daemon.pipeline import StageParams, process
    from depthnav_daemon.pipeline.scan import ScanParams

    params = StageParams(scan=ScanParams())
    frames = {n: create_driver(f"replay:{p}?rate=max") for n, p in recordings.items()}
    results = {}
    for name, drv in frames.items():
        drv.open()
        results[name] = process(drv.read_frame(1.0), LEFT if name == "left" else RIGHT, params)
        drv.close()
    m = Merger(["left", "right"], max_age_s=0.5)
    m.latest = {"left": (results["left"], 10.0), "right": (results["right"], 10.0)}
    with caplog.at_level("INFO"):
        assert [s.status for s in m.states(10.2, {})] == ["ok", "ok"]
        m.latest["left"] = (results["left"], 10.6)
        states = m.states(10.7, {})  # right: 0.7 s without a frame
        assert [s.status for s in states] == ["ok", "stale"]
        assert states[1].age_s == pytest.approx(0.7)
        m.states(10.8, {})  # still stale: not said again
        merged = m.merged(results["left"], states)
        assert np.isfinite(merged.scan.ranges[_bins(merged.scan, A)]).any()
        assert not np.isfinite(merged.scan.ranges[_bins(merged.scan, C)]).any()  # right left out
        m.latest["right"] = (results["right"], 10.9)
        assert [s.status for s in m.states(11.0, {})] == ["ok", "ok"]
        assert [s.status for s in m.states(11.0, {"right": "lost"})] == ["ok", "lost"]
    said = [r.getMessage() for r in caplog.records if "sensor right" in r.getMessage()]
    assert len(said) == 2
    assert "left out of the merged scan" in said[0] and "back in" in said[1]


def test_json_lists_every_sensor_with_its_own_results(recordings) -> None:
    import json

    from depthnav_daemon.sinks.json import message as jsonmsg

    both_ok = lambda r: all(s.status == "ok" for s in r.sensors)  # noqa: E731
    sink = UntilSink(both_ok, 1)
    run(
        _config(recordings, "daemon.sensor_max_age_s=600"),
        sink.stop,
        2000,
        sink_factory=lambda _s: sink,
    )
    last = next(r for r in reversed(sink.results) if both_ok(r))
    frame = Frame(0, 0.0, np.zeros((240, 424), np.uint16), WIDE)
    msg = json.loads(jsonmsg.dumps(jsonmsg.frame_message(frame, last, "0", 0.0)))
    assert [s["name"] for s in msg["sensors"]] == ["left", "right"]
    for s, state in zip(msg["sensors"], last.sensors, strict=True):
        assert s["status"] == "ok" and s["age_s"] >= 0
        assert len(s["scan"]["ranges"]) == state.result.scan.ranges.size
        assert s["pose"]["yaw_deg"] == state.result.mount.yaw_deg
    assert len(msg["scan"]["ranges"]) == last.scan.ranges.size  # the merged one on top
