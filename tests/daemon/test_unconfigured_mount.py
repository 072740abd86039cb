"""A mount nobody configured (issue 33 item 4): the daemon searches every plausible mount for the
floor, as ``depthnav calibrate`` does, and until the floor gives the mount every output says it is
unconfirmed and every range is unknown; then the output is normal. A configured mount is not
affected.

The reported case: a robot camera 1.27 m high pitched 73 deg down, no [mount]. The daemon's
default floor search (tilt up to 60 deg) never found the floor, the built-in 0.5 m / 0 deg stayed,
and the scan reported the floor as a wall at 0.98 m on 274 of 294 bins.
"""

from __future__ import annotations

import json
import logging
import math
import subprocess
import sys
import threading
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pytest

from depthnav_daemon.config.loader import build_config
from depthnav_daemon.daemon.loop import run
from depthnav_daemon.pipeline import Result, StageParams, process
from depthnav_daemon.pipeline.geometry import Mount
from depthnav_daemon.sim.synthetic import Box, KinectNoise, Scene, render
from depthnav_daemon.sinks.base import SinkContext
from depthnav_daemon.sinks.json import message as jsonmsg
from depthnav_daemon.sinks.mavlink.mavlink import MavlinkSink
from depthnav_daemon.sinks.mavlink.sectors import UNKNOWN
from depthnav_daemon.sinks.text import TextSink
from drivers.base import STANDARD_GRAVITY_MPS2, DeviceInfo, Frame
from drivers.formats.recording_writer import write_recording
from tests.pipeline.scenes import ASYM_640

ROOT = Path(__file__).resolve().parents[2]
STEEP = Mount(1.27, 73.0, 0.0)  # the robot camera of the issue
EMPTY = Scene()  # an empty floor: with the right mount no bin may hold an obstacle


def accel_of(m: Mount) -> tuple[float, float, float]:
    """A resting camera's accelerometer reading at mount ``m`` (README conventions: level reads
    (0, -g, 0); pitched down by t, (0, -g cos t, -g sin t); rolled by r, x = -g sin r)."""
    g, t, r = STANDARD_GRAVITY_MPS2, m.tilt_rad, m.roll_rad
    return (-g * math.sin(r) * math.cos(t), -g * math.cos(r) * math.cos(t), -g * math.sin(t))


@dataclass
class FloorCamera:
    """Renders ``scene`` from the camera's true mount with Kinect-like noise; the first ``blank``
    frames read nothing (a sensor warming up, a hand over the lens)."""

    mount: Mount
    frames: int = 30
    blank: int = 0
    scene: Scene = EMPTY
    accel: bool = False
    seq: int = 0
    rng: np.random.Generator = field(default_factory=lambda: np.random.default_rng(7))

    def open(self) -> DeviceInfo:
        return DeviceInfo("synthetic", None, "synthetic", ASYM_640)

    def frame(self, seq: int) -> Frame:
        depth = render(self.scene, ASYM_640, self.mount, KinectNoise(), self.rng).depth_mm
        if seq < self.blank:
            depth = np.zeros_like(depth)
        accel = accel_of(self.mount) if self.accel else None
        return Frame(seq, seq / 30.0, depth, ASYM_640, accel_mps2=accel)

    def read_frame(self, timeout_s: float = 1.0) -> Frame | None:
        if self.seq >= self.frames:
            return None
        self.seq += 1
        return self.frame(self.seq - 1)

    def close(self) -> None:
        pass


@dataclass
class Collect:
    name: str = "collect"
    results: list[tuple[Frame, Result]] = field(default_factory=list)

    def open(self, context: SinkContext) -> None:
        pass

    def write(self, frame: Frame, result: Result) -> None:
        self.results.append((frame, result))

    def close(self) -> None:
        pass


def run_camera(camera: FloorCamera, *sets: str) -> list[tuple[Frame, Result]]:
    sink = Collect()
    cfg = build_config([], list(sets), {"device": "synthetic"})
    report = run(
        cfg, threading.Event(), driver_factory=lambda _s: camera, sink_factory=lambda _s: sink
    )
    assert report.frames == camera.frames
    return sink.results


def first_known(results: list[tuple[Frame, Result]]) -> int:
    """Index of the first frame whose mount is trusted (len(results) if none)."""
    return next((i for i, (_f, r) in enumerate(results) if r.mount_trust.trusted), len(results))


def finite_share(result: Result) -> float:
    return float(np.isfinite(result.scan.ranges).mean())


def message(frame: Frame, result: Result) -> dict:
    return json.loads(jsonmsg.dumps(jsonmsg.frame_message(frame, result, "0", 1.0)))


def mavlink_sectors(sink: MavlinkSink, frame: Frame, result: Result) -> np.ndarray:
    sink.write(frame, result)
    assert sink._latest is not None
    return sink._latest[0].distances_cm


