"""Nav2 that works: the cliff points carry z = ``cliff_z`` exactly (float32, base frame) in the
rosbag, ros2 and foxglove sinks, and the costmap snippets of README.md and docs/ros.md use only
keys Nav2's obstacle layer declares, with both height filters below the cliff points."""

from __future__ import annotations

import dataclasses
import re
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import yaml

from depthnav_daemon.errors import ConfigError
from depthnav_daemon.pipeline.geometry import Mount
from depthnav_daemon.sinks import create_sink
from depthnav_daemon.sinks.base import parse_sink_spec
from depthnav_daemon.sinks.ros.cdr import CdrEncoder
from depthnav_daemon.sinks.ros.messages import (
    CLIFF_Z_DEFAULT,
    MessageBuilder,
    RosNames,
    typestore,
)
from tests.sinks.conftest import make_pair

ROOT = Path(__file__).resolve().parents[2]

# The parameters nav2_costmap_2d::ObstacleLayer declares, as in Nav2 Jazzy
# (nav2_costmap_2d/plugins/obstacle_layer.cpp, ObstacleLayer::onInitialize; the same names in
# docs.nav2.org's "Obstacle Layer Parameters"). Layer level, besides "plugin" (the costmap's):
LAYER_KEYS = {
    "plugin",
    "enabled",
    "footprint_clearing_enabled",
    "min_obstacle_height",  # default 0.0: marking drops every point below it
    "max_obstacle_height",
    "combination_method",
    "observation_sources",
}
# per observation source
SOURCE_KEYS = {
    "topic",
    "sensor_frame",
    "observation_persistence",
    "expected_update_rate",
    "data_type",
    "min_obstacle_height",
    "max_obstacle_height",  # default 0.0: a source without it keeps nothing above the floor
    "inf_is_valid",
    "marking",
    "clearing",
    "obstacle_max_range",
    "obstacle_min_range",
    "raytrace_max_range",
    "raytrace_min_range",
}
OBSTACLE_LAYER = "nav2_costmap_2d::ObstacleLayer"
SNIPPETS = {  # file -> the heading of the section holding its Nav2 snippet
    "README.md": "## ROS and Nav2",
    "docs/ros.md": "## Write a bag and play it into Nav2",
}
F32_DEFAULT = np.float32(CLIFF_Z_DEFAULT)


def yaml_blocks(path: str, heading: str) -> list[Any]:
    """The fenced ```yaml blocks of one section (up to the next heading of its level), parsed."""
    text = (ROOT / path).read_text(encoding="utf-8")
    assert heading in text, f"{path} has no {heading!r}"
    section = text.split(heading, 1)[1]
    level = heading.split(" ", 1)[0]
    section = re.split(rf"^{level} ", section, flags=re.M)[0]
    return [yaml.safe_load(b) for b in re.findall(r"^```yaml\n(.*?)^```", section, re.M | re.S)]


def obstacle_layers(tree: Any) -> list[dict[str, Any]]:
    """Every mapping in ``tree`` whose plugin is Nav2's obstacle layer."""
    if isinstance(tree, dict):
        found = [tree] if tree.get("plugin") == OBSTACLE_LAYER else []
        return found + [x for v in tree.values() for x in obstacle_layers(v)]
    return []


@pytest.mark.parametrize("path", SNIPPETS)
def test_snippet_uses_nav2_keys_and_keeps_the_cliff_points(path: str) -> None:
    layers = [x for block in yaml_blocks(path, SNIPPETS[path]) for x in obstacle_layers(block)]
    assert len(layers) == 1, f"{path}: one obstacle layer in the Nav2 section's yaml"
    layer = layers[0]
    names = layer["observation_sources"].split()
    assert set(layer) - set(names) <= LAYER_KEYS, f"{path}: not Nav2 keys"
    # the layer-level filter (default 0.0) must be set, below the cliff points
    assert layer["min_obstacle_height"] < CLIFF_Z_DEFAULT
    sources = {name: layer[name] for name in names}
    for name, source in sources.items():
        assert set(source) <= SOURCE_KEYS, f"{path}: {name} has keys Nav2 does not read"
    cliff = next(s for s in sources.values() if s["topic"] == "/cliff/points")
    assert cliff["data_type"] == "PointCloud2" and cliff.get("marking", True)
    assert cliff["min_obstacle_height"] < CLIFF_Z_DEFAULT < cliff["max_obstacle_height"]
    assert not cliff.get("clearing", False)
    scan = next(s for s in sources.values() if s["topic"] == "/scan")
    assert scan["data_type"] == "LaserScan" and scan["inf_is_valid"] and scan["clearing"]
    assert scan["max_obstacle_height"] > 0  # the per-source default 0.0 would drop the scan
    assert scan["raytrace_max_range"] >= scan["obstacle_max_range"]


def _names(option: str = "") -> RosNames:
    return RosNames.from_spec(parse_sink_spec(f"rosbag:x.mcap{option}"))


def _cloud_z(msg: Any) -> np.ndarray:
    xyz = np.frombuffer(bytes(msg.data), dtype="<f4").reshape(-1, 3)
    assert len(xyz) > 2 and np.isfinite(xyz).all()
    return xyz[:, 2]


# heights where float32(-h) + h is not 0 (the old z after the scan frame's transform)
MOUNTS = [Mount(0.5, 12.0, 1.5), Mount(0.37, 20.0, 0.0), Mount(0.83, 35.0, -2.0)]


