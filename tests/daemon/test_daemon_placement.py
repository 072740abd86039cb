"""The daemon keeps the configured placement ([mount] x_m, y_m, yaw_deg) while the floor estimate
and the tilt sensor move height, tilt and roll."""

from __future__ import annotations

import threading

import pytest

from depthnav_daemon.config.loader import build_config
from depthnav_daemon.daemon.loop import run
from depthnav_daemon.daemon.mount_tracker import MountTracker, TrackerParams
from depthnav_daemon.pipeline.geometry import Mount
from tests.daemon.test_loop import SPEC, CollectSink


def test_floor_estimate_keeps_the_configured_placement() -> None:
    sink = CollectSink()
    cfg = build_config(
        [],
        ["daemon.tilt_source=floor", "daemon.pose_every_frames=2", "mount.yaw_deg=-30.0"],
        {"device": SPEC, "mount": {"height_m": 1.0, "x_m": 0.25, "y_m": -0.1}},
    )
    run(cfg, threading.Event(), max_frames=3, sink_factory=lambda _s: sink)
    last = sink.results[-1]
    assert last.mount_source == "floor"
    assert last.mount.height_m == pytest.approx(0.55, abs=0.01)  # from the floor
    assert (last.mount.x_m, last.mount.y_m, last.mount.yaw_deg) == (0.25, -0.1, -30.0)
    # the outputs are in the base frame: the scan turned by -30 deg from the sensor's
    assert last.scan.angle_min < last.sensor_scan.angle_min - 0.3


def test_tracker_keeps_placement_through_tilt_sensor_and_floor() -> None:
    t = MountTracker(Mount(0.5, 0.0, 0.0, 0.3, 0.2, 90.0), TrackerParams(smoothing=0.5))
    t.from_tilt_sensor(12.0, 1.0, "accel")
    assert (t.mount.tilt_deg, t.mount.x_m, t.mount.y_m, t.mount.yaw_deg) == (12.0, 0.3, 0.2, 90.0)
    t.from_floor(0.6, 14.0, 0.0)
    assert t.mount == Mount(0.6, 14.0, 0.0, 0.3, 0.2, 90.0)
    t.from_floor(0.62, 14.5, 0.0)
    assert (t.mount.x_m, t.mount.y_m, t.mount.yaw_deg) == (0.3, 0.2, 90.0)
