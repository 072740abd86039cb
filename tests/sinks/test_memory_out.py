"""The obstacle memory out of the ``rosbag`` and ``foxglove`` sinks (issue 32 item 1): a drive with
odometry past two boxes toward a step down, written by the CLI to a ROS 2 .mcap, a ROS 1 .bag and
a Foxglove .mcap beside the stdout JSON, read back with rosbags, Debian's ROS 1 tools and the
Foxglove schemas; a Foxglove WebSocket client subscribes to the live grid. Occupied cells are
checked against the scene's geometry (tests/sinks/test_memory_out_kit.py), the memory scan and
the pose against the JSON of the same run."""

from __future__ import annotations

import json
import math
import re
import shutil
import subprocess
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from depthnav_daemon.errors import ConfigError
from depthnav_daemon.sinks import create_sink
from tests.drivers.driverkit import skip_without
from tests.faults.kit import depthnav, free_tcp_port, json_lines, start
from tests.sinks.roskit import same_ranges, special_recording
from tests.sinks.test_memory_out_kit import (
    BOXES,
    FRAMES,
    STEP_HALF_WIDTH_M,
    beyond_step,
    box_distance,
    drive_recording,
    to_odom,
    true_pose,
)

TOL_M = 0.08  # a cell's half diagonal (3.5 cm) plus the contract's drop-off error (5 cm), less
GRID_TIMES = [0.0, 0.5, 1.0, 1.5, 2.0]  # the default 2 Hz over 24 frames at 10 frames/s
OCCUPANCY_MD5 = "3381f2d731d4076ec5c71b0759edbe4e"  # ROS 1 nav_msgs/OccupancyGrid's md5sum


@pytest.fixture(scope="module")
def run(tmp_path_factory) -> tuple[Path, list[dict]]:
    """One CLI run of the drive into a ROS 2 .mcap, a ROS 1 .bag, a Foxglove .mcap (10 grids a
    second) and stdout."""
    tmp = tmp_path_factory.mktemp("memory_out")
    rec = drive_recording(tmp / "drive")
    p = depthnav(
        "run",
        "--device", f"replay:{rec}?rate=max",
        "--sink", f"rosbag:{tmp / 'out.mcap'}",
        "--sink", f"rosbag:{tmp / 'out.bag'}?compression=bz2",
        "--sink", f"foxglove:{tmp / 'view.mcap'}?grid_rate=10&image=0",
        "--sink", "stdout",
    )  # fmt: skip
    assert p.returncode == 0, p.stderr
    msgs = json_lines(p.stdout)
    assert len(msgs) == FRAMES and all(m["memory"]["status"] == "on" for m in msgs)
    return tmp, msgs


def read_bag(path: Path) -> dict[str, list]:
    from rosbags.highlevel import AnyReader

    out: dict[str, list] = {}
    with AnyReader([path]) as reader:
        for conn, _, raw in reader.messages():
            out.setdefault(conn.topic, []).append(reader.deserialize(raw, conn.msgtype))
    return out


def stamp_s(header: Any) -> float:
    return round(header.stamp.sec + header.stamp.nanosec * 1e-9, 6)


def occupied_xy(cells: np.ndarray, origin: tuple[float, float], cell_m: float) -> np.ndarray:
    """Odometry x, y (K, 2) of the centres of the occupied (100) cells of (rows = y, cols = x)."""
    rows, cols = np.nonzero(cells == 100)
    return np.stack([origin[0] + (cols + 0.5) * cell_m, origin[1] + (rows + 0.5) * cell_m], 1)


