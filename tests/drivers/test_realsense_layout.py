"""RealSense recordings without the SDK (drivers/formats/realsense_layout.py), and what the
realsense device says without it: these run everywhere, pyrealsense2 or not (an aarch64 board has
no wheel). The SDK's own recordings and playback are in test_realsense.py.
"""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest

import drivers
from depthnav_daemon.pipeline.geometry import Mount
from depthnav_daemon.sim.synthetic import Scene, render, wall
from drivers.base import Intrinsics
from drivers.errors import RecordingError
from drivers.formats.realsense_layout import counts_to_mm, intrinsics_of, units_um_from_m
from drivers.realsense.driver import RealSenseDriver
from tests.drivers.bagkit import _Out, header
from tests.test_cli import ROOT

W, H = 96, 72
FX, FY, PPX, PPY = 80.5, 80.25, 47.3, 35.6
COEFFS = [0.08, -0.04, 0.001, -0.0015, 0.01]  # Brown-Conrady k1 k2 p1 p2 k3
MOUNT = Mount(height_m=0.3, tilt_deg=20.0, roll_deg=0.0)
N_FRAMES = 4


def _expected_mm(counts: np.ndarray, units_um: int) -> np.ndarray:
    """Counts to millimetres, rounded half up, written out here independently of the driver."""
    mm = (counts.astype(np.int64) * units_um + 500) // 1000
    return np.where(mm > 65535, 0, mm).astype(np.uint16)


def _scene_counts(units_um: int) -> np.ndarray:
    """(N, H, W) z16 counts of a floor and a wall coming closer, in ``units_um`` counts."""
    intr = Intrinsics(W, H, FX, FY, PPX, PPY)
    out = []
    for i in range(N_FRAMES):
        view = render(Scene(boxes=(wall(2.0 - 0.2 * i),)), intr, MOUNT, max_range_m=6.0)
        mm = view.depth_mm.astype(np.int64)
        out.append(np.clip(np.rint(mm * 1000 / units_um), 0, 65535).astype(np.uint16))
    return np.stack(out)


def _frames(spec: str) -> list:
    driver = drivers.create_driver(spec)
    with drivers.opened(driver):
        out = list(drivers.iter_frames(driver, timeout_s=5.0))
        assert driver.read_frame(0.1) is None  # the end stays the end
    return out


def test_a_ros1_bag_in_the_realsense_layout_replays_the_same_frames(tmp_path):
    """librealsense before 2.56: raw mono16 images, Float32 Depth_Units, the SDK's model name in
    the CameraInfo under info/ (see realsense_layout.py)."""
    units_um = 100  # a D405
    counts = _scene_counts(units_um)
    out = _Out(tmp_path / "old.bag", "ros1")
    t = out.ts.types
    stamp = t["builtin_interfaces/msg/Time"]
    out.write(
        "/device_0/sensor_0/option/Depth_Units/value", t["std_msgs/msg/Float32"](data=1e-4), 1
    )
    roi = t["sensor_msgs/msg/RegionOfInterest"](
        x_offset=0, y_offset=0, height=0, width=0, do_rectify=False
    )
    k = np.array([FX, 0, PPX, 0, FY, PPY, 0, 0, 1], dtype=np.float64)
    info = t["sensor_msgs/msg/CameraInfo"](
        header=header(out.ts, stamp(sec=0, nanosec=0), "0"), height=H, width=W,
        distortion_model="Brown Conrady", D=np.array(COEFFS, dtype=np.float64), K=k,
        R=np.eye(3).reshape(-1), P=np.zeros(12), binning_x=0, binning_y=0, roi=roi,
    )  # fmt: skip
    out.write("/device_0/sensor_0/Depth_0/info/camera_info", info, 1)
    for i, frame in enumerate(counts):
        t_ns = 1_000_000_000 + i * 33_333_333
        image = t["sensor_msgs/msg/Image"](
            header=header(out.ts, stamp(sec=1, nanosec=i * 33_333_333), "0"), height=H, width=W,
            encoding="mono16", is_bigendian=0, step=W * 2,
            data=np.frombuffer(frame.astype("<u2").tobytes(), dtype=np.uint8),
        )  # fmt: skip
        out.write("/device_0/sensor_0/Depth_0/image/data", image, t_ns)
    out.writer.close()
    frames = _frames(f"replay:{tmp_path / 'old.bag'}?rate=max")
    assert len(frames) == N_FRAMES
    for got, want in zip(frames, _expected_mm(counts, units_um), strict=True):
        np.testing.assert_array_equal(got.depth_mm, want)
        assert got.intrinsics.distortion == pytest.approx(COEFFS, abs=1e-7)
        assert (got.intrinsics.fx, got.intrinsics.cx) == (
            float(np.float32(FX)),
            float(np.float32(PPX)),
        )


