"""The Kinect 360 (model 1414) motor device 045e:02b0 over pyusb: accelerometer, tilt motor, LED.

Control transfers (libfreenect src/tilt.c): state read ``(0xC0, 0x32, 0, 0, 10 bytes)`` with
big-endian int16 x, y, z counts at bytes 2..7, tilt in half-degrees (int8) at byte 8 and the
motor status at byte 9; set tilt ``(0x40, 0x31, int16(2 * deg), 0)`` for deg in -31..31; set LED
``(0x40, 0x06, option, 0)``. Model 1473 and Kinect for Windows have no 02b0 device (their motor
sits behind the audio firmware) and are reported as unsupported here.
"""

from __future__ import annotations

import errno
import logging
import struct
from dataclasses import dataclass
from typing import Any

from drivers.base import TiltState
from drivers.errors import DeviceLost, DeviceOpenError, DriverError, OpenFailure
from drivers.kinect.axes import accel_counts_to_camera, tilt_status_name

log = logging.getLogger(__name__)

VENDOR_MICROSOFT = 0x045E
PID_MOTOR, PID_CAMERA, PID_AUDIO = 0x02B0, 0x02AE, 0x02AD
PID_K4W_CAMERA = 0x02BF
BCD_MODEL_1414 = 0x010B
LED = {"off": 0, "green": 1, "red": 2, "yellow": 3, "blink_green": 4, "blink_red_yellow": 6}
TILT_LIMIT_DEG = 31.0
STATE_BYTES = 10  # the motor device's state report (drivers.md)
NOT_FOUND = "no Kinect found (045e:02ae/02b0): plugged in? udev rules? run `depthnav devices`"


@dataclass(frozen=True, slots=True)
class MotorState:
    """One reading of the motor device."""

    accel_mps2: tuple[float, float, float]  # camera frame, m/s^2
    raw_counts: tuple[int, int, int]  # device axes, 819 per g
    tilt: TiltState


def parse_state(buf: bytes) -> MotorState:
    """Decode the 10-byte reply to request 0x32."""
    if len(buf) < STATE_BYTES:
        raise DriverError(f"Kinect motor sent {len(buf)} state bytes, expected 10")
    _, x, y, z, tilt_raw, status = struct.unpack(">hhhhbB", bytes(buf[:10]))
    return MotorState(
        accel_counts_to_camera(x, y, z),
        (x, y, z),
        TiltState(tilt_raw / 2.0, tilt_status_name(status)),
    )


def describe_kinects(backend: Any = None) -> list[tuple[str, str]]:
    """Kinects on the USB bus as (model, note), e.g. ("1414", "supported")."""
    import usb.core

    out = []
    for dev in usb.core.find(find_all=True, idVendor=VENDOR_MICROSOFT, backend=backend) or []:
        if dev.idProduct == PID_CAMERA:
            if dev.bcdDevice == BCD_MODEL_1414:
                out.append(("1414", "Kinect 360 (1414): depth, accelerometer, tilt, LED"))
            else:
                out.append(
                    (
                        "1473",
                        "Kinect 360 (1473): depth only; its tilt/accelerometer need the "
                        "audio firmware, which depthnav does not upload (use accel=none)",
                    )
                )
        elif dev.idProduct == PID_K4W_CAMERA:
            out.append(
                (
                    "k4w",
                    "Kinect for Windows: depth only; tilt/accelerometer not supported "
                    "(use accel=none)",
                )
            )
    return out