@pytest.mark.parametrize("ros1", [False, True], ids=["ros2", "ros1"])
@pytest.mark.parametrize(("option", "z"), [("", CLIFF_Z_DEFAULT), ("?cliff_z=-0.2", -0.2)])
def test_cliff_points_lie_exactly_at_cliff_z_in_the_base_frame(
    ros1: bool, option: str, z: float
) -> None:
    builder = MessageBuilder(typestore(ros1), _names(option))
    for mount in MOUNTS:
        _, result = make_pair(0, mount)
        _, messages = builder.messages(None, result, t_ns=1)  # type: ignore[arg-type]
        cloud = dict(messages)["/cliff/points"]
        assert cloud.header.frame_id == "base_link"  # no transform adds the height back
        assert np.all(_cloud_z(cloud) == np.float32(z))


def test_ros2_cdr_carries_cliff_z_exactly() -> None:
    """The live sink's template CDR, decoded: the same z as the bag's messages."""
    for option, z in (("", F32_DEFAULT), ("?cliff_z=-0.123", np.float32(-0.123))):
        builder = MessageBuilder(typestore(ros1=False), _names(option))
        encoder = CdrEncoder(builder)
        for seq, mount in enumerate(MOUNTS):
            frame, result = make_pair(seq, mount)
            data = dict(encoder.encode(frame, result, 1_700_000_000 * 10**9))["/cliff/points"]
            cloud = builder.store.deserialize_cdr(bytes(data), "sensor_msgs/msg/PointCloud2")
            assert cloud.header.frame_id == "base_link"
            assert np.all(_cloud_z(cloud) == z)
        assert encoder._points is not None  # the template, not the fallback


def _rosbag_clouds(path: Path) -> list[Any]:
    from rosbags.highlevel import AnyReader

    with AnyReader([path]) as reader:
        conns = [c for c in reader.connections if c.topic == "/cliff/points"]
        return [reader.deserialize(raw, c.msgtype) for c, _, raw in reader.messages(conns)]


@pytest.mark.parametrize(("option", "z"), [("", F32_DEFAULT), ("?cliff_z=-0.3", np.float32(-0.3))])
@pytest.mark.parametrize("suffix", [".mcap", ".bag"])
def test_written_bag_carries_cliff_z(tmp_path: Path, context, option, z, suffix) -> None:
    path = tmp_path / f"out{suffix}"
    sink = create_sink(f"rosbag:{path}{option}")
    sink.open(context)
    for seq, mount in enumerate(MOUNTS):
        sink.write(*make_pair(seq, mount))
    sink.close()
    clouds = _rosbag_clouds(path)
    assert len(clouds) == len(MOUNTS)
    for cloud in clouds:
        assert cloud.header.frame_id == "base_link" and np.all(_cloud_z(cloud) == z)


def _decode(msg: Any) -> Any:
    """A foxglove-sdk message decoded with its own protobuf schema (an independent reader)."""
    from google.protobuf import descriptor_pb2, descriptor_pool, message_factory

    schema = msg.get_schema()
    pool = descriptor_pool.DescriptorPool()
    pending = list(descriptor_pb2.FileDescriptorSet.FromString(bytes(schema.data)).file)
    while pending:  # add each file once its dependencies are in
        done = [f for f in pending if all(_in(pool, d) for d in f.dependency)]
        assert done, "unresolvable schema"
        for f in done:
            pool.Add(f)
            pending.remove(f)
    cls = message_factory.GetMessageClass(pool.FindMessageTypeByName(schema.name))
    return cls.FromString(bytes(msg.encode()))


def _in(pool: Any, name: str) -> bool:
    try:
        pool.FindFileByName(name)
    except KeyError:
        return False
    return True


def test_foxglove_cloud_carries_cliff_z() -> None:
    pytest.importorskip("foxglove")
    from foxglove import messages as m

    for option, z in (("", F32_DEFAULT), ("?cliff_z=-0.07", np.float32(-0.07))):
        sink = create_sink(f"foxglove:x.mcap{option}")  # no I/O until open
        for seq, mount in enumerate(MOUNTS):
            _, result = make_pair(seq, mount)
            cloud = _decode(sink._points(m, m.Timestamp(1, 0), result))  # type: ignore[attr-defined]
            assert cloud.frame_id == "base_link"
            xyz = np.frombuffer(cloud.data, dtype="<f4").reshape(-1, 3)
            assert len(xyz) > 2 and np.all(xyz[:, 2] == z)


def test_an_empty_cloud_is_in_the_base_frame_too() -> None:
    """No drop-off seen: an empty cloud in the same frame (Nav2 clears its observation); no
    cliff stage: no cloud at all."""
    builder = MessageBuilder(typestore(ros1=False), _names())
    _, result = make_pair(0)
    assert result.cliff is not None
    empty = dataclasses.replace(result.cliff, points_m=np.zeros((0, 2), np.float32))
    _, messages = builder.messages(None, dataclasses.replace(result, cliff=empty), t_ns=1)  # type: ignore[arg-type]
    cloud = dict(messages)["/cliff/points"]
    assert cloud.width == 0 and cloud.header.frame_id == "base_link"
    _, messages = builder.messages(None, make_pair(0, cliff=False)[1], t_ns=1)  # type: ignore[arg-type]
    assert "/cliff/points" not in dict(messages)


@pytest.mark.parametrize("scheme", ["rosbag:x.mcap", "rosbag:x.bag", "ros2", "foxglove"])
@pytest.mark.parametrize("value", ["0", "0.05", "-1.5", "abc", "nan", ""])
def test_bad_cliff_z_is_one_clear_line(scheme: str, value: str) -> None:
    with pytest.raises(ConfigError) as info:
        create_sink(f"{scheme}?cliff_z={value}")
    text = str(info.value)
    assert "\n" not in text and "cliff_z" in text and "-1..-0.001" in text
