"""``replay:`` over ROS bags written by rosbags' own writers: same frames, same scans."""

from __future__ import annotations

import itertools
import logging
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

import drivers
from depthnav_daemon.pipeline import StageParams, process
from depthnav_daemon.pipeline.cliff import CliffParams
from depthnav_daemon.pipeline.geometry import Mount
from depthnav_daemon.pipeline.scan import ScanParams
from depthnav_daemon.sim.synthetic import Box, Scene, render, step_down, wall
from drivers.base import KINECT_V1, Frame, tilt_roll_to_accel
from drivers.errors import RecordingError
from drivers.formats.png_folder import write_png_folder
from tests.drivers.bagkit import (
    DEPTH_TOPIC,
    OPTICAL,
    T0_S,
    BagSpec,
    bare_storage,
    write_bag,
)
from tests.drivers.driverkit import ramp_frames
from tests.faults.kit import ROOT, depthnav, one_error_line

MOUNT = Mount(height_m=0.55, tilt_deg=14.0, roll_deg=1.5)
INTR = KINECT_V1.scaled(160, 120)
SCENE = Scene(boxes=(Box(1.6, 0.4, 0.3, 0.3, 0.25), wall(3.2)), holes=(step_down(2.2, 0.3),))
PARAMS = StageParams(
    scan=ScanParams(range_max_m=4.0), cliff=CliffParams(block_size=8, row_step=2, col_step=2)
)


def scene_frames(n: int = 3) -> list[Frame]:
    """Synthetic views at slightly different mounts, with accelerometer readings."""
    out = []
    for i in range(n):
        mount = Mount(MOUNT.height_m, MOUNT.tilt_deg + i, MOUNT.roll_deg)
        view = render(SCENE, INTR, mount)
        accel = tilt_roll_to_accel(mount.tilt_deg, mount.roll_deg)
        out.append(Frame(i, i / 15.0, view.depth_mm, INTR, accel_mps2=accel))
    return out


def replayed(spec: str) -> list[Frame]:
    with drivers.opened(drivers.create_driver(spec)) as driver:
        return list(drivers.iter_frames(driver))


def scans(frames: list[Frame]) -> list[tuple[np.ndarray, np.ndarray]]:
    out = []
    for f in frames:
        r = process(f, MOUNT, PARAMS)
        assert r.cliff is not None
        out.append((r.scan.ranges, r.cliff.scan.ranges))
    return out


def bag_variants(tmp_path: Path, frames: list[Frame]) -> dict[str, Path]:
    """Every kind of bag: ROS 1, ROS 2 db3/mcap folders, bare files; 16UC1 and 32FC1."""
    out: dict[str, Path] = {}
    for kind in ("ros1", "db3", "mcap"):
        for enc, big, pad in (("16UC1", False, 0), ("32FC1", True, 8)):
            name = f"{kind}-{enc}"
            path = tmp_path / (name + ".bag" if kind == "ros1" else name)
            out[name] = write_bag(path, frames, BagSpec(kind, enc, bigendian=big, pad=pad))
    out["bare.mcap"] = bare_storage(out["mcap-32FC1"], tmp_path / "bare.mcap")
    out["bare.db3"] = bare_storage(out["db3-16UC1"], tmp_path / "bare.db3")
    return out


def test_png_folder_and_every_bag_kind_give_identical_scans(tmp_path: Path) -> None:
    frames = scene_frames()
    write_png_folder(tmp_path / "png", frames, scale=1000.0)  # millimetres: lossless
    want = scans(replayed(f"replay:{tmp_path / 'png'}?rate=max"))
    assert any(np.isfinite(s).any() and np.isfinite(c).any() for s, c in want)  # not vacuous
    for name, path in bag_variants(tmp_path, frames).items():
        got = replayed(f"replay:{path}?rate=max")
        assert len(got) == len(frames), name
        for a, b in zip(frames, got, strict=True):
            np.testing.assert_array_equal(b.depth_mm, a.depth_mm, err_msg=name)
            assert b.intrinsics == INTR, name
            assert b.timestamp_s == pytest.approx(T0_S + a.timestamp_s, abs=1e-6), name
        for (s0, c0), (s1, c1) in zip(want, scans(got), strict=True):
            np.testing.assert_array_equal(s1, s0, err_msg=name)  # NaN, +inf, -inf included
            np.testing.assert_array_equal(c1, c0, err_msg=name)