def _run(args: list[str], code: str = "") -> subprocess.CompletedProcess:
    prog = code + "from depthnav_daemon.cli import entry_point; entry_point()"
    return subprocess.run(
        [sys.executable, "-c", prog, *args], capture_output=True, text=True, cwd=ROOT, timeout=300
    )


def _one_line(proc: subprocess.CompletedProcess) -> str:
    lines = [line for line in proc.stderr.splitlines() if line.strip()]
    assert "Traceback" not in proc.stderr, proc.stderr
    errors = [line for line in lines if "error" in line.lower()]
    assert len(errors) == 1, proc.stderr
    return errors[0]


def test_a_file_that_is_not_a_realsense_recording_is_one_line(tmp_path):
    out = _Out(tmp_path / "other.bag", "ros1")
    t = out.ts.types
    image = t["sensor_msgs/msg/Image"](
        header=header(out.ts, t["builtin_interfaces/msg/Time"](sec=1, nanosec=0), "cam"),
        height=2, width=2, encoding="16UC1", is_bigendian=0, step=4, data=np.zeros(8, np.uint8),
    )  # fmt: skip
    out.write("/camera/depth/image_raw", image, 1)
    out.writer.close()
    with pytest.raises(RecordingError, match="not a RealSense recording"):
        RealSenseDriver(file=tmp_path / "other.bag").open()
    text = tmp_path / "notes.txt"
    text.write_text("hello")
    proc = _run(
        ["run", "--device", f"realsense?file={text}", "--sink", "null", "--max-frames", "1"]
    )
    assert proc.returncode == 1
    assert "not a RealSense recording" in _one_line(proc)


def test_a_missing_sdk_is_one_line_saying_what_to_install(tmp_path):
    hide = "import sys; sys.modules['pyrealsense2'] = None\n"
    proc = _run(["run", "--device", "realsense", "--sink", "null", "--max-frames", "1"], hide)
    assert proc.returncode == 1
    line = _one_line(proc)
    assert "pyrealsense2" in line
    assert "pip install" in proc.stderr
    info = _run(["info"], hide)
    assert info.returncode == 0 and "missing: pyrealsense2" in info.stdout


def test_depth_units_become_whole_micrometres_and_counts_round_half_up():
    assert units_um_from_m(np.float32(0.0001).item(), "x") == 100  # the SDK's float32 0.1 mm
    assert units_um_from_m(0.001, "x") == 1000
    with pytest.raises(RecordingError, match="outside what a RealSense sets"):
        units_um_from_m(0.5, "x")
    counts = np.array([[0, 1, 5, 15, 25, 65535]], dtype=np.uint16)
    np.testing.assert_array_equal(counts_to_mm(counts, 100), [[0, 0, 1, 2, 3, 6554]])
    np.testing.assert_array_equal(counts_to_mm(counts, 2000), [[0, 2, 10, 30, 50, 0]])  # > 65 m
    assert counts_to_mm(counts, 1000) is counts


def test_sdk_lens_models_map_to_depthnavs_or_are_refused():
    kb = intrinsics_of(64, 48, 40, 40, 31.5, 23.5, "Kannala Brandt4", (0.1, 0.01, 0.0, 0.0), "x")
    assert kb.distortion_model == "equidistant" and kb.k1 == pytest.approx(0.1)
    bc = intrinsics_of(64, 48, 40, 40, 31.5, 23.5, "brown_conrady", (0.1, 0, 0, 0, 0), "x")
    assert bc.distortion_model == "plumb_bob" and bc.k1 == pytest.approx(0.1)
    flat = intrinsics_of(64, 48, 40, 40, 31.5, 23.5, "Inverse Brown Conrady", (0,) * 5, "x")
    assert not flat.has_distortion
    with pytest.raises(RecordingError, match=r"Inverse Brown Conrady.*not supported"):
        intrinsics_of(64, 48, 40, 40, 31.5, 23.5, "Inverse Brown Conrady", (0.1, 0, 0, 0, 0), "x")
