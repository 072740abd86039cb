"""OpenNI2 depth: live devices (Xtion, Carmine, any PS1080/PSLink sensor) and ``.oni`` playback.

Spec: ``openni://[URI][?mode=WxH@FPS]`` for a live device (first device when URI is empty;
``openni://Dummy`` is OpenNI's built-in test device), or
``openni:FILE.oni[?rate=realtime|max&loop=0|1]``
for a recording. ``rate=max`` (default for files) plays every frame in order as fast as it is read;
``rate=realtime`` delivers every frame too, each no sooner than its recorded time after the first.
The player always runs in OpenNI2's manual mode (speed -1: the next frame is read when asked for)
and the pacing is ours: at speed 1 the player's own thread pushes frames on its clock and a reader
that falls behind (the first frame's compile, a slow sink) lost the frames in between (2 of 12).
``fx, fy, cx, cy`` (pixels) replace the intrinsics, which otherwise come from the stream's field of
view with the principal point at the image centre (58 x 45 degrees when the device reports none),
or for a file from ``NAME.camera.toml`` beside it (``drivers.formats.oni.write_oni`` writes one for
a camera the file cannot hold: a principal point off the centre, any lens model).
OpenNI2 reports no lens distortion for depth (its API has only the field of view; PS1080 sensors
compute depth in the device), so a live image is an ideal pinhole unless ``k1, k2, p1, p2, k3``
(plumb_bob) are given as options.

Uses PyPI ``openni`` over the system libOpenNI2 (Debian: ``apt-get install libopenni2-0``), found
without user setup: a private folder of two symlinks is built next to the system library, because
``openni2.initialize()`` wants ``libOpenNI2.so`` and the library looks for drivers relative to
itself. ``DEPTHNAV_OPENNI2_REDIST`` may name another folder holding ``libOpenNI2.so`` and
``OpenNI2/Drivers``. Known traps avoided: ``PlaybackSupport.seek`` hangs this build (never called;
looping uses the player's repeat), the Dummy device crashes if a stream is destroyed within 33 ms of
``stop()`` (we wait), and frame buffers are reused after ``close()`` (we copy).
"""

from __future__ import annotations

import dataclasses
import logging
import math
import os
import time
from pathlib import Path
from typing import Any

import numpy as np

from drivers.base import DeviceInfo, Frame, Intrinsics
from drivers.errors import (
    DeviceLost,
    DeviceOpenError,
    DeviceSpecError,
    DriverError,
    FrameTimeout,
    OpenFailure,
    RecordingError,
)
from drivers.formats.oni import check_oni, read_sidecar_intrinsics, sidecar_path
from drivers.openni.native import LIB_NAME, find_library, initialize
from drivers.replay_clock import Pacer
from drivers.spec import (
    INTRINSICS_OPTIONS,
    Spec,
    bool_option,
    check_options,
    choice_option,
    intrinsics_options,
    mode_option,
)

log = logging.getLogger(__name__)

GRAMMAR = (
    "openni://[URI][?mode=WxH@FPS&fx=..&fy=..&cx=..&cy=..] or "
    "openni:FILE.oni[?rate=realtime|max&loop=0|1&fx=..&fy=..&cx=..&cy=..]"
)
LIVE_OPTIONS = ("mode", *INTRINSICS_OPTIONS)
FILE_OPTIONS = ("rate", "loop", *INTRINSICS_OPTIONS)
# PrimeSense PS1080 nominal field of view, used when a device does not report one (Dummy).
DEFAULT_HFOV_DEG, DEFAULT_VFOV_DEG = 58.0, 45.0
STOP_SETTLE_S = 0.1  # > 33 ms: stream threads outlive stop() by up to one frame period
MANUAL_SPEED = -1.0  # OpenNI2 PlaybackControl: -1 = manual, a frame is read when asked for


def _message(exc: Exception) -> str:
    """The text of an ``OpenNIError`` (args: code, message bytes, logfile)."""
    args = getattr(exc, "args", ())
    text = args[1] if len(args) > 1 else exc
    return text.decode(errors="replace") if isinstance(text, bytes) else str(text)


def _format_value(fmt: Any) -> int:
    """A pixel format as an int: the ``openni`` package's enum repr fails on unknown values."""
    for attr in ("value", "val"):
        value = getattr(fmt, attr, None)
        if isinstance(value, int):
            return value
    try:
        return int(fmt)
    except (TypeError, ValueError):
        return -1