def test_imu_in_the_image_frame_or_joined_by_tf_static(tmp_path: Path, caplog) -> None:
    frames = ramp_frames(3)
    same = write_bag(tmp_path / "same.bag", frames, BagSpec("ros1", imu_frame=OPTICAL))
    got = replayed(f"replay:{same}?rate=max")
    for want, have in zip(frames, got, strict=True):
        assert have.accel_mps2 == pytest.approx(want.accel_mps2)
    # the IMU reads in the camera body frame (x forward, y left, z up): REP 103 camera_link,
    # joined to the optical frame by the usual static rotation (roll -90, yaw -90)
    body = [
        Frame(f.seq, f.timestamp_s, f.depth_mm, f.intrinsics, accel_mps2=(a[2], -a[0], -a[1]))
        for f in frames
        for a in [f.accel_mps2]
        if a is not None
    ]
    optical_in_link = (-0.5, 0.5, -0.5, 0.5)
    tf = [("camera_link", OPTICAL, optical_in_link)]
    joined = write_bag(
        tmp_path / "tf", body, BagSpec("mcap", imu_frame="camera_link", tf_static=tf)
    )
    got = replayed(f"replay:{joined}?rate=max")
    for want, have in zip(frames, got, strict=True):
        assert have.accel_mps2 == pytest.approx(want.accel_mps2, abs=1e-9)
    alone = write_bag(tmp_path / "alone", body, BagSpec("db3", imu_frame="imu_link"))
    with caplog.at_level(logging.WARNING):
        with drivers.opened(drivers.create_driver(f"replay:{alone}?rate=max")) as driver:
            assert driver.read_frame().accel_mps2 is None
    assert "accelerometer not used" in caplog.text


def test_qos_mismatch_in_a_ros2_folder_falls_back_to_the_storage_file(tmp_path, caplog) -> None:
    frames = ramp_frames(3)
    folder = write_bag(tmp_path / "qos", frames, BagSpec("mcap"))
    meta = folder / "metadata.yaml"
    profile = (
        "offered_qos_profiles:\n      - history: keep_last\n        depth: 5\n"
        "        reliability: best_effort\n        durability: volatile\n"
        "        deadline: {sec: 9223372036, nsec: 854775807}\n"
        "        lifespan: {sec: 9223372036, nsec: 854775807}\n        liveliness: automatic\n"
        "        liveliness_lease_duration: {sec: 9223372036, nsec: 854775807}\n"
        "        avoid_ros_namespace_conventions: false"
    )
    meta.write_text(meta.read_text().replace("offered_qos_profiles: []", profile, 1))
    with caplog.at_level(logging.WARNING):
        got = replayed(f"replay:{folder}?rate=max")
    assert "QoS differs" in caplog.text
    assert len(got) == 3
    np.testing.assert_array_equal(got[2].depth_mm, frames[2].depth_mm)


def test_loop_and_start_over_a_bag(tmp_path: Path) -> None:
    frames = ramp_frames(3)
    bag = write_bag(tmp_path / "b.bag", frames, BagSpec("ros1"))
    driver = drivers.create_driver(f"replay:{bag}?rate=max&loop=1&start=1")
    with drivers.opened(driver):
        got = [driver.read_frame() for _ in range(5)]
    stamps = [f.timestamp_s for f in got]
    assert all(b > a for a, b in itertools.pairwise(stamps))
    for have, want in zip(got, [1, 2, 0, 1, 2], strict=True):  # starts at 1, loops to 0
        np.testing.assert_array_equal(have.depth_mm, frames[want].depth_mm)


# the replay's peak of Python memory, measured in a fresh interpreter: tracemalloc counts every
# thread, and a worker of the suite may still run another test's threads beside this one (seen
# once: twice the replay's own peak)
PEAK_CODE = """
import sys, tracemalloc
import drivers
def replay():
    count = 0
    with drivers.opened(drivers.create_driver(sys.argv[1])) as driver:
        while driver.read_frame() is not None:
            count += 1
    return count
replay()  # the readers' imports and caches, as in a daemon that has started
tracemalloc.start()
count = replay()
print(count, tracemalloc.get_traced_memory()[1])
"""