@pytest.mark.parametrize("blank", [0, 5])
def test_the_steep_robot_camera_is_found_and_its_floor_is_no_wall(blank: int) -> None:
    results = run_camera(FloorCamera(STEEP, blank=blank))
    k = first_known(results)
    # found on the first frame that shows the floor, and served from that frame on (its tables
    # are built on that frame, not on the worker while unknown ranges go out)
    assert k == blank
    mav = MavlinkSink("mavlink", udp=("127.0.0.1", 9), cliff=True)
    mav._thread = object()  # write() without open(): only what would be sent is checked
    text = TextSink()
    for frame, result in results[:k]:
        trust = result.mount_trust
        assert (trust.trusted, trust.dropoffs_trusted, trust.source) == (False, False, "default")
        assert np.isnan(result.scan.ranges).all() and np.isnan(result.cliff.scan.ranges).all()
        msg = message(frame, result)
        assert msg["scan"]["trusted"] is False and set(msg["scan"]["ranges"]) == {None}
        assert msg["mount"]["trusted"] is False and msg["cliff"]["trusted"] is False
        assert set(msg["cliff"]["scan"]["ranges"]) == {None}
        assert "unconfirmed" in msg["mount"]["note"] and "unconfirmed" in msg["warning"]
        assert "unconfirmed" in text.format(frame, result)
        assert (mavlink_sectors(mav, frame, result) == UNKNOWN).all()
    for frame, result in results[k:]:
        trust = result.mount_trust
        assert trust.trusted and trust.dropoffs_trusted and trust.floor == "confirmed"
        assert result.mount.height_m == pytest.approx(STEEP.height_m, abs=0.02)
        assert result.mount.tilt_deg == pytest.approx(STEEP.tilt_deg, abs=1.0)
        assert result.mount.roll_deg == pytest.approx(STEEP.roll_deg, abs=1.0)
        assert finite_share(result) <= 0.02  # the floor is no obstacle any more
        msg = message(frame, result)
        assert msg["scan"]["trusted"] is True and msg["mount"]["trusted"] is True
        assert msg["warning"] is None
        assert not (mavlink_sectors(mav, frame, result) < mav_max(result)).any()
    texts = [text for _sev, text in mav._texts]
    if k:
        assert texts == [
            "depthnav: mount unconfirmed, sectors unknown",
            "depthnav: mount confirmed by the floor",
        ]
    else:  # trusted from the first frame: nothing to say
        assert texts == []


def mav_max(result: Result) -> int:
    """The sectors' max_distance (cm): a sector below it reports an obstacle."""
    return round(result.scan.range_max * 100)


@pytest.mark.parametrize(
    "mount",
    [
        Mount(0.3, 5.0, 0.0),
        Mount(0.8, 40.0, 0.0),
        Mount(1.5, 80.0, 0.0),
        Mount(0.8, 40.0, 6.0),
        Mount(1.27, 73.0, -8.0),
        Mount(1.5, 80.0, 5.0),
        Mount(2.0, 60.0, -3.0),  # beyond the default prior's 1.5 m
        Mount(1.0, 25.0, -4.0),
    ],
    ids=str,
)
def test_other_unconfigured_mounts_are_found(mount: Mount) -> None:
    # (a mount far above a noisy floor is no example: at 2.5 m / 30 deg the Kinect-like noise 4-5
    # m away makes half the bins finite, configured or not)
    results = run_camera(FloorCamera(mount, frames=6, blank=2))
    assert first_known(results) == 2
    for _frame, result in results[2:]:
        assert result.mount_trust.source == "floor" and result.mount_trust.trusted
        m = result.mount
        assert m.height_m == pytest.approx(mount.height_m, abs=0.02)
        assert m.tilt_deg == pytest.approx(mount.tilt_deg, abs=1.0)
        assert m.roll_deg == pytest.approx(mount.roll_deg, abs=1.0)
        assert finite_share(result) <= 0.02


def test_obstacles_are_reported_once_the_mount_is_found() -> None:
    # the steep camera sees the floor from 0.3 to 1.1 m ahead: a 0.3 m box at 0.8 m
    box = Box(0.85, 0.0, 0.1, 0.3, 0.3)
    results = run_camera(FloorCamera(STEEP, frames=3, scene=Scene(boxes=(box,))))
    ranges = results[-1][1].scan.ranges
    hit = ranges[np.isfinite(ranges)]
    assert hit.size > 20 and np.all(np.abs(hit - 0.8) < 0.1)