class KinectMotor:
    """Accelerometer, tilt and LED of a Kinect 360 (1414) through pyusb.

    Args:
        index: which motor device, in bus order.
        backend: a pyusb backend; None uses libusb. Tests pass an emulated device here.
    """

    def __init__(self, index: int = 0, backend: Any = None) -> None:
        self.index = index
        self.backend = backend
        self._dev: Any = None

    def open(self) -> str | None:
        """Find and claim the motor device; return its serial number if readable.

        Raises:
            DeviceOpenError: no motor device (with a 1473/K4W explanation when one is present),
                or no permission.
        """
        import usb.core
        import usb.util

        try:
            motors = list(
                usb.core.find(
                    find_all=True,
                    idVendor=VENDOR_MICROSOFT,
                    idProduct=PID_MOTOR,
                    backend=self.backend,
                )
                or []
            )
        except usb.core.NoBackendError:
            raise DeviceOpenError(
                "pyusb found no libusb to talk to the Kinect motor",
                hint="apt-get install libusb-1.0-0",
                reason=OpenFailure.OTHER,
            ) from None
        if len(motors) <= self.index:
            others = [note for model, note in describe_kinects(self.backend) if model != "1414"]
            if others:
                raise DeviceOpenError(
                    f"{others[0].split(':')[0]} found, but it has no motor device 045e:02b0",
                    hint=others[0],
                    reason=OpenFailure.UNSUPPORTED,
                )
            raise DeviceOpenError(
                NOT_FOUND,
                hint="check `lsusb | grep 045e`; the Kinect needs its own power supply",
                reason=OpenFailure.NOT_FOUND,
            )
        dev = motors[self.index]
        try:
            dev.set_configuration()
        except usb.core.USBError as exc:
            usb.util.dispose_resources(dev)
            if exc.errno == errno.EACCES:
                raise DeviceOpenError(
                    "no permission to use the Kinect motor (045e:02b0)",
                    hint="install udev rules (libfreenect0.5) and re-plug, or join group plugdev",
                    reason=OpenFailure.PERMISSION,
                ) from None
            if exc.errno == errno.EBUSY:
                raise DeviceOpenError(
                    "the Kinect motor (045e:02b0) is busy",
                    hint="close other Kinect programs",
                    reason=OpenFailure.BUSY,
                ) from None
            raise DeviceOpenError(f"could not configure the Kinect motor: {exc}") from None
        self._dev = dev
        try:
            return str(dev.serial_number) if dev.iSerialNumber else None
        except (usb.core.USBError, ValueError):
            return None

    def _control(self, request_type: int, request: int, value: int, length_or_data: Any) -> Any:
        import usb.core

        if self._dev is None:
            raise DriverError("the Kinect motor is not open", hint="call open() first")
        try:
            return self._dev.ctrl_transfer(
                request_type, request, value, 0, length_or_data, timeout=500
            )
        except usb.core.USBError as exc:
            if exc.errno == errno.ENODEV:
                raise DeviceLost(
                    "the Kinect motor (045e:02b0) went away: unplugged?",
                    hint="re-plug the Kinect and its power supply; run `depthnav devices`",
                ) from None
            if exc.errno == errno.EPIPE:
                raise DriverError(
                    f"the Kinect motor stalled request {request:#04x}",
                    hint="transient; if it repeats, re-plug the Kinect",
                ) from None
            raise DriverError(f"Kinect motor request {request:#04x} failed: {exc}") from None

    def read_state(self) -> MotorState:
        """Read accelerometer and tilt state.

        Raises:
            DeviceLost: the device was unplugged (errno 19).
            DriverError: a stall or other transfer error; the next read may succeed.
        """
        return parse_state(bytes(self._control(0xC0, 0x32, 0, 10)))

    def set_tilt_deg(self, angle_deg: float) -> float:
        """Drive the motor to ``angle_deg`` (positive up, the device's sign), clamped to +-31.

        Returns:
            The angle actually requested, degrees.
        """
        angle = max(-TILT_LIMIT_DEG, min(TILT_LIMIT_DEG, float(angle_deg)))
        self._control(0x40, 0x31, struct.unpack("<H", struct.pack("<h", round(2 * angle)))[0], b"")
        return round(2 * angle) / 2.0

    def set_led(self, name: str) -> None:
        """Set the LED: off, green, red, yellow, blink_green, blink_red_yellow."""
        if name not in LED:
            raise DriverError(f"unknown LED state {name!r}; use one of {', '.join(LED)}")
        self._control(0x40, 0x06, LED[name], b"")

    def close(self) -> None:
        """Release the device. Safe to call twice."""
        dev, self._dev = self._dev, None
        if dev is not None:
            import usb.util

            usb.util.dispose_resources(dev)
