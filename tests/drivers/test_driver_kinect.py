"""The Kinect driver through Debian's real fakenect library (ctypes) and an emulated motor device.

Each test runs the driver in a child process: libfreenect is native code, and fakenect keeps
process-global playback state.
"""

from __future__ import annotations

import json

import pytest

import drivers
from drivers.errors import DeviceOpenError
from drivers.formats.fakenect import write_fakenect
from drivers.kinect.freenect import find_library
from tests.drivers.driverkit import kinect_exact_frames, run_isolated, skip_without


@pytest.fixture(autouse=True)
def _needs_fakenect():
    skip_without(find_library(fakenect=True) is None, "libfreenect0.5")


CHILD = """
import json, sys, numpy as np
from pathlib import Path
from drivers.errors import DriverError
from drivers.kinect.driver import KinectDriver
from tests.drivers.driverkit import kinect_exact_frames
from tests.drivers.fake_kinect_usb import FakeUsbBackend, KinectMotorModel
folder, accel, unplug_after, stall = Path(sys.argv[1]), sys.argv[2], sys.argv[3], int(sys.argv[4])
model = KinectMotorModel(counts=(-12, 805, 140), tilt_half_deg=-20)
if unplug_after != "none":
    model.unplug_after_reads = int(unplug_after)
expected = kinect_exact_frames(3)
tilt = None if sys.argv[5] == "none" else float(sys.argv[5])
led = None if sys.argv[6] == "none" else sys.argv[6]
driver = KinectDriver(fakenect_dir=folder, accel=accel, usb_backend=FakeUsbBackend(model),
                      tilt_deg=tilt, led=led)
out = {"frames": []}
try:
    info = driver.open()
    out["info"] = [info.name, info.serial, info.has_accel]
    model.stall_next = stall  # after open(), so the stall hits a mid-stream state read
    while True:
        f = driver.read_frame(5.0)
        if f is None:
            out["end"] = "none"; break
        equal = bool(np.array_equal(f.depth_mm, expected[f.seq].depth_mm))
        tilt = None if f.tilt is None else [f.tilt.angle_deg, f.tilt.status]
        out["frames"].append({"seq": f.seq, "equal": equal, "accel": f.accel_mps2, "tilt": tilt,
                              "shape": list(f.depth_mm.shape)})
except DriverError as exc:
    out["error"] = [type(exc).__name__, str(exc), exc.hint]
finally:
    driver.close()
    driver.close()
out["motor_writes"] = [entry for entry in model.log if entry[0] == 0x40]
print(json.dumps(out))
"""


def run_kinect(
    folder, accel="freenect", unplug_after="none", stall=0, tilt="none", led="none"
) -> dict:
    proc = run_isolated(CHILD, str(folder), accel, str(unplug_after), str(stall), str(tilt), led)
    assert proc.returncode == 0, (
        f"child exited {proc.returncode}: {proc.stdout[-500:]} {proc.stderr[-2000:]}"
    )
    # fakenect printf()s to stdout if played past its index; the driver must stop before that.
    assert "No more lines" not in proc.stdout
    return json.loads(proc.stdout.strip().splitlines()[-1])


@pytest.fixture
def recording(tmp_path):
    write_fakenect(tmp_path / "rec", kinect_exact_frames(3))
    return tmp_path / "rec"


def test_fakenect_replay_is_bit_exact_and_ends_cleanly(recording):
    out = run_kinect(recording)
    assert out.get("end") == "none", out
    assert [f["seq"] for f in out["frames"]] == [0, 1, 2]
    assert all(f["equal"] and f["shape"] == [480, 640] for f in out["frames"])
    # libfreenect's tilt API returns the recorded a-*.dump (written from (0, -9.7, -1.4) m/s^2);
    # the first frame may come before its dump has been played.
    readings = [f["accel"] for f in out["frames"] if f["accel"] is not None]
    assert readings and all(a == pytest.approx([0.0, -9.7, -1.4], abs=0.02) for a in readings)
    assert out["frames"][-1]["accel"] is not None


