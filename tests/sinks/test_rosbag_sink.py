"""``rosbag`` sink: one run writes a ROS 2 .mcap, a ROS 1 .bag and the stdout JSON; every reader
we can find (rosbags, mcap-ros2-support, Debian's own ROS 1 rosbag) gets the same scans back."""

from __future__ import annotations

import json
import math
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest

from depthnav_daemon.errors import ConfigError, SinkError
from depthnav_daemon.pipeline.geometry import Mount
from depthnav_daemon.sinks import create_sink
from tests.drivers.driverkit import skip_without
from tests.faults.kit import depthnav, json_lines
from tests.faults.test_run_faults import small_disk
from tests.sinks.roskit import (
    has_all_codes,
    optical_axis_in_base,
    rotate,
    same_ranges,
    special_recording,
)


@pytest.fixture(scope="module")
def run(tmp_path_factory) -> tuple[Path, list[dict]]:
    """One CLI run with three sinks: rosbag .mcap, rosbag .bag (bz2), stdout."""
    tmp = tmp_path_factory.mktemp("rosbag_sink")
    rec = special_recording(tmp / "rec")
    p = depthnav(
        "run",
        "--device", f"replay:{rec}?rate=max",
        "--sink", f"rosbag:{tmp / 'out.mcap'}",
        "--sink", f"rosbag:{tmp / 'out.bag'}?compression=bz2",
        "--sink", "stdout",
    )  # fmt: skip
    assert p.returncode == 0, p.stderr
    msgs = json_lines(p.stdout)
    assert len(msgs) == 6 and all(has_all_codes(m["scan"]["ranges"]) for m in msgs)
    assert all(m["cliff"]["points_m"] for m in msgs)  # the step down is seen
    assert not list(tmp.glob("*.partial*"))
    return tmp, msgs


def rosbags_messages(path: Path) -> dict[str, list]:
    from rosbags.highlevel import AnyReader

    out: dict[str, list] = {}
    with AnyReader([path]) as reader:
        for conn, _, raw in reader.messages():
            out.setdefault(conn.topic, []).append(reader.deserialize(raw, conn.msgtype))
    return out


def check_messages(got: dict[str, list], msgs: list[dict]) -> None:
    """Scans, cliff scans, cliff points, tf and pose against the JSON of the same run."""
    assert len(got["/scan"]) == len(msgs) == len(got["/cliff/scan"]) == len(got["/tf"])
    for m, scan, cliff, cloud, tf, pose in zip(
        msgs,
        got["/scan"],
        got["/cliff/scan"],
        got["/cliff/points"],
        got["/tf"],
        got["/depth_sensor_pose"],
        strict=True,
    ):
        same_ranges(scan.ranges, m["scan"]["ranges"])
        same_ranges(cliff.ranges, m["cliff"]["scan"]["ranges"])
        assert scan.header.frame_id == "depthnav_scan"
        assert scan.angle_min == pytest.approx(m["scan"]["angle_min"], abs=1e-6)
        stamp = scan.header.stamp.sec + scan.header.stamp.nanosec * 1e-9
        assert stamp == pytest.approx(m["t_s"], abs=1e-6)
        xyz = np.frombuffer(bytes(cloud.data), dtype="<f4").reshape(-1, 3)
        assert [f.name for f in cloud.fields] == ["x", "y", "z"] and cloud.point_step == 12
        np.testing.assert_allclose(xyz[:, :2], m["cliff"]["points_m"], atol=0.0006)
        # in base_link, cliff_z (-0.05) below the floor exactly: no rounding decides for Nav2
        assert cloud.header.frame_id == "base_link"
        assert np.all(xyz[:, 2] == np.float32(-0.05))
        height, tilt = m["pose"]["height_m"], m["pose"]["tilt_deg"]
        level, optical = tf.transforms
        assert (level.header.frame_id, level.child_frame_id) == ("base_link", "depthnav_scan")
        assert optical.child_frame_id == "depthnav_optical"
        for t in (level, optical):
            assert t.transform.translation.z == pytest.approx(height, abs=0.0006)
        r = optical.transform.rotation
        axis = rotate((r.x, r.y, r.z, r.w), (0.0, 0.0, 1.0))  # the optical z axis, in base_link
        np.testing.assert_allclose(axis, optical_axis_in_base(tilt), atol=1e-4)
        assert pose.pose.position.z == pytest.approx(height, abs=0.0006)
        q = pose.pose.orientation
        np.testing.assert_allclose(
            rotate((q.x, q.y, q.z, q.w), (1.0, 0.0, 0.0)), optical_axis_in_base(tilt), atol=1e-4
        )


def test_mcap_read_back_with_rosbags(run) -> None:
    tmp, msgs = run
    check_messages(rosbags_messages(tmp / "out.mcap"), msgs)