def test_a_tilt_sensor_narrows_the_wide_search() -> None:
    """With an accelerometer the tilt is known but the height is not: the mount is unconfirmed
    until the floor gives the height (searched at any height, the sensor's tilt +-10 deg)."""
    results = run_camera(FloorCamera(STEEP, frames=4, blank=2, accel=True))
    for _frame, result in results[:2]:
        trust = result.mount_trust
        assert (trust.source, trust.trusted) == ("accel", False)
        assert result.mount.tilt_deg == pytest.approx(73.0, abs=0.5)  # the sensor's tilt...
        assert result.mount.height_m == 0.5  # ...over the built-in height
        assert np.isnan(result.scan.ranges).all()
        assert "tilt from the accel" in result.warning and "unconfirmed" in result.warning
    for _frame, result in results[2:]:
        assert result.mount_trust.trusted and result.mount_trust.source == "floor"
        assert result.mount.height_m == pytest.approx(1.27, abs=0.02)
        pose = result.pose
        assert pose is None or pose.ok


def test_without_a_floor_estimate_an_unconfigured_mount_stays_unknown(caplog) -> None:
    with caplog.at_level(logging.WARNING):
        results = run_camera(FloorCamera(STEEP, frames=3), "daemon.pose_every_frames=0")
    for _frame, result in results:
        assert result.pose is None and not result.mount_trust.trusted
        assert np.isnan(result.scan.ranges).all()
    said = [r.getMessage() for r in caplog.records if "floor estimate is off" in r.getMessage()]
    assert len(said) == 1 and "set [mount] or run depthnav calibrate" in said[0]


def test_the_search_runs_on_every_frame_only_while_the_mount_is_unknown() -> None:
    results = run_camera(FloorCamera(STEEP, frames=8, blank=3))
    ran = [r.pose is not None for _f, r in results]
    # every frame until the floor is found (frame 3), then every pose_every_frames (30)
    assert ran == [True] * 4 + [False] * 4


@pytest.mark.parametrize("pinned", [False, True])
def test_a_configured_mount_is_not_affected(pinned: bool) -> None:
    true = Mount(0.55, 15.0, 2.0)
    camera = FloorCamera(true, frames=4, scene=Scene(boxes=(Box(1.6, 0.3, 0.3, 0.3, 0.4),)))
    sets = ["mount.height_m=0.55", "mount.tilt_deg=15.0", "mount.roll_deg=2.0"]
    if pinned:
        sets.append("daemon.tilt_source='config'")
    results = run_camera(camera, *sets)
    assert [r.pose is not None for _f, r in results] == [True, False, False, False]
    params = StageParams(scan=build_config([], sets, {"device": "x"}).scan)
    for frame, result in results:
        assert result.mount_trust.trusted and result.mount_trust.dropoffs_trusted
        assert result.warning is None
        # the scan is exactly what the stages give with this mount
        same = process(frame, result.mount, params).scan.ranges
        np.testing.assert_array_equal(result.scan.ranges, same)
        assert np.isfinite(result.scan.ranges).any()  # the box
        assert message(frame, result)["scan"]["trusted"] is True


def test_a_steep_configured_mount_keeps_its_narrow_search() -> None:
    results = run_camera(FloorCamera(STEEP, frames=2), "mount.height_m=1.27", "mount.tilt_deg=73.0")
    pose = results[0][1].pose
    assert pose is not None and pose.ok and results[0][1].mount_trust.trusted
    assert results[-1][1].mount.tilt_deg == pytest.approx(73.0, abs=0.3)


def test_the_cli_on_a_recording_says_unconfirmed_until_the_floor_is_found(tmp_path: Path) -> None:
    camera = FloorCamera(STEEP, frames=12, blank=4)
    write_recording(tmp_path / "steep", (camera.frame(i) for i in range(camera.frames)))
    p = subprocess.run(
        [
            sys.executable,
            "-m",
            "depthnav_daemon",
            "run",
            "--device",
            f"replay:{tmp_path / 'steep'}?rate=max",
            "--sink",
            "stdout",
        ],
        capture_output=True,
        text=True,
        timeout=300,
        cwd=ROOT,
    )
    assert p.returncode == 0, p.stderr
    lines = [json.loads(line) for line in p.stdout.splitlines()]
    assert len(lines) == 12
    for msg in lines[:4]:
        assert msg["scan"]["trusted"] is False and msg["mount"]["trusted"] is False
        assert set(msg["scan"]["ranges"]) == {None}
        assert "unconfirmed" in msg["mount"]["note"] and "unconfirmed" in msg["warning"]
    for msg in lines[4:]:
        assert msg["scan"]["trusted"] is True and msg["mount"]["trusted"] is True
        assert msg["mount"]["source"] == "floor" and msg["pose"]["tilt_deg"] == pytest.approx(
            73.0, abs=1.0
        )
        ranges = jsonmsg.decode_ranges(msg["scan"]["ranges"])
        assert np.isfinite(ranges).mean() <= 0.02
    assert "unconfirmed" in p.stderr and "ranges are reported from this frame on" in p.stderr