def test_frames_are_streamed_not_loaded(tmp_path: Path) -> None:
    """120 frames of 320x240 (18 MB of depth) replay within a few MB of Python memory."""
    intr = KINECT_V1.scaled(320, 240)
    frames = ramp_frames(120, intr=intr, accel=False)
    bags = [
        write_bag(tmp_path / "big.bag", frames, BagSpec("ros1")),
        write_bag(tmp_path / "big", frames, BagSpec("mcap")),
    ]
    total = sum(f.depth_mm.nbytes for f in frames)
    del frames
    for bag in bags:
        proc = subprocess.run(
            [sys.executable, "-c", PEAK_CODE, f"replay:{bag}?rate=max"],
            capture_output=True,
            text=True,
            cwd=ROOT,
            check=True,
        )
        count, peak = (int(x) for x in proc.stdout.split())
        assert count == 120
        assert peak < total / 4, f"{bag.name}: peak {peak} B for {total} B of depth"


# --- bad input: one line each, with a hint -----------------------------------------------------
def _error(spec: str) -> RecordingError:
    with pytest.raises(RecordingError) as info:
        replayed(spec)
    assert "\n" not in str(info.value)
    return info.value


def test_no_depth_topic_or_several(tmp_path: Path) -> None:
    frames = ramp_frames(2)
    colour = write_bag(tmp_path / "c.bag", frames, BagSpec("ros1", encoding="rgb8", info=False))
    err = _error(f"replay:{colour}")
    assert "no depth image topic" in str(err) and f"{DEPTH_TOPIC} (rgb8)" in (err.hint or "")
    two = write_bag(
        tmp_path / "two", frames, BagSpec("mcap", extra_images={"/cam2/depth/image": "32FC1"})
    )
    err = _error(f"replay:{two}")
    assert "2 depth image topics" in str(err)
    assert f"{DEPTH_TOPIC} (16UC1)" in str(err) and "/cam2/depth/image (32FC1)" in str(err)
    assert "?topic=" in (err.hint or "")
    got = replayed(f"replay:{two}?rate=max&topic=/cam2/depth/image")
    np.testing.assert_array_equal(got[1].depth_mm, frames[1].depth_mm)
    err = _error(f"replay:{colour}?topic={DEPTH_TOPIC}")
    assert "'rgb8' is not depth" in str(err) and "16UC1" in (err.hint or "")


def test_images_without_camera_info_ask_for_intrinsics(tmp_path: Path) -> None:
    frames = ramp_frames(2)
    bag = write_bag(tmp_path / "n.bag", frames, BagSpec("ros1", info=False))
    err = _error(f"replay:{bag}")
    assert "no CameraInfo" in str(err) and "fx=" in (err.hint or "")
    i = frames[0].intrinsics
    got = replayed(f"replay:{bag}?rate=max&fx={i.fx}&fy={i.fy}&cx={i.cx}&cy={i.cy}")
    assert got[0].intrinsics == i