def check_occupancy(cells: np.ndarray, origin: tuple[float, float], cell_m: float) -> None:
    """Every occupied cell is on a box or at the step's edge; both boxes and the edge are in."""
    assert set(np.unique(cells)) <= {-1, 0, 100}
    xy = occupied_xy(cells, origin, cell_m)
    on_box = box_distance(xy) <= TOL_M
    at_edge = (np.abs(beyond_step(xy)) <= TOL_M) & (np.abs(xy[:, 1]) <= STEP_HALF_WIDTH_M)
    assert np.all(on_box | at_edge), xy[~(on_box | at_edge)]
    for box in BOXES:
        near = np.hypot(xy[:, 0] - box.x_m, xy[:, 1] - box.y_m) <= box.width_m / 2 + 0.2
        assert np.count_nonzero(near & on_box) >= 3, f"too few cells on {box}"
    rows, cols = np.nonzero(cells == 0)  # known free: never on an obstacle
    free = np.stack([origin[0] + (cols + 0.5) * cell_m, origin[1] + (rows + 0.5) * cell_m], 1)
    assert np.all(box_distance(free) > 0.0)


def test_the_grid_marks_the_scene_in_the_odom_frame(run) -> None:
    tmp, msgs = run
    by_t = {round(m["t_s"], 6): m for m in msgs}
    grids = read_bag(tmp / "out.mcap")["/memory/grid"]
    assert [stamp_s(g.header) for g in grids] == GRID_TIMES  # 2 Hz of frame time, the first at once
    last_edge = 0
    for g in grids:
        info = g.info
        assert g.header.frame_id == "odom" and info.resolution == pytest.approx(0.05)
        assert (info.width, info.height) == (160, 160) and len(g.data) == 160 * 160  # 8 m at 5 cm
        assert (info.origin.orientation.w, info.origin.position.z) == (1.0, 0.0)
        origin = (info.origin.position.x, info.origin.position.y)
        x, y, _ = true_pose(stamp_s(g.header))
        assert abs(origin[0] + 4.0 - x) <= 0.05 and abs(origin[1] + 4.0 - y) <= 0.05  # centred
        cells = np.asarray(g.data, dtype=np.int8).reshape(160, 160)
        m = by_t[stamp_s(g.header)]["memory"]
        assert np.count_nonzero(cells == 100) == m["cells"]["obstacle"] + m["cells"]["cliff"]
        if stamp_s(g.header) > 0:  # the step is seen from the second frame on
            check_occupancy(cells, origin, info.resolution)
            edge = np.abs(beyond_step(occupied_xy(cells, origin, info.resolution))) <= TOL_M
            last_edge = int(np.count_nonzero(edge))
    assert last_edge >= 20


def test_the_memory_scan_is_the_pipelines_and_lands_on_the_scene(run) -> None:
    tmp, msgs = run
    scans = read_bag(tmp / "out.mcap")["/memory/scan"]
    assert len(scans) == FRAMES
    for scan, m in zip(scans, msgs, strict=True):
        same_ranges(scan.ranges, m["memory"]["scan"]["ranges"])  # NaN and +inf as they are
        assert scan.header.frame_id == "depthnav_scan" and len(scan.ranges) == 360
        assert scan.angle_min == pytest.approx(-math.pi)
        r = np.asarray(scan.ranges, dtype=np.float64)
        assert np.isnan(r).any()  # behind the robot: never seen, unknown
        # every remembered point is on a box or at the step's edge (the scene, not our memory)
        angles = scan.angle_min + scan.angle_increment * np.arange(r.size)
        hit = np.isfinite(r)
        base = np.stack([r[hit] * np.cos(angles[hit]), r[hit] * np.sin(angles[hit])], 1)
        xy = to_odom(base, true_pose(stamp_s(scan.header)))
        ok = (box_distance(xy) <= TOL_M) | (np.abs(beyond_step(xy)) <= TOL_M)
        assert np.all(ok), xy[~ok]


