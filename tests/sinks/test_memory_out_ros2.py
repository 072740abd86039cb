"""The obstacle memory on live ROS 2 topics: a Cyclone DDS subscriber in another process that
learns every type from discovery (tests/sinks/ros2_listener.py) sees ``/memory/grid`` as
``nav_msgs/OccupancyGrid``, ``/memory/scan``, ``/memory/cliff/points`` and odom -> base_link on
``/tf`` while depthnav replays a drive with odometry (DDS on 127.0.0.1 only)."""

from __future__ import annotations

import math
import sys
from pathlib import Path

import numpy as np
import pytest

from tests.sinks.ros2kit import free_domain, require_cyclonedds
from tests.sinks.test_memory_out_kit import drive_recording
from tests.sinks.test_ros2_sink import LISTENER, WAIT_S, live_run

TOPICS = {  # DDS topic -> DDS type name
    "rt/memory/grid": "nav_msgs::msg::dds_::OccupancyGrid_",
    "rt/memory/scan": "sensor_msgs::msg::dds_::LaserScan_",
    "rt/memory/cliff/points": "sensor_msgs::msg::dds_::PointCloud2_",
    "rt/tf": "tf2_msgs::msg::dds_::TFMessage_",
}


def test_a_discovery_only_subscriber_gets_the_memory(tmp_path: Path) -> None:
    require_cyclonedds()
    domain = free_domain()
    got, msgs, err = live_run(
        tmp_path,
        [sys.executable, str(LISTENER), str(domain), "4", str(WAIT_S), *TOPICS],
        f"ros2:?domain={domain}&grid_rate=5",
        drive_recording(tmp_path / "drive"),
    )
    assert "publishing /memory/grid" in err
    endpoints = {e["topic"]: e for e in got if e.get("event") == "endpoint"}
    assert {t: e["type"] for t, e in endpoints.items()} == TOPICS
    samples: dict[str, list] = {}
    for s in (x for x in got if x.get("event") == "sample"):
        samples.setdefault(s["topic"], []).append(s["data"])
    for grid in samples["rt/memory/grid"]:
        info = grid["info"]
        assert grid["header"]["frame_id"] == "odom"
        assert (info["width"], info["height"]) == (160, 160)
        assert info["resolution"] == pytest.approx(0.05)
        assert grid["data"] == {"bytes": 160 * 160}  # the listener gives long byte arrays' size
    for scan in samples["rt/memory/scan"]:
        r = np.asarray(scan["ranges"], dtype=np.float64)
        assert r.size == 360 and np.isnan(r).any() and np.isfinite(r).any()
        assert scan["angle_min"] == pytest.approx(-math.pi)
    for cloud in samples["rt/memory/cliff/points"]:
        assert cloud["header"]["frame_id"] == "base_link" and cloud["point_step"] == 12
    frames = {
        (t["header"]["frame_id"], t["child_frame_id"])
        for tf in samples["rt/tf"]
        for t in tf["transforms"]
    }
    assert ("odom", "base_link") in frames
    odoms = {(m["memory"]["odom"]["x_m"], m["memory"]["odom"]["y_m"]) for m in msgs}
    for tf in samples["rt/tf"]:
        (first,) = tf["transforms"][:1]
        if first["header"]["frame_id"] == "odom":
            tr = first["transform"]["translation"]
            assert any(math.hypot(tr["x"] - x, tr["y"] - y) < 1e-3 for x, y in odoms)
