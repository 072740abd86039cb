"""Kinect 360 (model 1414): depth via libfreenect (ctypes), accelerometer/tilt/LED via pyusb.

Spec: ``kinect[://INDEX][?accel=usb|freenect|none&tilt_deg=D&led=NAME&lib=PATH&fakenect=DIR&const_shift=C]``

- ``accel``: where each Frame's accelerometer vector comes from. ``usb`` (default) reads the motor
  device 045e:02b0 with pyusb, ``freenect`` uses libfreenect's tilt API, ``none`` gives depth only
  (the choice for model 1473 and Kinect for Windows, whose motor needs the audio firmware).
- ``tilt_deg``: drive the tilt motor to this angle (device sign: positive = up) when opening.
- ``led``: off, green, red, yellow, blink_green, blink_red_yellow, set when opening.
- ``lib``: a libfreenect.so to load instead of the system's ``libfreenect.so.0.5``.
- ``fakenect``: replay a fakenect recording folder through Debian's fakenect library, the same
  ctypes code path as a live Kinect (accel defaults to ``freenect``; one playback per process).
- ``const_shift``: the device's zero-plane constant for disparity -> mm when libfreenect only
  gives 11-bit disparity (fakenect); default 200.

Depth is 640x480 uint16 mm with the KINECT_V1 intrinsics unless ``fx, fy, cx, cy`` (pixels) are
given. Debian ships no OpenNI2 driver for the Kinect 360, hence libfreenect.
"""

from __future__ import annotations

import logging
import os
from pathlib import Path
from typing import Any

from drivers.base import KINECT_V1, DeviceInfo, Frame, TiltState
from drivers.errors import (
    DeviceLost,
    DeviceSpecError,
    DriverError,
    DriverNotAvailable,
    FrameTimeout,
    RecordingError,
)
from drivers.files import INDEX_MAX_BYTES, check_regular, open_input, read_bytes
from drivers.formats import fakenect as fakenect_format
from drivers.kinect.axes import accel_counts_to_camera, tilt_status_name
from drivers.kinect.freenect import FreenectDepth, find_library
from drivers.kinect.motor import LED, KinectMotor, describe_kinects
from drivers.spec import (
    INTRINSICS_OPTIONS,
    Spec,
    check_options,
    choice_option,
    float_option,
    intrinsics_options,
    with_overrides,
)
from drivers.values import NumberError, short_repr, to_number

log = logging.getLogger(__name__)

GRAMMAR = (
    "kinect[://INDEX][?accel=usb|freenect|none&tilt_deg=D&led=NAME&lib=PATH"
    "&fakenect=DIR&const_shift=C&fx=..&fy=..&cx=..&cy=..]"
)
OPTIONS = ("accel", "tilt_deg", "led", "lib", "fakenect", "const_shift", *INTRINSICS_OPTIONS)
FAKENECT_STOP_WAIT_S = 0.2  # its event call sleeps until the next recorded event: not waited for
LIVE_STOP_WAIT_S = 2.0  # a live device's event call returns within 0.1 s


def check_fakenect_recording(folder: Path) -> tuple[int, int]:
    """Check a fakenect folder so the C library never meets a file it would exit() or over-read
    on, or block on: the folder, INDEX.txt and every file it names are regular files (the
    library fopen()s them itself, and a FIFO would hang it where no signal can end it).

    Returns:
        (depth frames, index lines); fakenect plays one index line per event.
    """
    entries = fakenect_format.read_index(folder)  # checks the folder and every file it names
    index = folder / "INDEX.txt"
    lines = read_bytes(index, what="fakenect index", max_bytes=INDEX_MAX_BYTES).splitlines()
    for number, line in enumerate(lines, 1):
        if not line.strip():
            raise RecordingError(f"{index}:{number}: blank line; fakenect cannot play it")
    expected = len(fakenect_format.PGM_HEADER) + fakenect_format.WIDTH * fakenect_format.HEIGHT * 2
    for entry in entries:
        if entry.kind in "dr":
            with open_input(entry.path) as fh:
                head = fh.read(len(fakenect_format.PGM_HEADER))
                size = os.fstat(fh.fileno()).st_size
            if entry.kind == "d" and (head != fakenect_format.PGM_HEADER or size != expected):
                raise RecordingError(
                    f"{entry.path}: not a 640x480 11-bit fakenect depth file of {expected} bytes "
                    "(truncated or corrupt)"
                )
            if entry.kind == "r" and b"\n" not in head:
                raise RecordingError(f"{entry.path}: colour file without a header line")
        elif entry.kind == "a" and entry.path.stat().st_size != fakenect_format.ACCEL_DUMP.size:
            # fakenect printf()s a warning about it onto stdout, the daemon's JSON channel
            raise RecordingError(
                f"{entry.path}: {entry.path.stat().st_size} bytes, an accelerometer dump has "
                f"{fakenect_format.ACCEL_DUMP.size} (truncated or from another libfreenect version)"
            )
    return sum(e.kind == "d" for e in entries), len(lines)