def test_usb_motor_accelerometer_goes_into_every_frame(recording):
    out = run_kinect(recording, accel="usb")
    assert out["info"] == ["Kinect 360 (fakenect replay)", "A00366911234567A", True]
    assert len(out["frames"]) == 3 and all(f["equal"] for f in out["frames"])
    for f in out["frames"]:
        assert f["accel"] == pytest.approx([0.1437, -9.639, 1.676], abs=1e-3)
        assert f["tilt"] == [-10.0, "stopped"]


def test_motor_stall_mid_stream_drops_one_reading_not_the_stream(recording):
    out = run_kinect(recording, accel="usb", stall=1)
    assert out.get("end") == "none" and len(out["frames"]) == 3
    assert out["frames"][0]["accel"] is None and out["frames"][1]["accel"] is not None


def test_unplug_mid_stream_is_device_lost_not_a_hang(recording):
    out = run_kinect(recording, accel="usb", unplug_after=1)
    assert len(out["frames"]) == 1
    name, message, hint = out["error"]
    assert name == "DeviceLost" and "unplugged" in message and hint


@pytest.mark.parametrize("damage", ["truncate", "delete", "header"])
def test_corrupt_fakenect_recording_is_rejected_before_the_native_library(recording, damage):
    victim = sorted(recording.glob("d-*.pgm"))[1]
    if damage == "truncate":
        victim.write_bytes(victim.read_bytes()[:5000])
    elif damage == "delete":
        victim.unlink()
    else:
        victim.write_bytes(b"P5 320 240 65535\n" + victim.read_bytes()[17:])
    out = run_kinect(recording)  # fakenect itself would exit(1) or over-read; we must not get there
    name, message, _ = out["error"]
    assert name == "RecordingError" and victim.name in message and "\n" not in message


def test_without_a_kinect_the_message_says_what_to_check():
    driver = drivers.create_driver("kinect")
    with pytest.raises(DeviceOpenError) as info:
        driver.open()
    driver.close()
    assert "no Kinect found (045e:02ae/02b0)" in str(info.value)


def test_open_sets_led_and_tilt_on_the_motor(recording):
    out = run_kinect(recording, accel="usb", tilt=-10.0, led="red")
    assert out["motor_writes"] == [[0x40, 0x06, 2, 0, 0], [0x40, 0x31, 0xFFEC, 0, 0]]
    assert out["frames"][-1]["tilt"] == [-10.0, "moving"]


CHILD_CAMERA = """
import json, sys
import drivers
spec = sys.argv[1]
with drivers.opened(drivers.create_driver(spec)) as driver:
    f = driver.read_frame(5.0)
i = f.intrinsics
print(json.dumps([i.fx, i.fy, i.cx, i.cy, i.k1]))
"""


def test_a_fakenect_export_of_another_camera_replays_with_its_camera(tmp_path):
    """record --format fakenect keeps a camera the format cannot hold in camera.toml beside it;
    the Kinect driver's fakenect replay reads it (spec intrinsics still win)."""
    import dataclasses

    from drivers.base import KINECT_V1

    camera = dataclasses.replace(KINECT_V1, fx=600.0, fy=601.0, cx=330.5, cy=250.25, k1=0.05)
    frames = [dataclasses.replace(f, intrinsics=camera) for f in kinect_exact_frames(2)]
    write_fakenect(tmp_path / "rec", frames)
    assert (tmp_path / "rec" / "camera.toml").exists()
    spec = f"kinect://0?fakenect={tmp_path / 'rec'}&accel=none"
    proc = run_isolated(CHILD_CAMERA, spec)
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert json.loads(proc.stdout.strip().splitlines()[-1]) == [600.0, 601.0, 330.5, 250.25, 0.05]
    proc = run_isolated(CHILD_CAMERA, spec + "&fx=590&fy=590&cx=320&cy=240")
    assert proc.returncode == 0, proc.stderr[-2000:]
    got = json.loads(proc.stdout.strip().splitlines()[-1])
    assert got[:4] == [590.0, 590.0, 320.0, 240.0]
