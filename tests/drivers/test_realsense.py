"""The RealSense driver through the real SDK (pyrealsense2): a software device records with
``rs.recorder``; ``realsense?file=`` plays that back through the SDK, ``replay:`` reads the same
file without it, a ``.npz`` holds the same frames: all three give the same frames and scan.
A software device stands in for a camera to pin the IMU axes and the stop/timeout behaviour.
"""

from __future__ import annotations

import threading
import time
from pathlib import Path

import numpy as np
import pytest

import drivers
from depthnav_daemon.pipeline.params import ScanParams
from depthnav_daemon.pipeline.pose import tilt_roll_from_accel
from depthnav_daemon.pipeline.scan import depth_to_scan
from drivers.base import tilt_roll_to_accel
from drivers.errors import FrameTimeout
from drivers.realsense.driver import RealSenseDriver
from tests.drivers.test_realsense_layout import (
    COEFFS,
    FX,
    FY,
    MOUNT,
    N_FRAMES,
    PPX,
    PPY,
    H,
    W,
    _expected_mm,
    _frames,
    _scene_counts,
)

rs = pytest.importorskip("pyrealsense2")


def _software_device(units_m: float, accel: bool, extrinsic: list[float] | None = None):
    """A software device with a depth sensor (and an accelerometer): (device, depth sensor,
    depth profile, accel sensor, accel profile, the accel stream's rs.extrinsics)."""
    dev = rs.software_device()
    dev.register_info(rs.camera_info.name, "Intel RealSense D435I")
    dev.register_info(rs.camera_info.serial_number, "000111222333")
    dev.register_info(rs.camera_info.firmware_version, "5.16.0.1")
    depth = dev.add_sensor("Stereo Module")
    intr = rs.intrinsics()
    intr.width, intr.height, intr.fx, intr.fy, intr.ppx, intr.ppy = W, H, FX, FY, PPX, PPY
    intr.model, intr.coeffs = rs.distortion.brown_conrady, COEFFS
    vs = rs.video_stream()
    vs.type, vs.index, vs.uid, vs.width, vs.height = rs.stream.depth, 0, 0, W, H
    vs.fps, vs.bpp, vs.fmt, vs.intrinsics = 30, 2, rs.format.z16, intr
    dprof = depth.add_video_stream(vs)
    depth.add_read_only_option(rs.option.depth_units, units_m)
    motion = aprof = ext = None
    if accel:
        motion = dev.add_sensor("Motion Module")
        ms = rs.motion_stream()
        ms.type, ms.index, ms.uid, ms.fps, ms.fmt = (
            rs.stream.accel, 0, 1, 100, rs.format.motion_xyz32f,
        )  # fmt: skip
        aprof = motion.add_motion_stream(ms)
        ext = rs.extrinsics()
        ext.rotation = extrinsic or [1, 0, 0, 0, 1, 0, 0, 0, 1]
        ext.translation = [0.005, -0.005, 0.01]
        aprof.register_extrinsics_to(dprof, ext)
    return dev, depth, dprof, motion, aprof, ext


def _feed(sensor, profile, counts: np.ndarray, i: int, units_m: float) -> None:
    f = rs.software_video_frame()
    f.pixels, f.stride, f.bpp = np.ascontiguousarray(counts), W * 2, 2
    f.timestamp, f.domain, f.frame_number = 1000.0 + 33.3 * i, rs.timestamp_domain.hardware_clock, i
    f.depth_units = units_m
    f.profile = profile.as_video_stream_profile()
    sensor.on_video_frame(f)


def _feed_accel(sensor, profile, vec, i: int) -> None:
    m = rs.software_motion_frame()
    v = rs.vector()
    v.x, v.y, v.z = vec
    m.data, m.timestamp, m.frame_number = v, 1000.0 + 33.3 * i - 1.0, i
    m.domain, m.profile = rs.timestamp_domain.hardware_clock, profile.as_motion_stream_profile()
    sensor.on_motion_frame(m)


def _record(path: Path, counts: np.ndarray, units_m: float) -> Path:
    """Record ``counts`` with ``rs.recorder`` from a software device, with an accelerometer
    reading the scene's attitude."""
    dev, depth, dprof, motion, aprof, _ = _software_device(units_m, accel=True)
    rec = rs.recorder(str(path), dev)
    sink = rs.frame_queue(64)
    depth.open(dprof)
    motion.open(aprof)
    depth.start(sink)
    motion.start(sink)
    for i, frame in enumerate(counts):
        _feed_accel(motion, aprof, tilt_roll_to_accel(MOUNT.tilt_deg, MOUNT.roll_deg), i)
        _feed(depth, dprof, frame, i, units_m)
        time.sleep(0.02)  # the recorder writes on its own thread
    depth.stop(), motion.stop(), depth.close(), motion.close()
    del rec  # closes the .db3
    return path


def _scan(frame) -> np.ndarray:
    return depth_to_scan(frame.depth_mm, frame.intrinsics, MOUNT, ScanParams()).ranges