class KinectDriver:
    """A Kinect 360. Construction does no I/O.

    Args:
        index: device index on the bus.
        accel: "usb", "freenect" or "none".
        lib_path: libfreenect to load; None finds the system's (fakenect's with ``fakenect_dir``).
        fakenect_dir: a fakenect recording to replay instead of a live device.
        usb_backend: pyusb backend for the motor device; None means libusb (tests inject one).
    """

    def __init__(
        self,
        index: int = 0,
        *,
        accel: str = "usb",
        tilt_deg: float | None = None,
        led: str | None = None,
        lib_path: Path | None = None,
        fakenect_dir: Path | None = None,
        const_shift: float = fakenect_format.CONST_SHIFT,
        usb_backend: Any = None,
        spec_text: str = "",
    ) -> None:
        if accel not in ("usb", "freenect", "none"):
            raise DeviceSpecError(f"accel={accel!r} is not usb, freenect or none")
        self.index = index
        self.accel = accel
        self.tilt_deg = tilt_deg
        self.led = led
        self.lib_path = lib_path
        self.fakenect_dir = fakenect_dir
        self.const_shift = const_shift
        self.usb_backend = usb_backend
        self.intrinsics = KINECT_V1
        self._intrinsics_given = False  # fx.. given in the spec (they win over a sidecar)
        self.spec_text = spec_text or f"kinect://{index}"
        self._depth: FreenectDepth | None = None
        self._motor: KinectMotor | None = None
        self._seq = 0
        self._stall_warned = False

    @classmethod
    def from_spec(cls, spec: Spec) -> KinectDriver:
        """Build from ``kinect[://INDEX]?...``."""
        check_options(spec, OPTIONS, GRAMMAR)
        try:
            index = int(to_number(spec.target or "0", integer=True, low=0, high=255))
        except NumberError:
            raise DeviceSpecError(
                f"{short_repr(spec.text)}: device index {short_repr(spec.target)} is not a "
                "number in 0..255",
                hint=f"the kinect spec is {GRAMMAR}",
            ) from None
        fakenect = Path(spec.options["fakenect"]) if "fakenect" in spec.options else None
        accel = choice_option(
            spec, "accel", ("usb", "freenect", "none"), "freenect" if fakenect else "usb"
        )
        led = spec.options.get("led")
        if led is not None and led not in LED:
            raise DeviceSpecError(
                f"led={short_repr(led)} in {short_repr(spec.text)} is not one of {', '.join(LED)}"
            )
        driver = cls(
            index,
            accel=accel,
            tilt_deg=float_option(spec, "tilt_deg", None, -31.0, 31.0),
            led=led,
            lib_path=Path(spec.options["lib"]) if "lib" in spec.options else None,
            fakenect_dir=fakenect,
            const_shift=float_option(spec, "const_shift", fakenect_format.CONST_SHIFT, 0.0, 1000.0)
            or fakenect_format.CONST_SHIFT,
            spec_text=spec.text,
        )
        overrides = intrinsics_options(spec)
        driver.intrinsics = with_overrides(KINECT_V1, overrides, spec.text)
        driver._intrinsics_given = bool(overrides)
        return driver

    @staticmethod
    def detect() -> list[tuple[str, str]]:
        """Kinects on the USB bus as (spec, description)."""
        found = describe_kinects()
        return [
            (f"kinect://{i}" + ("" if model == "1414" else "?accel=none"), note)
            for i, (model, note) in enumerate(found)
        ]

    @staticmethod
    def backend_status() -> list[tuple[str, str]]:
        """Where libfreenect and fakenect are, or what is missing."""
        real, fake = find_library(), find_library(fakenect=True)
        return [
            (
                "kinect",
                f"libfreenect found at {real}"
                if real
                else "missing: libfreenect.so.0.5 (apt-get install libfreenect0.5)",
            ),
            (
                "kinect fakenect",
                f"fakenect found at {fake}"
                if fake
                else "missing: fakenect (apt-get install libfreenect0.5)",
            ),
        ]

    def _library(self) -> Path:
        if self.lib_path is not None:
            if not os.path.lexists(self.lib_path):
                raise DriverNotAvailable(
                    f"{self.lib_path}: no such libfreenect", hint="check the lib= option"
                )
            check_regular(self.lib_path, DriverNotAvailable)  # dlopen() of a FIFO would block
            return self.lib_path
        path = find_library(fakenect=self.fakenect_dir is not None)
        if path is None:
            what = "Debian's fakenect library" if self.fakenect_dir else "libfreenect.so.0.5"
            raise DriverNotAvailable(f"{what} not found", hint="apt-get install libfreenect0.5")
        return path

    def open(self) -> DeviceInfo:
        """Open the motor (if accel=usb) and start libfreenect's depth stream."""
        if self._depth is not None:
            raise DriverError(f"{self.spec_text} is already open")
        lib = self._library()
        if self.fakenect_dir is not None:
            n, events = check_fakenect_recording(self.fakenect_dir)
            log.info("replaying %d fakenect frames from %s", n, self.fakenect_dir)
            # the camera a record --format fakenect export of another camera kept beside it
            # (the format itself assumes a Kinect v1); the spec's fx.. win
            camera = fakenect_format.folder_intrinsics(self.fakenect_dir)
            if camera is not None and not self._intrinsics_given:
                self.intrinsics = camera
                log.info("fakenect camera from %s", self.fakenect_dir / fakenect_format.SIDECAR)
            os.environ["FAKENECT_PATH"] = os.path.realpath(self.fakenect_dir)  # read by the C lib
        else:
            events = 0
        serial = None
        try:
            if self.accel == "usb":
                self._motor = KinectMotor(self.index, backend=self.usb_backend)
                serial = self._motor.open()
                if self.led:
                    self._motor.set_led(self.led)
                if self.tilt_deg is not None:
                    self._motor.set_tilt_deg(self.tilt_deg)
            self._depth = FreenectDepth(
                lib,
                self.index,
                use_motor=self.accel == "freenect",
                want_mm=self.fakenect_dir is None,
                # Stop at the last index line: one more call makes fakenect printf() a warning
                # to stdout, which may be the daemon's data channel.
                max_events=events if self.fakenect_dir is not None else None,
            )
            self._depth.open()
        except BaseException:
            self.close()
            raise
        name = "Kinect 360 (fakenect replay)" if self.fakenect_dir else "Kinect 360 (1414)"
        return DeviceInfo(
            name=name,
            serial=serial,
            spec=self.spec_text,
            intrinsics=self.intrinsics,
            has_accel=self.accel != "none",
        )

    def _accel(self) -> tuple[tuple[float, float, float] | None, TiltState | None]:
        if self._motor is not None:
            try:
                state = self._motor.read_state()
            except DeviceLost:
                raise
            except DriverError as exc:
                if not self._stall_warned:
                    log.warning("%s; this frame has no accelerometer reading", exc)
                    self._stall_warned = True
                return None, None
            return state.accel_mps2, state.tilt
        if self.accel == "freenect" and self._depth is not None:
            x, y, z, tilt, status = self._depth.tilt_state()
            if (x, y, z) == (0, 0, 0):  # no accelerometer record yet
                return None, None
            return accel_counts_to_camera(x, y, z), TiltState(tilt / 2.0, tilt_status_name(status))
        return None, None

    def read_frame(self, timeout_s: float = 1.0) -> Frame | None:
        """The next depth frame; None when a fakenect recording ends.

        Raises:
            FrameTimeout: no frame within ``timeout_s``.
            DeviceLost: libfreenect stopped or the motor device went away.
        """
        if self._depth is None:
            raise DriverError(f"{self.spec_text} is not open", hint="call open() first")
        item = self._depth.get(timeout_s)
        if item is None:
            if self._depth.ended.is_set():
                if self.fakenect_dir is not None:
                    return None
                raise DeviceLost(
                    f"libfreenect stopped delivering frames (status {self._depth.end_status}): "
                    "Kinect unplugged?",
                    hint="re-plug the Kinect and its power supply",
                )
            raise FrameTimeout(
                f"{self.spec_text}: no depth frame within {timeout_s:g} s",
                hint="is the Kinect's power supply connected?",
            )
        t_s, depth = item
        if not self._depth.is_mm:
            depth = fakenect_format.disparity_to_mm(depth, self.const_shift)
        accel, tilt = self._accel()
        frame = Frame(
            seq=self._seq,
            timestamp_s=t_s,
            depth_mm=depth,
            intrinsics=self.intrinsics,
            accel_mps2=accel,
            tilt=tilt,
        )
        self._seq += 1
        return frame

    @property
    def motor(self) -> KinectMotor | None:
        """The pyusb motor device (accel=usb), for tilt and LED control."""
        return self._motor

    def close(self) -> None:
        """Stop streaming and release both devices. Safe to call twice.

        A fakenect replay is not waited for: fakenect sleeps inside its event call until the
        next recorded event (seconds, for a recording with gaps), so its thread is left there
        and the library is not torn down under it (a stop took 2.3 s; now well under one).
        """
        depth, self._depth = self._depth, None
        if depth is not None:
            depth.close(wait_s=FAKENECT_STOP_WAIT_S if self.fakenect_dir else LIVE_STOP_WAIT_S)
        motor, self._motor = self._motor, None
        if motor is not None:
            motor.close()