def test_tf_puts_base_link_at_the_odometry_pose(run) -> None:
    tmp, msgs = run
    tfs = read_bag(tmp / "out.mcap")["/tf"]
    odom = [t.transforms for t in tfs if t.transforms[0].header.frame_id == "odom"]
    assert len(odom) == FRAMES and len(tfs) == 2 * FRAMES  # the sensor's own /tf goes on
    for (tf,), m in zip(odom, msgs, strict=True):
        assert tf.child_frame_id == "base_link"
        x, y, yaw = true_pose(stamp_s(tf.header))  # exact odometry: the true pose
        tr, q = tf.transform.translation, tf.transform.rotation
        assert (tr.x, tr.y, tr.z) == pytest.approx((x, y, 0.0), abs=1e-9)
        assert (q.x, q.y) == (0.0, 0.0)
        assert 2 * math.atan2(q.z, q.w) == pytest.approx(yaw, abs=1e-9)
        assert m["memory"]["odom"]["yaw_rad"] == pytest.approx(yaw, abs=1e-4)
    assert true_pose(2.3)[2] > math.radians(15)  # the drive turned: base_link is not odom's axes


def test_remembered_dropoffs_are_points_at_the_step_edge(run) -> None:
    tmp, msgs = run
    clouds = read_bag(tmp / "out.mcap")["/memory/cliff/points"]
    assert len(clouds) == FRAMES
    for cloud, m in zip(clouds, msgs, strict=True):
        assert cloud.header.frame_id == "base_link" and cloud.point_step == 12
        assert cloud.width == m["memory"]["cells"]["cliff"]
        xyz = np.frombuffer(bytes(cloud.data), dtype="<f4").reshape(-1, 3)
        assert np.all(xyz[:, 2] == np.float32(-0.05))  # cliff_z, as the live cliff points
        xy = to_odom(xyz[:, :2].astype(np.float64), true_pose(stamp_s(cloud.header)))
        # at the step's edge, or on a box (the cliff stage sees the floor vanish behind a
        # box's corner as a drop: a drop-off on an obstacle, occupied either way)
        at_edge = np.abs(beyond_step(xy)) <= TOL_M
        assert np.all(at_edge | (box_distance(xy) <= TOL_M)), xy
    assert np.count_nonzero(at_edge) >= 20


DEBIAN_READER = r"""
import json, sys, rosbag
out = {"grid": [], "scan": [], "odom": [], "cloud": []}
with rosbag.Bag(sys.argv[1]) as bag:
    for topic, msg, t in bag.read_messages():
        if topic == "/memory/grid":
            i = msg.info
            out["grid"].append([msg.header.frame_id, i.width, i.height, i.resolution,
                                i.origin.position.x, i.origin.position.y, list(msg.data)])
        elif topic == "/memory/scan":
            out["scan"].append(list(msg.ranges))
        elif topic == "/memory/cliff/points":
            out["cloud"].append(msg.width)
        elif topic == "/tf" and msg.transforms[0].header.frame_id == "odom":
            tr = msg.transforms[0].transform.translation
            out["odom"].append([msg.transforms[0].child_frame_id, tr.x, tr.y])
print(json.dumps(out))
"""