@pytest.mark.parametrize("units_um", [1000, 200])
def test_sdk_playback_replay_and_npz_give_the_same_frames_and_scan(tmp_path, units_um):
    units_m = units_um / 1e6
    counts = _scene_counts(units_um)
    db3 = _record(tmp_path / "rec.db3", counts, units_m)
    expected = _expected_mm(counts, units_um)
    npz = tmp_path / "same.npz"
    np.savez(npz, depth_mm=expected)
    via_sdk = _frames(f"realsense?file={db3}")
    via_replay = _frames(f"replay:{db3}?rate=max")
    f32 = [float(np.float32(v)) for v in (FX, FY, PPX, PPY)]
    pin = "&".join(f"{k}={v!r}" for k, v in zip(("fx", "fy", "cx", "cy"), f32, strict=True))
    lens32 = "&".join(
        f"{k}={float(np.float32(v))!r}"
        for k, v in zip(("k1", "k2", "p1", "p2", "k3"), COEFFS, strict=True)
    )
    via_npz = _frames(f"replay:{npz}?rate=max&{pin}&{lens32}")
    # the lens reaches every path (the npz's through options, as float32 like the SDK's)
    assert len(via_sdk) == len(via_replay) == len(via_npz) == N_FRAMES
    for a, b, c, want in zip(via_sdk, via_replay, via_npz, expected, strict=True):
        np.testing.assert_array_equal(a.depth_mm, want)
        np.testing.assert_array_equal(b.depth_mm, want)
        np.testing.assert_array_equal(c.depth_mm, want)
        assert a.intrinsics == b.intrinsics == c.intrinsics
        assert a.intrinsics.distortion == pytest.approx(COEFFS, abs=1e-7)
        np.testing.assert_array_equal(_scan(a), _scan(c))
        np.testing.assert_array_equal(_scan(b), _scan(c))
    assert np.isfinite(_scan(via_sdk[-1])).any()  # the wall is seen: the scan is not empty
    # hardware timestamps (ms) through the SDK
    assert [f.timestamp_s for f in via_sdk] == pytest.approx([1.0 + 0.0333 * i for i in range(4)])


def _live(dev, **kw) -> RealSenseDriver:
    return RealSenseDriver(device=dev, mode=(W, H, 30), spec_text="realsense://test", **kw)


def _wait_for_accel(driver: RealSenseDriver, i: int) -> None:
    """Until the SDK's thread has handed the driver accelerometer sample ``i`` (a live camera's
    frame takes the samples already in: the test must not race the SDK's dispatch)."""
    for _ in range(1000):
        if driver._stream._accel_newest_ms >= 1000.0 + 33.3 * i - 1.0:
            return
        time.sleep(0.005)
    raise AssertionError("the accelerometer sample never arrived")


def test_the_accelerometer_at_a_known_attitude_gives_that_tilt_and_roll():
    """The accel stream's axes differ from the depth stream's by a quarter turn about z (the
    registered extrinsic); the SDK's own transform says what the depth axes read."""
    rot = [0, 1, 0, -1, 0, 0, 0, 0, 1]  # rs2_extrinsics rotation, column-major
    dev, depth, dprof, motion, aprof, ext = _software_device(0.001, accel=True, extrinsic=rot)
    want_depth_axes = np.array(tilt_roll_to_accel(23.0, -6.0))
    # the accel-frame vector that the extrinsic takes to want_depth_axes (translation removed)
    basis = [
        np.array(rs.rs2_transform_point_to_point(ext, list(map(float, e))))
        - np.array(rs.rs2_transform_point_to_point(ext, [0.0, 0.0, 0.0]))
        for e in np.eye(3)
    ]
    m = np.stack(basis, axis=1)  # depth = m @ accel
    accel_axes = np.linalg.solve(m, want_depth_axes)
    driver = _live(dev)
    info = driver.open()
    try:
        assert info.has_accel and info.serial == "000111222333"
        counts = _scene_counts(1000)
        for i in range(3):
            _feed_accel(motion, aprof, tuple(map(float, accel_axes)), i)
            _wait_for_accel(driver, i)
            _feed(depth, dprof, counts[i], i, 0.001)
            frame = driver.read_frame(5.0)
            assert frame is not None and frame.accel_mps2 is not None
            np.testing.assert_allclose(frame.accel_mps2, want_depth_axes, atol=1e-4)
            tilt, roll = tilt_roll_from_accel(np.array(frame.accel_mps2))
            assert (tilt, roll) == pytest.approx((23.0, -6.0), abs=1e-3)  # degrees
    finally:
        driver.close()


def test_a_camera_that_stops_sending_times_out_and_closes_promptly():
    dev, depth, dprof, *_ = _software_device(0.0001, accel=False)
    driver = _live(dev)
    info = driver.open()
    assert not info.has_accel
    counts = _scene_counts(100)
    _feed(depth, dprof, counts[0], 0, 0.0001)
    frame = driver.read_frame(5.0)
    np.testing.assert_array_equal(frame.depth_mm, _expected_mm(counts[0], 100))  # D405 units
    with pytest.raises(FrameTimeout, match=r"no depth frame within 0\.3 s"):
        driver.read_frame(0.3)
    closer = threading.Thread(target=driver.close)
    closer.start()
    closer.join(5.0)
    assert not closer.is_alive()
    driver.close()  # twice is fine


def test_the_spec_options_table_lists_what_the_driver_accepts():
    from drivers.realsense import options
    from drivers.spec_options import option_names

    assert set(option_names("realsense")) == set(options.LIVE_OPTIONS) | set(options.FILE_OPTIONS)


def test_frames_kept_by_the_caller_do_not_starve_the_sdk(tmp_path):
    """A recorder or the bench keeps every Frame: the SDK's frame pool (32 frames) must not run
    dry, or the playback drops the rest."""
    counts = np.stack([_scene_counts(1000)[i % N_FRAMES] for i in range(40)])
    db3 = _record(tmp_path / "long.db3", counts, 0.001)
    kept = _frames(f"realsense?file={db3}")
    assert len(kept) == 40
    for frame, want in zip(kept, counts, strict=True):
        np.testing.assert_array_equal(frame.depth_mm, want)


def test_no_camera_is_a_not_found_open_error_the_daemon_waits_on():
    from drivers.errors import DeviceOpenError, OpenFailure

    with pytest.raises(DeviceOpenError, match="no RealSense camera with serial 999") as info:
        drivers.create_driver("realsense://999").open()
    assert info.value.reason is OpenFailure.NOT_FOUND