def test_mcap_read_back_with_mcap_ros2_support(run) -> None:
    """An independent decoder: it parses the ros2msg schemas we wrote and decodes the CDR."""
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory

    tmp, msgs = run
    got: dict[str, list] = {}
    with open(tmp / "out.mcap", "rb") as fh:
        reader = make_reader(fh, decoder_factories=[DecoderFactory()])
        assert reader.get_header().profile == "ros2"
        for schema, channel, _, decoded in reader.iter_decoded_messages():
            assert schema is not None and schema.encoding == "ros2msg"
            assert channel.message_encoding == "cdr"
            got.setdefault(channel.topic, []).append(decoded)
    check_messages(got, msgs)


def test_ros1_bag_read_back_with_rosbags(run) -> None:
    tmp, msgs = run
    check_messages(rosbags_messages(tmp / "out.bag"), msgs)


DEBIAN_READER = r"""
import json, sys, rosbag
out = []
with rosbag.Bag(sys.argv[1]) as bag:
    for topic, msg, t in bag.read_messages():
        if topic == "/scan":
            out.append({"ranges": list(msg.ranges), "frame": msg.header.frame_id})
        elif topic == "/cliff/points":
            out[-1]["cloud"] = [msg.width, [f.name for f in msg.fields]]
        elif topic == "/tf":
            out[-1]["tf"] = [t.child_frame_id for t in msg.transforms]
print(json.dumps(out))
"""


def test_ros1_bag_passes_debian_ros1_tools(run) -> None:
    """Debian's python3-rosbag (ROS 1's own code, system Python): rosbag info, every message."""
    tool = shutil.which("rosbag")
    ok = tool is not None and Path("/usr/bin/python3").exists()
    if ok:
        probe = subprocess.run(
            ["/usr/bin/python3", "-c", "import rosbag"], capture_output=True, check=False
        )
        ok = probe.returncode == 0
    skip_without(not ok, "python3-rosbag")
    tmp, msgs = run
    info = subprocess.run(
        [tool, "info", str(tmp / "out.bag")], capture_output=True, text=True, check=False
    )
    assert info.returncode == 0, info.stderr
    assert "compression:  bz2" in info.stdout
    for line in ("/scan ", "/cliff/points", "/tf ", "/depth_sensor_pose"):
        assert line in info.stdout
    assert "tf2_msgs/TFMessage        [94810edda583a504dfda3829e70d7eec]" in info.stdout
    p = subprocess.run(
        ["/usr/bin/python3", "-c", DEBIAN_READER, str(tmp / "out.bag")],
        capture_output=True,
        text=True,
        timeout=120,
        check=False,
    )
    assert p.returncode == 0, p.stderr
    scans = json.loads(p.stdout)
    assert len(scans) == len(msgs)
    for scan, m in zip(scans, msgs, strict=True):
        same_ranges(scan["ranges"], m["scan"]["ranges"])  # NaN/Infinity: json reads both
        assert scan["frame"] == "depthnav_scan"
        assert scan["cloud"] == [len(m["cliff"]["points_m"]), ["x", "y", "z"]]
        assert scan["tf"] == ["depthnav_scan", "depthnav_optical"]


@pytest.mark.parametrize("lens", ["", "&k1=-0.2&k2=0.05&p1=0.001&p2=-0.002&k3=0.01"])
def test_image_option_replays_the_run(tmp_path: Path, lens: str) -> None:
    """``image=1`` writes the depth and its CameraInfo (with the lens coefficients in D):
    ``replay:`` gives the frames back."""
    import drivers

    rec = special_recording(tmp_path / "rec", n=3)
    out = tmp_path / "names.mcap"
    spec = f"rosbag:{out}?image=1&base_frame=base_footprint&scan_topic=/depth/scan&tf=0"
    p = depthnav("run", "--device", f"replay:{rec}?rate=max{lens}", "--sink", spec)
    assert p.returncode == 0, p.stderr
    got = rosbags_messages(out)
    assert "/tf" not in got and len(got["/depth/scan"]) == 3
    assert got["/depth_sensor_pose"][0].header.frame_id == "base_footprint"
    with drivers.opened(drivers.create_driver(f"replay:{rec}?rate=max{lens}")) as a:
        with drivers.opened(drivers.create_driver(f"replay:{out}?rate=max")) as b:
            for x, y in zip(drivers.iter_frames(a), drivers.iter_frames(b), strict=True):
                np.testing.assert_array_equal(x.depth_mm, y.depth_mm)
                assert x.intrinsics == y.intrinsics
                assert x.intrinsics.has_distortion == bool(lens)
                assert x.timestamp_s == pytest.approx(y.timestamp_s, abs=1e-6)