def test_truncated_bags(tmp_path: Path) -> None:
    frames = ramp_frames(4)
    for name, kind in (("t.bag", "ros1"), ("t", "mcap")):
        path = write_bag(tmp_path / name, frames, BagSpec(kind))
        file = path if path.is_file() else next(path.glob("*.mcap"))
        data = file.read_bytes()
        file.write_bytes(data[: len(data) // 2])
        err = _error(f"replay:{path}?rate=max")
        assert "not a readable ROS bag" in str(err) and err.hint


def test_compressed_depth_of_zeros_is_one_error(tmp_path: Path) -> None:
    from rosbags.rosbag2 import Writer
    from rosbags.typesys import Stores, get_typestore

    ts = get_typestore(Stores.ROS2_HUMBLE)
    path = tmp_path / "packed"
    with Writer(path, version=9) as writer:
        topic = "/camera/depth/image_raw/compressedDepth"
        conn = writer.add_connection(topic, "sensor_msgs/msg/CompressedImage", typestore=ts)
        msg = ts.types["sensor_msgs/msg/CompressedImage"](
            header=ts.types["std_msgs/msg/Header"](
                stamp=ts.types["builtin_interfaces/msg/Time"](sec=1, nanosec=0), frame_id="c"
            ),
            format="16UC1; compressedDepth png",
            data=np.zeros(16, dtype=np.uint8),
        )
        writer.write(conn, 1, ts.serialize_cdr(msg, msg.__msgtype__))
    err = _error(f"replay:{path}")
    assert "the compressedDepth payload is not a PNG" in str(err)  # see test_ros_compressed_depth


def test_the_cli_says_one_line(tmp_path: Path) -> None:
    two = write_bag(
        tmp_path / "two.bag",
        ramp_frames(2),
        BagSpec("ros1", extra_images={"/cam2/depth/image": "16UC1"}),
    )
    p = depthnav("run", "--device", f"replay:{two}?rate=max", "--sink", "null", timeout=120)
    assert p.returncode != 0
    line = one_error_line(p.stderr)
    assert "2 depth image topics" in line and "/cam2/depth/image (16UC1)" in line
    assert "depthnav: hint: choose one with ?topic=" in p.stderr


def test_plumb_bob_distortion_is_applied(tmp_path: Path, caplog) -> None:
    from drivers.formats.rosbag import DepthBag

    d = (0.1, -0.2, 0.001, -0.002, 0.05)
    bag = write_bag(tmp_path / "d.bag", ramp_frames(1), BagSpec("ros1", distortion=d))
    with caplog.at_level(logging.WARNING):
        probe = DepthBag(bag).probe()
    assert probe.camera is not None and probe.camera.distortion == d
    assert probe.camera.distortion_model == "plumb_bob"
    assert probe.camera.intrinsics.distortion == d and "not modelled" not in caplog.text
    assert math.isclose(probe.camera.intrinsics.fx, ramp_frames(1)[0].intrinsics.fx)
    # and the replayed frames carry it
    with drivers.opened(drivers.create_driver(f"replay:{bag}?rate=max")) as driver:
        frame = driver.read_frame()
    assert frame is not None and frame.intrinsics.distortion == d


@pytest.mark.parametrize(
    ("model", "d", "keys"),
    [
        ("rational_polynomial", (0.1, -0.2, 0.0, 0.0, 0.05, 0.0, 0.0, 0.0), 8),
        ("rational_polynomial", (2.0, 0.5, 0.0, 0.0, 0.0, 2.1, 0.6, 0.0), 8),
        ("equidistant", (0.1, 0.01, 0.0, 0.0), 4),
        ("equidistant", (0.0, 0.0, 0.0, 0.0), 4),  # the ideal fisheye, not a pinhole
    ],
    ids=["rational_without_denominator", "rational", "equidistant", "equidistant_zero"],
)
def test_other_lens_models_are_applied_whole(
    tmp_path: Path, model: str, d: tuple[float, ...], keys: int
) -> None:
    from drivers.formats.rosbag import DepthBag

    spec = BagSpec("ros1", distortion=d, distortion_model=model)
    bag = write_bag(tmp_path / "d.bag", ramp_frames(1), spec)
    probe = DepthBag(bag).probe()
    assert probe.camera is not None and probe.camera.distortion == d
    intr = probe.camera.intrinsics
    assert intr.distortion_model == model and intr.distortion == d[:keys]
    assert intr.has_distortion
    # and the replayed frames carry the whole model (replay rebuilds intrinsics from the file's)
    with drivers.opened(drivers.create_driver(f"replay:{bag}?rate=max")) as driver:
        frame = driver.read_frame()
    assert frame is not None and frame.intrinsics == intr


@pytest.mark.parametrize(
    ("model", "d"),
    [
        ("fisheye", (0.1, 0.01, 0.0, 0.0)),
        ("", (0.1, 0.0, 0.0, 0.0, 0.0)),
        ("plumb_bob", (0.1, 0.0, 0.0, 0.0, 0.0, 0.2)),  # a sixth term would be cut off
        ("rational_polynomial", (0.1,) + (0.0,) * 8 + (1e-3,) * 40),  # thin prism and more
    ],
    ids=["unknown_name", "unnamed", "plumb_bob_with_k4", "rational_with_thin_prism"],
)
def test_a_lens_that_cannot_be_expressed_is_refused_in_one_line(
    tmp_path: Path, model: str, d: tuple[float, ...]
) -> None:
    from drivers.formats.rosbag import DepthBag

    spec = BagSpec("ros1", distortion=d, distortion_model=model)
    bag = write_bag(tmp_path / "d.bag", ramp_frames(1), spec)
    with pytest.raises(RecordingError, match="cannot be expressed") as info:
        DepthBag(bag).probe()
    text = str(info.value)
    assert "\n" not in text and len(text) < 600 and "rational_polynomial (k1-k6" in text
    assert f"{model or 'unnamed'} D = [0.1, " in text


def test_a_folding_plumb_bob_d_is_a_one_line_error(tmp_path: Path) -> None:
    from drivers.formats.rosbag import DepthBag

    spec = BagSpec("ros1", distortion=(-2.0, 0.0, 0.0, 0.0, 0.0))
    bag = write_bag(tmp_path / "d.bag", ramp_frames(1), spec)
    with pytest.raises(RecordingError, match=r"CameraInfo K/D does not fit the image: lens"):
        DepthBag(bag).probe()
