"""``depthnav replay`` as a user runs it: the path's own ``?options`` kept beside the flags, a
looped epoch-stamped bag into the ROS and Foxglove sinks, and stamps a ROS time cannot hold."""

from __future__ import annotations

import dataclasses
import itertools
from pathlib import Path

import pytest

from drivers.base import KINECT_V1
from drivers.formats.recording_writer import write_recording
from tests.drivers.bagkit import DEPTH_TOPIC, T0_S, BagSpec, write_bag
from tests.drivers.driverkit import ramp_frames
from tests.faults.kit import depthnav, json_lines, one_error_line

INTR = KINECT_V1.scaled(160, 120)
FRAMES = 3  # in the bag, 30 Hz from T0_S (UNIX time)


@pytest.fixture(scope="module")
def bag(tmp_path_factory) -> Path:
    """A ROS 1 bag with a second depth topic beside /camera/depth/image_raw: ?topic= is needed."""
    tmp = tmp_path_factory.mktemp("replay_command")
    spec = BagSpec("ros1", extra_images={"/cam2/depth/image": "16UC1"})
    return write_bag(tmp / "b.bag", ramp_frames(FRAMES, INTR), spec)


def test_replay_keeps_the_paths_own_topic(bag: Path) -> None:
    p = depthnav("replay", f"{bag}?topic={DEPTH_TOPIC}", "--rate", "max", "--sink", "stdout")
    assert p.returncode == 0, p.stderr
    msgs = json_lines(p.stdout)
    assert len(msgs) == FRAMES
    assert [m["t_s"] for m in msgs] == pytest.approx([T0_S + i / 30 for i in range(FRAMES)])


def test_a_flag_and_the_same_option_in_the_path(bag: Path) -> None:
    """Disagreeing: a usage error naming both (exit 2); agreeing: fine."""
    path = f"{bag}?topic={DEPTH_TOPIC}&rate=realtime"
    p = depthnav("replay", path, "--rate", "max", "--sink", "null")
    assert p.returncode == 2, p.stderr
    line = one_error_line(p.stderr)
    assert "--rate max and rate=realtime" in line and "disagree" in line
    assert "depthnav: hint: give rate once" in p.stderr
    p = depthnav("replay", f"{bag}?topic={DEPTH_TOPIC}&loop=0", "--loop", "--sink", "null")
    assert p.returncode == 2 and "--loop and loop=0" in one_error_line(p.stderr)
    p = depthnav(
        "replay", f"{bag}?topic={DEPTH_TOPIC}&loop=yes", "--loop", "--max-frames", "4",
        "--sink", "stdout",
    )  # fmt: skip
    assert p.returncode == 0, p.stderr
    assert len(json_lines(p.stdout)) == 4  # looped, paced at the default max


def mcap_log_times(path: Path, topic: str) -> list[int]:
    from mcap.reader import make_reader

    with open(path, "rb") as fh:
        return [msg.log_time for _, _, msg in make_reader(fh).iter_messages(topics=[topic])]


def test_a_looped_epoch_bag_into_rosbag_and_foxglove(bag: Path, tmp_path: Path) -> None:
    """8 frames of a 3-frame bag stamped in UNIX time: 8 scans in each output, stamps strictly
    increasing, 1/30 s apart, near the bag's own epoch (the loop once doubled them)."""
    from rosbags.highlevel import AnyReader

    ros, fox = tmp_path / "out.mcap", tmp_path / "fox.mcap"
    p = depthnav(
        "replay", f"{bag}?topic={DEPTH_TOPIC}", "--loop", "--max-frames", "8",
        "--sink", f"rosbag:{ros}", "--sink", f"foxglove:{fox}", "--sink", "stdout",
    )  # fmt: skip
    assert p.returncode == 0, p.stderr
    assert "ERROR" not in p.stderr, p.stderr
    assert len(json_lines(p.stdout)) == 8
    t0_ns, period_ns = T0_S * 10**9, 10**9 / 30
    with AnyReader([ros]) as reader:
        conns = [c for c in reader.connections if c.topic == "/scan"]
        headers = [
            reader.deserialize(raw, c.msgtype).header.stamp
            for c, _, raw in reader.messages(connections=conns)
        ]
    stamps = {
        "rosbag": [s.sec * 10**9 + s.nanosec for s in headers],
        "foxglove": mcap_log_times(fox, "/scan"),
    }
    for name, got in stamps.items():
        assert len(got) == 8, name
        assert all(b > a for a, b in itertools.pairwise(got)), (name, got)
        for k, t_ns in enumerate(got):
            assert abs(t_ns - (t0_ns + k * period_ns)) < 2_000, (name, k, t_ns)


@pytest.mark.parametrize(
    ("sink", "what"),
    [
        ("rosbag:out.mcap", "a ROS 2 builtin_interfaces/Time (int32 sec)"),
        ("rosbag:out.bag", "a ROS 1 time as rosbags writes it (int32 sec)"),
        ("foxglove:fox.mcap", "a foxglove Timestamp"),
    ],
)
def test_a_stamp_past_the_message_time_is_one_sink_error(
    tmp_path: Path, sink: str, what: str
) -> None:
    """Frames stamped past what the sink's time type holds: that sink is dropped with one line
    and a hint (no struct.error), the others go on."""
    t_s = 3e9 if sink.startswith("rosbag") else 5e9  # foxglove's sec is uint32
    frames = [dataclasses.replace(f, timestamp_s=t_s + f.timestamp_s) for f in ramp_frames(2, INTR)]
    write_recording(tmp_path / "r", frames)
    p = depthnav(
        "replay", str(tmp_path / "r"), "--sink", sink.replace(":", f":{tmp_path}/"),
        "--sink", "stdout",
    )  # fmt: skip
    assert p.returncode == 0, p.stderr
    assert len(json_lines(p.stdout)) == 2
    assert "Traceback" not in p.stderr and "struct.error" not in p.stderr
    (line,) = [x for x in p.stderr.splitlines() if "ERROR" in x]
    assert f"frame time {t_s:.3f} s is past what {what} holds" in line, line
    assert "dropped, the others go on (the source's timestamps" in line
