"""Intel RealSense D4xx depth through the SDK (pyrealsense2): live cameras and their recordings.

Spec: ``realsense[://SERIAL][?mode=WxH@FPS&preset=NAME&emitter=0|1&laser_power=MW&filters=..
&accel=0|1]`` for a camera (the first one without SERIAL), or ``realsense?file=REC.db3|REC.bag
[&rate=max|realtime&filters=..&accel=0|1]`` to play a recording through the SDK's own playback.

- ``mode``: the depth stream, default 640x480@30 (D4xx); ``preset``: the visual preset, default
  high_accuracy (ArduPilot's and Intel's choice for obstacle avoidance; a camera without presets
  is left as it is unless one is asked for); ``emitter``, ``laser_power`` (mW): the projector;
- ``filters``: the SDK's post-processing, off by default: a comma list of decimation, spatial,
  temporal, hole_filling, applied in that order (hole filling invents depth: know why you want it);
- ``accel``: the IMU's accelerometer (D435i, D455) as each frame's tilt prior, default 1 when the
  camera has one (axes: drivers/realsense/sdk.py); ``fx, fy, cx, cy, k1..`` replace the intrinsics.

Depth is z16 times the device's depth units (1 mm on D4xx by default, 0.1 mm on the D405; read
from the device, never assumed), rounded to millimetres. Intrinsics and the lens model come from
the stream profile (drivers/formats/realsense_layout.py says which models). Timestamps are the
SDK's frame timestamps (ms; the device clock, or its host-synchronised global time).

Frames reach the driver through SDK callbacks that only queue them (drivers/realsense/stream.py:
live, the newest frames win; a file plays every frame in order, the SDK's reader paced by the
queue). A camera unplugged is seen through the SDK's devices-changed callback (DeviceLost: the
daemon reopens it with backoff); a camera that stops sending gives FrameTimeout, never a hang.
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

import numpy as np

from drivers.base import DeviceInfo, Frame, Intrinsics
from drivers.errors import (
    DeviceLost,
    DeviceOpenError,
    DeviceSpecError,
    DriverError,
    OpenFailure,
    RecordingError,
)
from drivers.files import check_path_length, check_regular
from drivers.formats.realsense_layout import DEPTH_TOPIC, counts_to_mm, units_um_from_m
from drivers.realsense import sdk
from drivers.realsense.options import (
    DEFAULT_MODE,
    DEFAULT_PRESET,
    FILE_OPTIONS,
    GRAMMAR,
    LIVE_OPTIONS,
    parse_filters,
    parse_mode,
)
from drivers.realsense.stream import SdkStream
from drivers.spec import (
    Spec,
    bool_option,
    check_options,
    choice_option,
    float_option,
    intrinsics_options,
    with_overrides,
)
from drivers.values import short_repr

log = logging.getLogger(__name__)

SUFFIXES = (".db3", ".bag")


class RealSenseDriver:
    """A RealSense camera or recording through the SDK. Construction does no I/O.

    Args:
        serial: the camera's serial number; None for the first camera.
        file: a recording (.db3 / .bag) to play instead.
        device: an SDK device to use instead of searching (tests pass a software device).
    """

    def __init__(
        self,
        serial: str | None = None,
        *,
        file: Path | None = None,
        mode: tuple[int, int, int] = DEFAULT_MODE,
        preset: str | None = None,
        emitter: bool | None = None,
        laser_power: float | None = None,
        filters: tuple[str, ...] = (),
        accel: bool = True,
        realtime: bool = False,
        spec_text: str = "",
        intrinsics_override: dict[str, float] | None = None,
        device: Any = None,
    ) -> None:
        self.serial = serial
        self.file = file
        self.mode = mode
        self.preset = preset
        self.emitter = emitter
        self.laser_power = laser_power
        self.filters = filters
        self.accel = accel
        self.realtime = realtime
        self.spec_text = spec_text or (
            f"realsense?file={file}" if file else f"realsense://{serial or ''}"
        )
        self.overrides = dict(intrinsics_override or {})
        self._given_device = device
        self._rs: Any = None
        self._ctx: Any = None
        self._dev: Any = None
        self._playback: Any = None
        self._sensors: list[Any] = []
        self._filters: list[Any] = []
        self._stream = SdkStream(file is None, self.spec_text)
        self._units_um = 1000
        self._intrinsics: Intrinsics | None = None
        self._profile_intrinsics: dict[int, Intrinsics] = {}
        self._n_frames = 0
        self._seq = 0

    @classmethod
    def from_spec(cls, spec: Spec) -> RealSenseDriver:
        """Build from ``realsense[://SERIAL]?...`` or ``realsense?file=REC``."""
        filters = parse_filters(spec)
        accel = bool_option(spec, "accel", True)
        overrides = intrinsics_options(spec)
        if "file" in spec.options:
            check_options(spec, FILE_OPTIONS, GRAMMAR)
            if spec.target:
                raise DeviceSpecError(
                    f"{short_repr(spec.text)} names both a camera and a file",
                    hint=f"the realsense spec is {GRAMMAR}",
                )
            if not spec.options["file"]:
                raise DeviceSpecError(f"{short_repr(spec.text)}: file= names no recording")
            return cls(
                file=Path(spec.options["file"]),
                filters=filters,
                accel=accel,
                realtime=choice_option(spec, "rate", ("max", "realtime"), "max") == "realtime",
                spec_text=spec.text,
                intrinsics_override=overrides,
            )
        check_options(spec, LIVE_OPTIONS, GRAMMAR)
        emitter = bool_option(spec, "emitter", True) if "emitter" in spec.options else None
        return cls(
            spec.target or None,
            mode=parse_mode(spec),
            preset=choice_option(spec, "preset", sdk.PRESETS, DEFAULT_PRESET)
            if "preset" in spec.options
            else None,
            emitter=emitter,
            laser_power=float_option(spec, "laser_power", None, 0.0, 1000.0),
            filters=filters,
            accel=accel,
            spec_text=spec.text,
            intrinsics_override=overrides,
        )

    # --- discovery -------------------------------------------------------------------------
    @staticmethod
    def detect() -> list[tuple[str, str]]:
        """Attached RealSense cameras as (spec, "model (serial S, firmware F)")."""
        rs = sdk.import_sdk()
        found = []
        for dev in rs.context().query_devices():
            name, serial, firmware = sdk.device_info(rs, dev)
            found.append(
                (f"realsense://{serial}", f"{name} (serial {serial}, firmware {firmware})")
            )
        return found

    @staticmethod
    def backend_status() -> list[tuple[str, str]]:
        """The SDK's version, or what to install."""
        try:
            rs = sdk.import_sdk()
        except DriverError:
            return [("realsense", f"missing: pyrealsense2 ({sdk.install_hint()})")]
        return [("realsense", f"pyrealsense2 {sdk.sdk_version(rs)} (the RealSense SDK)")]

    # --- opening ---------------------------------------------------------------------------
    def _check_file(self) -> None:
        """A readable RealSense recording (checked without the SDK, which aborts on some files),
        its depth frames counted."""
        from drivers.formats.rosbag import DepthBag

        assert self.file is not None
        check_path_length(self.file)
        if self.file.suffix.lower() not in SUFFIXES:
            raise RecordingError(
                f"{self.file}: not a RealSense recording (.db3 from SDK 2.56 on, .bag before)",
                hint="RealSense recordings come from realsense-viewer or rs-record; other "
                "recordings play with replay:PATH",
            )
        check_regular(self.file)
        probe = DepthBag(self.file).probe(intrinsics_given=True)
        if not DEPTH_TOPIC.match(probe.depth_topic):
            raise RecordingError(
                f"{self.file}: not a RealSense recording (its depth is on {probe.depth_topic}, "
                "not /device_0/sensor_N/Depth_N/image/data)",
                hint=f"play it with replay:{self.file}",
            )
        self._n_frames = probe.frames

    def _find_device(self, rs: Any) -> Any:
        if self._given_device is not None:
            return self._given_device
        devices = list(self._ctx.query_devices())
        for dev in devices:
            if self.serial is None or sdk.device_info(rs, dev)[1] == self.serial:
                return dev
        seen = ", ".join(sdk.device_info(rs, d)[1] for d in devices) or "none"
        raise DeviceOpenError(
            f"no RealSense camera{' with serial ' + self.serial if self.serial else ''} "
            f"(cameras seen: {seen})",
            hint="plugged in (USB 3)? udev rules (configs/udev/59-depthnav.rules)? "
            "run `depthnav devices`",
            reason=OpenFailure.NOT_FOUND,
        )

    def open(self) -> DeviceInfo:
        """Find the camera (or load the recording) and start its depth (and accel) streams."""
        if self._dev is not None:
            raise DriverError(f"{self.spec_text} is already open")
        if self.file is not None:
            self._check_file()
        rs = self._rs = sdk.import_sdk()
        self._stream = SdkStream(self.file is None, self.spec_text)  # a reopen starts afresh
        try:
            self._ctx = rs.context()
            if self.file is not None:
                try:
                    self._dev = self._ctx.load_device(str(self.file))
                except RuntimeError as exc:
                    raise RecordingError(f"{self.file}: the SDK cannot play it ({exc})") from None
                self._playback = self._dev.as_playback()
                self._playback.set_real_time(self.realtime)
            else:
                self._dev = self._find_device(rs)
                self._ctx.set_devices_changed_callback(self._on_devices_changed)
            info = self._start(rs)
        except RuntimeError as exc:  # the SDK's errors: a camera gone or busy while starting
            self.close()
            if self.file is not None:
                raise RecordingError(f"{self.file}: the SDK cannot play it ({exc})") from None
            raise DeviceOpenError(
                f"{self.spec_text}: starting the depth stream failed: {exc}",
                hint="is another program using the camera? re-plug it",
                reason=OpenFailure.BUSY,
            ) from None
        except BaseException:
            self.close()
            raise
        return info

    def _depth_profile(self, rs: Any, sensor: Any) -> Any:
        depth = [
            p
            for p in sensor.get_stream_profiles()
            if p.stream_type() == rs.stream.depth and p.format() == rs.format.z16
        ]
        if not depth:
            raise self._error("no z16 depth stream", OpenFailure.UNSUPPORTED)
        if self.file is not None:
            return depth[0]
        width, height, fps = self.mode
        for p in depth:
            v = p.as_video_stream_profile()
            if (v.width(), v.height(), p.fps()) == (width, height, fps):
                return p
        videos = [(p.as_video_stream_profile(), p.fps()) for p in depth]
        modes = sorted({f"{v.width()}x{v.height()}@{fps}" for v, fps in videos})
        raise DeviceOpenError(
            f"{self.spec_text}: depth mode {width}x{height}@{fps} not offered",
            hint=f"offered: {', '.join(modes)}",
            reason=OpenFailure.UNSUPPORTED,
        )

    def _error(self, what: str, reason: OpenFailure) -> DriverError:
        if self.file is not None:
            return RecordingError(f"{self.file}: {what}")
        return DeviceOpenError(f"{self.spec_text}: {what}", reason=reason)

    def _set_options(self, rs: Any, sensor: Any) -> None:
        """The visual preset, emitter and laser power of a live camera."""
        wanted = self.preset or DEFAULT_PRESET
        if sensor.supports(rs.option.visual_preset):
            sensor.set_option(
                rs.option.visual_preset, float(getattr(rs.rs400_visual_preset, wanted))
            )
        elif self.preset is not None:
            raise DeviceOpenError(
                f"{self.spec_text}: this camera has no visual presets (preset={self.preset})",
                reason=OpenFailure.UNSUPPORTED,
            )
        for option, value, name in (
            (rs.option.emitter_enabled, self.emitter, "emitter"),
            (rs.option.laser_power, self.laser_power, "laser_power"),
        ):
            if value is None:
                continue
            if not sensor.supports(option):
                raise DeviceOpenError(
                    f"{self.spec_text}: this camera has no {name} option",
                    reason=OpenFailure.UNSUPPORTED,
                )
            low, high = sensor.get_option_range(option).min, sensor.get_option_range(option).max
            if not low <= float(value) <= high:
                raise DeviceSpecError(
                    f"{self.spec_text}: {name}={float(value):g} is outside {low:g}..{high:g}"
                )
            sensor.set_option(option, float(value))

    def _start(self, rs: Any) -> DeviceInfo:
        dev = self._dev
        depth_sensor = dev.first_depth_sensor()
        profile = self._depth_profile(rs, depth_sensor)
        where = str(self.file) if self.file else self.spec_text
        lost = RecordingError if self.file else DeviceOpenError
        base = sdk.profile_intrinsics(profile, where, lost)
        self._intrinsics = with_overrides(base, self.overrides, self.spec_text)
        self._units_um = units_um_from_m(float(depth_sensor.get_depth_scale()), where)
        if self.file is None:
            self._set_options(rs, depth_sensor)
        self._filters = sdk.make_filters(rs, self.filters)
        depth_sensor.open(profile)
        self._sensors.append(depth_sensor)
        # a playback starts reading at the first sensor started and drops the frames of a sensor
        # not started yet: paused until both run, so frame 0 has the sample recorded before it
        if self._playback is not None:
            self._playback.pause()
        has_accel = self._start_accel(rs, profile) if self.accel else False
        depth_sensor.start(self._stream.on_depth)
        if self._playback is not None:
            self._playback.resume()
        name, serial, firmware = sdk.device_info(rs, dev)
        if self.file is not None:
            name = f"RealSense recording {self.file.name}" + (f" ({name})" if name else "")
        elif firmware:
            name = f"{name} (firmware {firmware})"
        log.debug("%s: depth units %g mm, %s", self.spec_text, self._units_um / 1000, base)
        return DeviceInfo(
            name=name,
            serial=serial or None,
            spec=self.spec_text,
            intrinsics=None if "decimation" in self.filters else self._intrinsics,
            has_accel=has_accel,
        )

    def _start_accel(self, rs: Any, depth_profile: Any) -> bool:
        """Open the accelerometer stream (the lowest rate offered: a tilt prior needs a few
        samples a second) when the device has one."""
        for sensor in self._dev.query_sensors():
            accel = [
                p
                for p in sensor.get_stream_profiles()
                if p.stream_type() == rs.stream.accel and p.format() == rs.format.motion_xyz32f
            ]
            if not accel:
                continue
            profile = min(accel, key=lambda p: p.fps())
            rot = sdk.accel_rotation(profile, depth_profile).tolist()
            self._stream.rotation = tuple(tuple(row) for row in rot)
            sensor.open(profile)
            self._sensors.append(sensor)
            sensor.start(self._stream.on_accel)
            self._stream.accel_open = True
            return True
        return False

    def _on_devices_changed(self, event: Any) -> None:
        try:
            if self._dev is not None and event.was_removed(self._dev):
                self._stream.lost.set()
        except RuntimeError:  # the device object itself is gone
            self._stream.lost.set()

    def _stopped(self) -> bool:
        return bool(self._playback.current_status() == self._rs.playback_status.stopped)

    def read_frame(self, timeout_s: float = 1.0) -> Frame | None:
        """The next depth frame; None at the end of a recording.

        Raises:
            FrameTimeout: no frame within ``timeout_s`` (the camera stopped sending).
            DeviceLost: the camera was unplugged.
        """
        if self._dev is None or self._intrinsics is None:
            raise DriverError(f"{self.spec_text} is not open", hint="call open() first")
        if self.file is not None and self._seq >= self._n_frames:
            return None  # every recorded frame given: no waiting out the end
        raw = self._stream.next_frame(timeout_s, self._stopped if self._playback else None)
        if raw is None:
            return None
        intr = self._intrinsics
        if self._filters:
            for block in self._filters:
                raw = block.process(raw)
            intr = self._filtered_intrinsics(raw)
        # the Frame may hold the SDK's buffer for long (a recording, the bench keep every frame):
        # keep() takes it out of the SDK's frame pool, which runs dry at 32 frames held
        raw.keep()
        counts = np.asanyarray(raw.get_data())
        if counts.dtype != np.uint16 or counts.shape != (intr.height, intr.width):
            raise self._bad(
                f"a {counts.dtype} {counts.shape} frame, not {intr.width}x{intr.height}"
            )
        t_ms = float(raw.get_timestamp())
        frame = Frame(
            seq=self._seq,
            timestamp_s=t_ms / 1000.0,
            depth_mm=counts_to_mm(counts, self._units_um),  # 1 mm units: the SDK's buffer
            intrinsics=intr,
            accel_mps2=self._stream.accel_at(t_ms, self._stopped if self._playback else None),
        )
        self._seq += 1
        return frame

    def _filtered_intrinsics(self, raw: Any) -> Intrinsics:
        key = int(raw.get_profile().unique_id())
        if key not in self._profile_intrinsics:
            where = str(self.file) if self.file else self.spec_text
            base = sdk.profile_intrinsics(raw.get_profile(), where)
            self._profile_intrinsics[key] = with_overrides(base, self.overrides, self.spec_text)
        return self._profile_intrinsics[key]

    def _bad(self, what: str) -> DriverError:
        if self.file is not None:
            return RecordingError(f"{self.file}: {what}", hint="re-record it")
        return DeviceLost(f"{self.spec_text}: {what}", hint="re-plug the camera")

    def close(self) -> None:
        """Stop the streams and release the camera or file. Safe to call twice."""
        self._stream.closing.set()  # callbacks waiting for room return
        sensors, self._sensors = self._sensors, []
        for sensor in sensors:
            for step in (sensor.stop, sensor.close):
                try:
                    step()
                except RuntimeError:  # closing must not raise (a camera already gone)
                    log.debug("closing a RealSense sensor failed", exc_info=True)
        self._stream.close()
        if self._ctx is not None and self.file is None:
            try:
                self._ctx.set_devices_changed_callback(lambda _event: None)
            except RuntimeError:
                log.debug("dropping the devices-changed callback failed", exc_info=True)
        self._filters = []
        self._playback = self._dev = self._ctx = None