class OpenNIDriver:
    """OpenNI2 depth stream from a live device or an ``.oni`` file."""

    def __init__(
        self,
        uri: str | None = None,
        *,
        file: Path | None = None,
        mode: tuple[int, int, int] | None = None,
        realtime: bool = False,
        loop: bool = False,
        spec_text: str = "",
        intrinsics_override: dict[str, float] | None = None,
    ) -> None:
        self.uri = uri
        self.intrinsics_override = dict(intrinsics_override or {})
        self.file = file
        self.mode = mode
        self.realtime = realtime
        self.loop = loop
        self.spec_text = spec_text or (f"openni:{file}" if file else f"openni://{uri or ''}")
        self._dev: Any = None
        self._stream: Any = None
        self._openni2: Any = None
        self._intrinsics: Intrinsics | None = None
        self._n_frames = 0
        self._read = 0
        self._seq = 0
        self._t_offset_s = 0.0
        self._last_raw_t_s = -1.0
        self._pacer = Pacer()  # rate=realtime

    @classmethod
    def from_spec(cls, spec: Spec) -> OpenNIDriver:
        """Build from ``openni://...`` or ``openni:FILE.oni``."""
        if spec.target.lower().endswith(".oni"):
            check_options(spec, FILE_OPTIONS, GRAMMAR)
            return cls.for_file(
                Path(spec.target),
                realtime=choice_option(spec, "rate", ("realtime", "max"), "max") == "realtime",
                loop=bool_option(spec, "loop", False),
                spec_text=spec.text,
                intrinsics_override=intrinsics_options(spec),
            )
        check_options(spec, LIVE_OPTIONS, GRAMMAR)
        return cls(
            spec.target or None,
            mode=mode_option(spec),
            spec_text=spec.text,
            intrinsics_override=intrinsics_options(spec),
        )

    @classmethod
    def for_file(
        cls,
        path: Path,
        *,
        realtime: bool = False,
        loop: bool = False,
        spec_text: str = "",
        intrinsics_override: dict[str, float] | None = None,
    ) -> OpenNIDriver:
        """A driver playing an ``.oni`` file."""
        return cls(
            None,
            file=Path(path),
            realtime=realtime,
            loop=loop,
            spec_text=spec_text,
            intrinsics_override=intrinsics_override,
        )

    @staticmethod
    def detect() -> list[tuple[str, str]]:
        """Attached OpenNI2 devices as (spec, description)."""
        openni2 = initialize()
        return [
            (f"openni://{info.uri.decode()}", f"{info.vendor.decode()} {info.name.decode()}")
            for info in openni2.Device.enumerate_devices()
            if info.uri
        ]

    @staticmethod
    def backend_status() -> list[tuple[str, str]]:
        """Where libOpenNI2 is, or what is missing."""
        found = find_library()
        if found is None:
            return [("openni", f"missing: {LIB_NAME} (apt-get install libopenni2-0)")]
        drivers = sorted(p.name for p in (found[1] / "Drivers").glob("lib*.so*"))
        return [
            ("openni", f"libOpenNI2 found at {found[0]} (drivers: {', '.join(drivers) or 'none'})")
        ]

    def _open_device(self, openni2: Any) -> Any:
        from openni.utils import OpenNIError

        try:
            if self.file is not None:  # checked by check_oni in open()
                return openni2.Device.open_file(os.fsencode(self.file))
            if self.uri:
                return openni2.Device(self.uri.encode())
            return openni2.Device.open_any()
        except OpenNIError as exc:
            if self.file is not None:
                raise RecordingError(
                    f"{self.file}: OpenNI2 cannot play it ({_message(exc)})"
                ) from exc
            what = f"OpenNI2 device {self.uri!r}" if self.uri else "an OpenNI2 device"
            raise DeviceOpenError(
                f"could not open {what}: {_message(exc)}",
                hint="plugged in? udev rules (libopenni2-0)? run `depthnav devices`",
                reason=OpenFailure.NOT_FOUND,
            ) from exc

    def open(self) -> DeviceInfo:
        """Open the device or file and start the depth stream."""
        if self._dev is not None:
            raise DriverError(f"{self.spec_text} is already open")
        if self.file is not None:  # a file's problems before the library's (which may be absent)
            self._n_frames = check_oni(self.file).frames
        openni2 = self._openni2 = initialize()
        from openni.utils import OpenNIError

        self._dev = self._open_device(openni2)
        try:
            if self._dev.playback is not None:
                self._dev.playback.set_repeat_enabled(self.loop)
                # manual at every rate: read_frame paces rate=realtime (see the module doc)
                self._dev.playback.set_speed(MANUAL_SPEED)
            self._stream = self._dev.create_depth_stream()
            if self._stream is None:
                raise DeviceOpenError(
                    f"{self.spec_text}: no depth stream", reason=OpenFailure.UNSUPPORTED
                )
            if self.mode is not None:
                self._set_mode(openni2)
            vm = self._stream.get_video_mode()
            self._intrinsics = self._with_options(
                self._intrinsics_for(vm.resolutionX, vm.resolutionY)
            )
            self._stream.start()
            info = self._dev.get_device_info()
        except OpenNIError as exc:
            self.close()
            raise DeviceOpenError(
                f"{self.spec_text}: starting the depth stream failed: {_message(exc)}"
            ) from exc
        except BaseException:
            self.close()
            raise
        name = (
            f"OpenNI file {self.file.name}"
            if self.file
            else f"{info.vendor.decode()} {info.name.decode()}".strip()
        )
        return DeviceInfo(name=name, serial=None, spec=self.spec_text, intrinsics=self._intrinsics)

    def _set_mode(self, openni2: Any) -> None:
        assert self.mode is not None
        width, height, fps = self.mode
        for vm in self._stream.get_sensor_info().videoModes:
            if (vm.resolutionX, vm.resolutionY, vm.fps) == (
                width,
                height,
                fps,
            ) and vm.pixelFormat in (
                openni2.PIXEL_FORMAT_DEPTH_1_MM,
                openni2.PIXEL_FORMAT_DEPTH_100_UM,
            ):
                self._stream.set_video_mode(vm)
                return
        modes = sorted(
            {
                f"{vm.resolutionX}x{vm.resolutionY}@{vm.fps}"
                for vm in self._stream.get_sensor_info().videoModes
            }
        )
        raise DeviceOpenError(
            f"{self.spec_text}: mode {width}x{height}@{fps} not supported",
            hint=f"supported: {', '.join(modes)}",
            reason=OpenFailure.UNSUPPORTED,
        )

    def _with_options(self, base: Intrinsics) -> Intrinsics:
        """``base`` with the spec's fx, fy, cx, cy and lens options; the lens fields they do not
        name (a sidecar's rational or fisheye model) kept whole."""
        if not self.intrinsics_override:
            return base
        try:
            return dataclasses.replace(base, **self.intrinsics_override)
        except ValueError as exc:  # the one-line error with_overrides gives
            raise DeviceSpecError(
                f"{self.spec_text}: intrinsics options do not fit the image: {exc}"
            ) from None

    def _intrinsics_for(self, width: int, height: int) -> Intrinsics:
        if self.file is not None:  # a camera the file cannot hold, written beside it
            side = read_sidecar_intrinsics(self.file, width, height)
            if side is not None:
                log.info("%s: intrinsics from %s", self.spec_text, sidecar_path(self.file).name)
                return side
        try:
            hfov, vfov = self._stream.get_horizontal_fov(), self._stream.get_vertical_fov()
        except Exception:  # Dummy and some drivers lack the FOV property
            log.info(
                "%s reports no field of view; assuming %.0f x %.0f deg",
                self.spec_text,
                DEFAULT_HFOV_DEG,
                DEFAULT_VFOV_DEG,
            )
            return Intrinsics.from_fov(width, height, DEFAULT_HFOV_DEG, DEFAULT_VFOV_DEG)
        try:
            return Intrinsics.from_fov(width, height, math.degrees(hfov), math.degrees(vfov))
        except (ValueError, ZeroDivisionError) as exc:  # a corrupt file or a confused device
            raise self._bad(f"{self.spec_text}: the depth stream reports {exc}") from None

    def _bad(self, message: str) -> DriverError:
        """The error for a stream that delivers nonsense: a file is damaged (RecordingError, the run
        ends), a live device may recover on reopening (DeviceLost, the daemon reconnects)."""
        if self.file is not None:
            return RecordingError(message, hint="the .oni file is damaged; re-record it")
        return DeviceLost(message, hint="check the cable; run `depthnav devices`")

    def read_frame(self, timeout_s: float = 1.0) -> Frame | None:
        """The next depth frame; None at the end of a non-looping file."""
        if self._stream is None or self._intrinsics is None:
            raise DriverError(f"{self.spec_text} is not open", hint="call open() first")
        from openni.utils import OpenNIError

        if self.file is not None and not self.loop and self._read >= self._n_frames:
            return None  # saves waiting out a timeout at the end of the file
        try:
            ready = self._openni2.wait_for_any_stream([self._stream], timeout=max(timeout_s, 0.001))
            if not ready:
                if self.file is not None and not self.loop:
                    return None
                raise FrameTimeout(
                    f"{self.spec_text}: no frame within {timeout_s:g} s",
                    hint="is the sensor covered or the USB bus overloaded?",
                )
            raw = self._stream.read_frame()
            try:
                depth, t_s = self._copy(raw)
            finally:
                raw.close()
        except OpenNIError as exc:
            raise self._bad(f"{self.spec_text}: depth stream failed: {_message(exc)}") from exc
        self._read += 1
        if t_s < self._last_raw_t_s:  # the file looped: keep time increasing
            self._t_offset_s += self._last_raw_t_s - t_s + 1.0 / 30.0
        self._last_raw_t_s = t_s
        if self.realtime and self.file is not None:
            self._pacer.wait(t_s + self._t_offset_s, timeout_s)
        frame = Frame(
            seq=self._seq,
            timestamp_s=t_s + self._t_offset_s,
            depth_mm=depth,
            intrinsics=self._intrinsics,
        )
        self._seq += 1
        return frame

    def _copy(self, raw: Any) -> tuple[np.ndarray, float]:
        intr = self._intrinsics
        assert intr is not None
        if (raw.width, raw.height) != (intr.width, intr.height):
            raise self._bad(
                f"{self.spec_text}: frame is {raw.width}x{raw.height}, "
                f"stream was {intr.width}x{intr.height} (cropping or mode change)"
            )
        fmt = _format_value(raw.videoMode.pixelFormat)
        if fmt not in (self._depth_1_mm, self._depth_100_um):
            raise self._bad(f"{self.spec_text}: pixel format {fmt} is not depth")
        buf = np.frombuffer(raw.get_buffer_as_uint16(), dtype=np.uint16)
        row = raw.stride // 2
        if row < raw.width or buf.size < raw.height * row:  # never reshape past the buffer
            raise self._bad(
                f"{self.spec_text}: frame holds {buf.size * 2} bytes, "
                f"a {raw.width}x{raw.height} frame with stride {raw.stride} needs "
                f"{raw.height * row * 2}"
            )
        rows = buf[: raw.height * row].reshape(raw.height, row)
        depth = np.array(rows[:, : raw.width], dtype=np.uint16)  # copy: the buffer is reused
        if fmt == self._depth_100_um:
            depth = ((depth.astype(np.uint32) + 5) // 10).astype(np.uint16)
        return depth, raw.timestamp / 1e6

    @property
    def _depth_1_mm(self) -> int:
        return _format_value(self._openni2.PIXEL_FORMAT_DEPTH_1_MM)

    @property
    def _depth_100_um(self) -> int:
        return _format_value(self._openni2.PIXEL_FORMAT_DEPTH_100_UM)

    def close(self) -> None:
        """Stop and release the stream and device. Safe to call twice."""
        stream, dev = self._stream, self._dev
        self._stream = self._dev = None
        if stream is not None:
            try:
                stream.stop()
                # Both DummyDevice's stream thread and the .oni player can still touch the
                # stream for one frame period after stop(); destroying it sooner crashes
                # (seen here: 2 in 30 runs for .oni files, 10 in 10 for Dummy).
                time.sleep(STOP_SETTLE_S)
                stream.close()
            except Exception:  # closing must not raise
                log.debug("closing OpenNI2 stream failed", exc_info=True)
        if dev is not None:
            try:
                dev.close()
            except Exception:  # closing must not raise
                log.debug("closing OpenNI2 device failed", exc_info=True)