def test_ros1_bag_reads_back_with_rosbags_and_debian_ros1_tools(run) -> None:
    tmp, msgs = run
    ros2, ros1 = read_bag(tmp / "out.mcap"), read_bag(tmp / "out.bag")
    for topic in ("/memory/grid", "/memory/scan", "/memory/cliff/points"):
        assert len(ros1[topic]) == len(ros2[topic])
    for a, b in zip(ros1["/memory/grid"], ros2["/memory/grid"], strict=True):
        np.testing.assert_array_equal(a.data, b.data)
        assert (a.info.width, a.header.frame_id) == (b.info.width, b.header.frame_id)
    tool = shutil.which("rosbag")
    ok = tool is not None and Path("/usr/bin/python3").exists()
    if ok:
        probe = subprocess.run(["/usr/bin/python3", "-c", "import rosbag"], check=False)
        ok = probe.returncode == 0
    skip_without(not ok, "python3-rosbag")
    info = subprocess.run([tool, "info", str(tmp / "out.bag")], capture_output=True, text=True)
    assert info.returncode == 0, info.stderr
    assert re.search(rf"nav_msgs/OccupancyGrid +\[{OCCUPANCY_MD5}\]", info.stdout)
    assert "/memory/grid" in info.stdout and "/memory/scan" in info.stdout
    p = subprocess.run(
        ["/usr/bin/python3", "-c", DEBIAN_READER, str(tmp / "out.bag")],
        capture_output=True, text=True, timeout=120, check=False,
    )  # fmt: skip
    assert p.returncode == 0, p.stderr
    got = json.loads(p.stdout)
    for (frame, w, h, res, ox, oy, data), g in zip(got["grid"], ros2["/memory/grid"], strict=True):
        assert (frame, w, h) == ("odom", 160, 160) and res == pytest.approx(0.05)
        cells = np.asarray(data, dtype=np.int8).reshape(h, w)
        np.testing.assert_array_equal(cells.reshape(-1), g.data)
        check_occupancy(cells, (ox, oy), res) if stamp_s(g.header) > 0 else None
    for ranges, m in zip(got["scan"], msgs, strict=True):
        same_ranges(ranges, m["memory"]["scan"]["ranges"])
    assert got["cloud"] == [m["memory"]["cells"]["cliff"] for m in msgs]
    for (child, x, y), m in zip(got["odom"], msgs, strict=True):
        assert child == "base_link" and (x, y) == pytest.approx(true_pose(m["t_s"])[:2])


def decode_grid(grid: Any) -> tuple[np.ndarray, tuple[float, float], float]:
    """A foxglove.Grid's ``occupancy`` field as (rows, cols) int8, its origin and cell side."""
    names = {f.name: f.offset for f in grid.fields}
    assert set(names) == {"occupancy", "red", "green", "blue", "alpha"}
    assert grid.cell_stride == 5 and grid.row_stride == 5 * grid.column_count
    raw = np.frombuffer(grid.data, np.uint8).reshape(-1, grid.column_count, 5)
    cells = raw[..., names["occupancy"]].view(np.int8)
    alpha = raw[..., names["alpha"]]
    assert np.all(alpha[cells == -1] == 0) and np.all(alpha[cells == 100] > 0)  # unknown: clear
    assert grid.cell_size.x == grid.cell_size.y == pytest.approx(0.05)
    return cells, (grid.pose.position.x, grid.pose.position.y), grid.cell_size.x


def test_foxglove_file_has_the_grid_at_its_rate(run) -> None:
    from mcap.reader import make_reader

    from tests.sinks.test_foxglove_sink import _has

    tmp, msgs = run
    with open(tmp / "view.mcap", "rb") as fh:
        items = list(make_reader(fh).iter_messages(topics=["/memory/grid", "/tf"]))
    from google.protobuf import descriptor_pb2, descriptor_pool, message_factory

    decoded: dict[str, list] = {}
    for schema, channel, message in items:
        pool = descriptor_pool.DescriptorPool()
        pending = list(descriptor_pb2.FileDescriptorSet.FromString(schema.data).file)
        while pending:
            done = [f for f in pending if all(_has(pool, d) for d in f.dependency)]
            for f in done:
                pool.Add(f)
                pending.remove(f)
        cls = message_factory.GetMessageClass(pool.FindMessageTypeByName(schema.name))
        decoded.setdefault(channel.topic, []).append(cls.FromString(message.data))
    grids = decoded["/memory/grid"]
    assert len(grids) == FRAMES  # grid_rate=10 at 10 frames/s: every frame
    for grid in grids[1:]:
        assert grid.frame_id == "odom"
        check_occupancy(*decode_grid(grid))
    odom = [t for tf in decoded["/tf"] for t in tf.transforms if t.parent_frame_id == "odom"]
    assert len(odom) == FRAMES and {t.child_frame_id for t in odom} == {"base_link"}
    assert odom[-1].translation.x == pytest.approx(true_pose(msgs[-1]["t_s"])[0])