@pytest.mark.parametrize("name", ["full.mcap", "full.bag"])
def test_full_disk_leaves_a_readable_bag(tmp_path: Path, name: str) -> None:
    rec = special_recording(tmp_path / "rec", n=40, size=(320, 240))
    with small_disk(tmp_path, "2m") as (disk, preexec):
        bag = disk / name
        p = depthnav(
            "run",
            "--device", f"replay:{rec}?rate=max",
            "--sink", f"rosbag:{bag}?image=1&compression=none",
            "--sink", "stdout",
            preexec_fn=preexec,
        )  # fmt: skip
        assert p.returncode == 0, p.stderr  # stdout went on without the bag
        msgs = json_lines(p.stdout)
        assert len(msgs) == 40
        assert "Traceback" not in p.stderr
        (line,) = [x for x in p.stderr.splitlines() if "ERROR" in x]
        assert f"writing {bag} failed" in line and "keeps what was written" in line
        assert not list(disk.glob("*.partial*"))
        got = rosbags_messages(bag)
        kept = len(got["/scan"])
        assert 1 <= kept < 40
        for scan, m in zip(got["/scan"], msgs[:kept], strict=True):
            same_ranges(scan.ranges, m["scan"]["ranges"])


def test_bad_specs_say_one_line(tmp_path: Path) -> None:
    for spec, words in (
        (f"rosbag:{tmp_path / 'x.db3'}", ".mcap (ROS 2) or .bag (ROS 1)"),
        (f"rosbag:{tmp_path / 'x.bag'}?compression=lz4", "none or bz2"),
        (f"rosbag:{tmp_path / 'x.mcap'}?compression=bz2", "zstd or none"),
        (f"rosbag:{tmp_path / 'x.mcap'}?topic=/a", "unknown option 'topic'"),
    ):
        with pytest.raises(ConfigError) as info:
            create_sink(spec)
        assert words in str(info.value)
    (tmp_path / "busy.bag.partial").write_bytes(b"another run's")
    with pytest.raises(SinkError, match=r"busy\.bag\.partial exists"):
        create_sink(f"rosbag:{tmp_path / 'busy.bag'}").open(None)  # type: ignore[arg-type]
    assert (tmp_path / "busy.bag.partial").read_bytes() == b"another run's"
    assert not (tmp_path / "busy.bag.partial.reserve").exists()
    (tmp_path / "there.mcap").write_bytes(b"mine")
    p = depthnav(
        "run", "--device", f"replay:{special_recording(tmp_path / 'r', n=1)}?rate=max",
        "--sink", f"rosbag:{tmp_path / 'there.mcap'}", "--sink", "null",
    )  # fmt: skip
    assert p.returncode == 0, p.stderr
    (line,) = [x for x in p.stderr.splitlines() if "ERROR" in x]
    assert "exists; not overwriting" in line and "Traceback" not in p.stderr
    assert (tmp_path / "there.mcap").read_bytes() == b"mine"


@pytest.mark.parametrize("ros1", [True, False])
def test_tf_and_pose_place_the_sensor_on_the_robot(ros1: bool) -> None:
    # asymmetric placement: 0.2 m forward, 0.1 m right, turned 30 deg left, 20 deg down, 5 deg
    # roll. The optical frame sits where the sensor is; the scan frame (whose ranges are from
    # the base origin) stays above the base origin with the base's axes
    from depthnav_daemon.sinks.ros.messages import NAME_OPTIONS, MessageBuilder, RosNames, typestore

    mount = Mount(0.6, 20.0, 5.0, x_m=0.2, y_m=-0.1, yaw_deg=30.0)
    builder = MessageBuilder(typestore(ros1=ros1), RosNames(dict(NAME_OPTIONS)))
    level, optical = builder.transforms(mount, 0).transforms
    lt, ot = level.transform, optical.transform
    assert (lt.translation.x, lt.translation.y, lt.translation.z) == (0.0, 0.0, 0.6)
    assert (lt.rotation.x, lt.rotation.y, lt.rotation.z, lt.rotation.w) == (0.0, 0.0, 0.0, 1.0)
    assert (ot.translation.x, ot.translation.y, ot.translation.z) == (0.2, -0.1, 0.6)
    r = ot.rotation
    axis = rotate((r.x, r.y, r.z, r.w), (0.0, 0.0, 1.0))  # the optical axis, in base_link
    yaw, tilt = math.radians(30.0), math.radians(20.0)
    expected = [math.cos(tilt) * math.cos(yaw), math.cos(tilt) * math.sin(yaw), -math.sin(tilt)]
    np.testing.assert_allclose(axis, expected, atol=1e-9)
    # the image's right (optical x) tips down on the right with positive roll (left side up)
    right = rotate((r.x, r.y, r.z, r.w), (1.0, 0.0, 0.0))
    assert right[2] < 0 and right[1] < 0
    pose = builder.pose(mount, 0).pose
    assert (pose.position.x, pose.position.y, pose.position.z) == (0.2, -0.1, 0.6)
    q = pose.orientation
    np.testing.assert_allclose(rotate((q.x, q.y, q.z, q.w), (1.0, 0.0, 0.0)), expected, atol=1e-9)
