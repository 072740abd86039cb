"""Kinect motor device over pyusb (real pyusb code, emulated 045e:02b0) and the accelerometer
axes."""

from __future__ import annotations

import math

import pytest

from drivers.base import STANDARD_GRAVITY_MPS2 as G
from drivers.errors import DeviceLost, DeviceOpenError, DriverError, OpenFailure
from drivers.kinect.axes import accel_counts_to_camera, camera_to_accel_counts
from drivers.kinect.motor import NOT_FOUND, KinectMotor, describe_kinects, parse_state
from tests.drivers.fake_kinect_usb import FakeUsbBackend, KinectMotorModel


def opened_motor(model: KinectMotorModel) -> KinectMotor:
    motor = KinectMotor(backend=FakeUsbBackend(model))
    motor.open()
    return motor


def test_level_sensor_reads_minus_g_on_y():
    # A level Kinect's accelerometer reads about +1 g (819 counts) on its up axis.
    assert accel_counts_to_camera(0, 819, 0) == pytest.approx((0.0, -G, 0.0))


@pytest.mark.parametrize("tilt_deg", [-20.0, 0.0, 15.0, 30.0])
def test_pitched_down_reads_negative_z_and_tilt_recovers(tilt_deg):
    t = math.radians(tilt_deg)
    # Device axes: y up, z forward; pitched down by t, "up" leans backwards (-z).
    _, ay, az = accel_counts_to_camera(0, round(819 * math.cos(t)), round(-819 * math.sin(t)))
    assert ay == pytest.approx(-G * math.cos(t), abs=0.02)
    assert az == pytest.approx(-G * math.sin(t), abs=0.02)
    assert math.degrees(math.atan2(-az, -ay)) == pytest.approx(tilt_deg, abs=0.1)


def test_roll_left_side_up_reads_negative_x():
    roll = math.radians(10.0)
    # Device x points to the sensor's left; with the left side up, "up" leans to the left (+x raw).
    ax, _, _ = accel_counts_to_camera(round(819 * math.sin(roll)), round(819 * math.cos(roll)), 0)
    assert ax == pytest.approx(-G * math.sin(roll), abs=0.02)


def test_counts_round_trip():
    assert camera_to_accel_counts(accel_counts_to_camera(-12, 805, 140)) == (-12, 805, 140)


def test_parse_state_decodes_big_endian_counts_tilt_and_status():
    # Bytes from drivers.md: x=-12, y=805, z=140 (BE int16), tilt -20 half-degrees, status 4 =
    # moving
    state = parse_state(bytes([0, 0, 0xFF, 0xF4, 0x03, 0x25, 0x00, 0x8C, 0xEC, 0x04]))
    assert state.raw_counts == (-12, 805, 140)
    assert state.tilt.angle_deg == -10.0 and state.tilt.status == "moving"
    assert state.accel_mps2 == pytest.approx((0.1437, -9.639, 1.676), abs=1e-3)


def test_read_state_sends_the_documented_request():
    model = KinectMotorModel(counts=(-12, 805, 140), tilt_half_deg=-20, status=1)
    motor = opened_motor(model)
    state = motor.read_state()
    assert model.log[-1] == (0xC0, 0x32, 0, 0, 10)
    assert state.raw_counts == (-12, 805, 140) and state.tilt.status == "at_limit"
    motor.close()


def test_serial_number_comes_from_string_descriptors():
    motor = KinectMotor(backend=FakeUsbBackend(KinectMotorModel(serial="B00123")))
    assert motor.open() == "B00123"
    motor.close()


@pytest.mark.parametrize(
    ("angle", "w_value", "result"),
    [(10.0, 20, 10.0), (-10.0, 0xFFEC, -10.0), (45.0, 62, 31.0), (-90.0, 0xFFC2, -31.0)],
)
def test_set_tilt_clamps_and_encodes_int16_half_degrees(angle, w_value, result):
    model = KinectMotorModel()
    motor = opened_motor(model)
    assert motor.set_tilt_deg(angle) == result
    assert model.log[-1] == (0x40, 0x31, w_value, 0, 0)
    assert motor.read_state().tilt.angle_deg == result
    motor.close()


def test_led_request():
    model = KinectMotorModel()
    motor = opened_motor(model)
    motor.set_led("blink_green")
    assert model.log[-1] == (0x40, 0x06, 4, 0, 0) and model.led == 4
    with pytest.raises(DriverError, match="purple"):
        motor.set_led("purple")
    motor.close()


def test_stall_is_an_error_the_next_read_recovers_from():
    model = KinectMotorModel()
    motor = opened_motor(model)
    model.stall_next = 1
    with pytest.raises(DriverError) as info:
        motor.read_state()
    assert (
        not isinstance(info.value, DeviceLost) and "stalled" in str(info.value) and info.value.hint
    )
    assert motor.read_state().raw_counts == (0, 819, 0)
    motor.close()


def test_unplug_is_device_lost():
    model = KinectMotorModel()
    motor = opened_motor(model)
    model.unplug_after_reads = 1
    motor.read_state()
    with pytest.raises(DeviceLost, match="unplugged"):
        motor.read_state()
    motor.close()
    motor.close()


def test_no_kinect_gives_the_documented_message():
    with pytest.raises(DeviceOpenError) as info:
        KinectMotor(backend=FakeUsbBackend()).open()
    assert (
        str(info.value)
        == NOT_FOUND
        == ("no Kinect found (045e:02ae/02b0): plugged in? udev rules? run `depthnav devices`")
    )
    assert info.value.reason is OpenFailure.NOT_FOUND


@pytest.mark.parametrize(
    ("product", "bcd", "model"), [(0x02AE, 0x0100, "1473"), (0x02BF, 0x0100, "Kinect for Windows")]
)
def test_model_1473_and_k4w_are_detected_as_unsupported(product, bcd, model):
    camera = KinectMotorModel(product=product, bcd=bcd)
    with pytest.raises(DeviceOpenError) as info:
        KinectMotor(backend=FakeUsbBackend(camera)).open()
    assert info.value.reason is OpenFailure.UNSUPPORTED
    assert model in str(info.value) and "accel=none" in info.value.hint


def test_describe_kinects_lists_models():
    backend = FakeUsbBackend(
        KinectMotorModel(),
        KinectMotorModel(product=0x02AE, bcd=0x010B),
        KinectMotorModel(product=0x02AE, bcd=0x0100),
    )
    assert [m for m, _ in describe_kinects(backend)] == ["1414", "1473"]