@pytest.mark.filterwarnings("ignore:connect\\(\\) must be used:DeprecationWarning")  # as there
def test_a_foxglove_client_subscribes_to_the_grid_and_decodes_it(tmp_path: Path) -> None:
    from tests.sinks.test_foxglove_sink import TOPICS, Client, Lines

    rec = drive_recording(tmp_path / "drive")
    port = free_tcp_port()
    proc = start(
        "run", "--device", f"replay:{rec}?rate=realtime&loop=1",
        "--sink", f"foxglove://127.0.0.1:{port}?image=0", "--sink", "stdout",
    )  # fmt: skip
    out = Lines(proc)
    got: dict[str, list[Any]] = {}
    try:
        client = Client(port)
        memory = {"/memory/grid", "/memory/scan", "/memory/cliff/points"}
        image = {t for t in TOPICS if t.startswith("/depthnav/depth")}
        channels = client.advertised(len(TOPICS) - len(image) + len(memory))
        assert channels["/memory/grid"]["schemaName"] == "foxglove.Grid"
        assert channels["/memory/scan"]["schemaName"] == "foxglove.LaserScan"
        assert channels["/memory/cliff/points"]["schemaName"] == "foxglove.PointCloud"
        client.subscribe(["/memory/grid", "/tf"])
        while len(got.get("/memory/grid", [])) < 3 or "/tf" not in got:
            topic, msg = client.next_message()
            got.setdefault(topic, []).append(msg)
    finally:
        code, _, err = out.stop()
    assert code == 0, err
    for grid in got["/memory/grid"]:
        assert grid.frame_id == "odom" and grid.column_count == 160
        cells, origin, cell = decode_grid(grid)
        assert cells.shape == (160, 160)
        if np.count_nonzero(cells == 100) > 40:  # past the first frame of a pass: the step too
            check_occupancy(cells, origin, cell)
    frames = {(t.parent_frame_id, t.child_frame_id) for tf in got["/tf"] for t in tf.transforms}
    assert ("odom", "base_link") in frames and ("base_link", "depthnav_scan") in frames


def test_without_odometry_no_memory_topic_is_written(tmp_path: Path) -> None:
    rec = special_recording(tmp_path / "rec", n=2)
    p = depthnav("run", "--device", f"replay:{rec}?rate=max", "--sink", f"rosbag:{tmp_path}/a.mcap")
    assert p.returncode == 0, p.stderr
    got = read_bag(tmp_path / "a.mcap")
    assert not [t for t in got if t.startswith("/memory")]
    assert all(t.transforms[0].header.frame_id == "base_link" for t in got["/tf"])


@pytest.mark.parametrize("sink", ["rosbag:x.mcap", "rosbag:x.bag", "ros2", "foxglove"])
@pytest.mark.parametrize(
    ("option", "says"),
    [
        ("grid_rate=-1", "option grid_rate='-1'"),
        ("grid_rate=31", "(accepted: 0..30)"),
        ("grid_rate=fast", "option grid_rate='fast'"),
        ("odom_tf=2", "option odom_tf='2'"),
        ("odom_frame=base_link", "odom_frame and base_frame"),
        ("memory_grid_topic=/scan", "scan_topic and memory_grid_topic"),
    ],
)
def test_bad_memory_options_are_one_line(sink: str, option: str, says: str) -> None:
    with pytest.raises(ConfigError) as info:
        create_sink(f"{sink}?{option}")
    assert says in str(info.value) and "\n" not in str(info.value)


def test_a_bad_grid_rate_exits_2_with_one_line(tmp_path: Path) -> None:
    rec = special_recording(tmp_path / "rec", n=1)
    p = depthnav(
        "run", "--device", f"replay:{rec}?rate=max",
        "--sink", f"rosbag:{tmp_path / 'a.mcap'}?grid_rate=-2",
    )  # fmt: skip
    assert p.returncode == 2
    (line,) = [x for x in p.stderr.splitlines() if "grid_rate" in x]
    assert "Traceback" not in p.stderr and "accepted: 0..30" in line
