"""The fake driver: replays recorded frames as if a sensor were attached.

Spec: ``replay:PATH[?OPTION=VALUE&...]``, the options listed in drivers/spec_options.py (which
``depthnav --help`` prints).

PATH is one of (detected when opened):
- a depthnav recording folder (``recording.toml`` + ``frames.npz``) or a bare ``.npz`` (uint16
  ``depth_mm`` or float ``depth_m`` metres; ``fx, fy, cx, cy`` when it has no intrinsics), or a
  bare ``.npy`` depth array (drivers/formats/npy.py; intrinsics from ``fx, fy, cx, cy``);
- a folder of 16-bit PNG or PGM depth images (see drivers/formats/png_folder.py; ``scale`` units
  per metre from ``camera.toml`` or the option, 5000 for TUM RGB-D; intrinsics from
  ``camera.toml`` or ``fx, fy, cx, cy``; ``glob`` picks the depth images, else colour images
  beside them are skipped);
- a fakenect recording (``INDEX.txt``; disparity converted with ``const_shift``, default 200);
- an ``.oni`` file, played by OpenNI2's libOniFile (see drivers/openni/);
- a ROS bag: ROS 1 ``.bag``, ROS 2 folder, ``.mcap`` or ``.db3`` (see drivers/formats/rosbag.py;
  ``topic`` picks the depth image topic, ``info_topic`` its CameraInfo).

Options: ``rate`` realtime (default; sleep to the recorded timestamps) or max (no sleeping);
``loop`` 1 to start again at the end (time goes on from the pass before: drivers/replay_clock.py);
``fps`` frame rate for sources without timestamps (default 30); ``fx, fy, cx, cy`` override the
intrinsics (pixels); ``start`` skips that many frames when opening (a seek done by reading, as
OpenNI2's own seek hangs; a loop restarts at frame 0); ``glob`` (image folders) a pattern relative
to PATH naming the depth images.

Times handed out always increase: a stamp not after the last one is moved just past it, warned
once (drivers/replay_clock.py).

A depthnav recording whose decoded frames fit in ``CACHE_MAX_BYTES`` is decompressed once and kept
for looping; a larger one is decompressed one frame at a time, again on every loop pass.
"""

from __future__ import annotations

import dataclasses
import logging
import os
import threading
from collections.abc import Callable, Iterator
from pathlib import Path

import numpy as np
import numpy.typing as npt

from drivers.base import (
    KINECT_V1,
    LENS_KEYS,
    DeviceInfo,
    Driver,
    Frame,
    Intrinsics,
    SensorPlacement,
    TiltState,
)
from drivers.errors import DeviceSpecError, DriverError, RecordingError
from drivers.files import check_path_length, check_regular
from drivers.formats import fakenect, png_folder, rosbag
from drivers.formats.npy import iter_npy, open_npy
from drivers.formats.recording import (
    Recording,
    RecordingStream,
    open_recording_stream,
    read_recording,
    recording_depth_nbytes,
)
from drivers.kinect.axes import accel_counts_to_camera, tilt_status_name
from drivers.replay_clock import Pacer, ReplayClock
from drivers.spec import (
    INTRINSICS_OPTIONS,
    Spec,
    bool_option,
    check_options,
    choice_option,
    float_option,
    int_option,
    intrinsics_options,
)
from drivers.spec_options import option_names

log = logging.getLogger(__name__)

OPTIONS = option_names("replay")  # the one table: depthnav --help prints it
GRAMMAR = "replay:PATH[?" + "&".join(f"{name}=.." for name in OPTIONS) + "]"
# Decoded depth up to this size stays in memory for looping (decompressing the 12-frame fixture
# on every pass cost 40 % of the daemon's CPU at 30 frames/s); above it frames are streamed.
CACHE_MAX_BYTES = 256 << 20

Vec3 = tuple[float, float, float]
# (timestamp, depth, accelerometer, tilt motor, odometry)
Item = tuple[float, npt.NDArray[np.uint16], Vec3 | None, TiltState | None, Vec3 | None]


class ReplayDriver:
    """Replays a recording. Construction does no I/O; ``open()`` checks the recording."""

    open_count = 0  # drivers open right now, for leak checks in tests
    _count_lock = threading.Lock()

    def __init__(
        self,
        path: str | Path,
        *,
        realtime: bool = True,
        loop: bool = False,
        fps: float = 30.0,
        intrinsics_override: dict[str, float] | None = None,
        scale: float | None = None,
        const_shift: float = fakenect.CONST_SHIFT,
        start: int = 0,
        spec_text: str = "",
        topic: str | None = None,
        info_topic: str | None = None,
        glob: str | None = None,
        base_frame: str | None = None,
    ) -> None:
        self.path = Path(path)
        self.realtime = realtime
        self.loop = loop
        self.fps = fps
        self.overrides = dict(intrinsics_override or {})
        self.scale = scale
        self.const_shift = const_shift
        self.start = start
        self.spec_text = spec_text or f"replay:{path}"
        self.topics = (topic, info_topic)  # ROS bags: depth image and CameraInfo topics
        self.base_frame = base_frame  # ROS bags: the robot frame /tf_static places the camera in
        self._placement: SensorPlacement | None = None
        self.glob = glob  # image folders: which files are depth
        self._image_list: list[tuple[float, Path]] | None = None  # listed once, kept to loop
        self._items: Iterator[Item] | None = None
        self._recording: Recording | RecordingStream | None = None  # opened once, kept to loop
        self._inner: Driver | None = None
        self._intrinsics: Intrinsics | None = None
        self._seq = 0
        self._clock = ReplayClock(str(self.path), fps)  # loop offsets, increasing times
        self._pacer = Pacer()
        self._is_open = False
        self._has_accel = False
        self._make_items: Callable[[], tuple[Iterator[Item], Intrinsics, str]] | None = None

    @classmethod
    def from_spec(cls, spec: Spec) -> ReplayDriver:
        """Build from ``replay:PATH?...``."""
        check_options(spec, OPTIONS, GRAMMAR)
        if not spec.target:
            raise RecordingError(f"{spec.text!r} names no recording", hint=f"write {GRAMMAR}")
        overrides = intrinsics_options(spec)
        return cls(
            spec.target,
            realtime=choice_option(spec, "rate", ("realtime", "max"), "realtime") == "realtime",
            loop=bool_option(spec, "loop", False),
            fps=float_option(spec, "fps", 30.0, 0.1, 1000.0) or 30.0,
            intrinsics_override=overrides,
            scale=float_option(spec, "scale", None, 1.0, 1e6),
            const_shift=float_option(spec, "const_shift", fakenect.CONST_SHIFT, 0.0, 1000.0)
            or fakenect.CONST_SHIFT,
            spec_text=spec.text,
            start=int_option(spec, "start", 0, 0, 10_000_000),
            topic=spec.options.get("topic"),
            info_topic=spec.options.get("info_topic"),
            glob=spec.options.get("glob"),
            base_frame=spec.options.get("base_frame"),
        )

    # --- sources -------------------------------------------------------------------------
    def _intrinsics_with(
        self, base: Intrinsics | None, shape: tuple[int, int] | None
    ) -> Intrinsics:
        height, width = shape if shape else ((base.height, base.width) if base else (0, 0))
        if base is None:
            missing = [k for k in ("fx", "fy", "cx", "cy") if k not in self.overrides]
            if missing:
                raise RecordingError(
                    f"{self.path}: no intrinsics ({', '.join(missing)} unknown)",
                    hint=f"add a {png_folder.SIDECAR} with an [intrinsics] table, "
                    "or ?fx=..&fy=..&cx=..&cy=..",
                )
            values = dict(self.overrides)
        else:
            # every lens field, not only the options': a rational or fisheye lens kept whole
            values = {
                k: getattr(base, k) for k in (*INTRINSICS_OPTIONS, *LENS_KEYS)
            } | self.overrides
        try:
            return Intrinsics(width, height, **values)
        except ValueError as exc:
            if any(key in self.overrides for key in INTRINSICS_OPTIONS):
                # the user's ?fx=..&cx=.. options do not fit this recording: a usage error (exit 2)
                raise DeviceSpecError(
                    f"{self.spec_text}: intrinsics options do not fit the {width}x{height} "
                    f"image: {exc}"
                ) from None
            raise RecordingError(f"{self.path}: bad intrinsics: {exc}") from None

    def _open_depthnav(self) -> Recording | RecordingStream:
        """The recording decoded in memory when it fits CACHE_MAX_BYTES, else a frame stream."""
        if recording_depth_nbytes(self.path) <= CACHE_MAX_BYTES:
            # the cap again: the member decoded is the one whose size was just read
            return read_recording(
                self.path,
                default_fps=self.fps,
                max_depth_bytes=CACHE_MAX_BYTES,
                intrinsics_override=self.overrides,
            )
        return open_recording_stream(
            self.path, default_fps=self.fps, intrinsics_override=self.overrides
        )

    def _depthnav_items(self) -> tuple[Iterator[Item], Intrinsics, str]:
        rec = self._recording
        if rec is None:
            rec = self._recording = self._open_depthnav()
        self._has_accel = rec.accel_mps2 is not None
        intr = self._intrinsics_with(rec.intrinsics, None)
        # rows of the decoded array, or frames decompressed from the file anew on this pass
        depth = rec.depth_mm if isinstance(rec, Recording) else rec.iter_depth()

        def items() -> Iterator[Item]:
            for i, frame in enumerate(depth):
                # a row's tolist() makes Python floats at once (map(float, row) cost ~1.8 us a
                # frame, a percent of the frame loop)
                accel = None if rec.accel_mps2 is None else tuple(rec.accel_mps2[i].tolist())
                odom = None if rec.odom is None else tuple(rec.odom[i].tolist())
                yield rec.timestamp_s.item(i), frame, accel, None, odom  # type: ignore[misc]

        return items(), intr, rec.description or self.path.name

    def _png_items(self) -> tuple[Iterator[Item], Intrinsics, str]:
        side = png_folder.read_sidecar(self.path)
        no_intrinsics = "intrinsics" not in side and not all(
            k in self.overrides for k in ("fx", "fy", "cx", "cy")
        )
        if self.scale is None and "depth_scale" not in side and no_intrinsics:
            if not png_folder.is_tum(self.path):
                raise RecordingError(
                    f"{self.path}: the depth scale and the intrinsics (fx, fy, cx, cy) are not "
                    f"stated (no {png_folder.SIDECAR}, no scale= or fx=)",
                    hint=f"add a {png_folder.SIDECAR} with depth_scale and an [intrinsics] "
                    "table, or give them in the spec: "
                    "replay:PATH?scale=1000&fx=..&fy=..&cx=..&cy=.. "
                    "(scale 1000 for millimetre PNGs, 5000 for TUM RGB-D)",
                )
        scale = self.scale or png_folder.sidecar_scale(self.path, side)
        if self._image_list is None:  # picking the depth images reads every file's header
            self._image_list = png_folder.list_frames(self.path, self.fps, self.glob)
        frames = self._image_list
        first = png_folder.read_depth_image(frames[0][1], scale)
        base = png_folder.sidecar_intrinsics(self.path, side, first.shape)
        intr = self._intrinsics_with(base, first.shape)

        def items() -> Iterator[Item]:
            for stamp, depth in png_folder.iter_png_folder(
                self.path, intr, scale, self.fps, frames
            ):
                yield stamp, depth, None, None, None

        return items(), intr, self.path.name

    def _npy_items(self) -> tuple[Iterator[Item], Intrinsics, str]:
        npy = open_npy(self.path)
        intr = self._intrinsics_with(None, npy.shape[1:])

        def items() -> Iterator[Item]:
            for i, depth in enumerate(iter_npy(npy)):
                yield i / self.fps, depth, None, None, None

        return items(), intr, self.path.name

    def _fakenect_items(self) -> tuple[Iterator[Item], Intrinsics, str]:
        entries = fakenect.read_index(self.path)  # fail at open, not at the first frame
        self._has_accel = any(e.kind == "a" for e in entries)
        # the camera.toml write_fakenect leaves for another camera than the format's Kinect v1
        intr = self._intrinsics_with(fakenect.folder_intrinsics(self.path) or KINECT_V1, None)

        def items() -> Iterator[Item]:
            for stamp, depth, dump in fakenect.iter_fakenect(self.path, self.const_shift):
                accel = tilt = None
                if dump is not None:
                    accel = accel_counts_to_camera(*dump[:3])
                    tilt = TiltState(dump[3] / 2.0, tilt_status_name(dump[4]))
                yield stamp, depth, accel, tilt, None

        return items(), intr, self.path.name

    def _rosbag_items(self) -> tuple[Iterator[Item], Intrinsics, str]:
        # the bag reader opens its files itself: regular files only (a FIFO would block it)
        if self.path.is_dir():
            for part in sorted(self.path.iterdir()):
                if part.suffix.lower() in (*rosbag.SUFFIXES, ".yaml"):
                    check_regular(part)
        else:
            check_regular(self.path)
        bag = rosbag.DepthBag(self.path, *self.topics, base_frame=self.base_frame)
        probe = bag.probe(
            intrinsics_given=all(k in self.overrides for k in ("fx", "fy", "cx", "cy"))
        )
        self._has_accel = probe.imu_topic is not None
        self._placement = probe.placement
        base = None if probe.camera is None else probe.camera.intrinsics
        intr = self._intrinsics_with(base, probe.shape)
        items = ((stamp, depth, accel, None, None) for stamp, depth, accel in bag.frames())
        return items, intr, f"{self.path.name} {probe.depth_topic}"

    def _start(self) -> None:
        if self._make_items is None:  # the kind of recording: found once, not on every loop pass
            self._make_items = self._items_maker()
        self._items, intr, name = self._make_items()
        if self._intrinsics is not None and intr != self._intrinsics:
            raise RecordingError(f"{self.path}: intrinsics changed while looping")
        self._intrinsics = intr
        self._name = name

    def _items_maker(self) -> Callable[[], tuple[Iterator[Item], Intrinsics, str]]:
        if rosbag.is_rosbag(self.path) and self.path.exists():
            return self._rosbag_items
        if self.path.is_dir():
            if (self.path / "recording.toml").exists():
                return self._depthnav_items
            if (self.path / "INDEX.txt").exists():
                return self._fakenect_items
            if self.glob is not None or png_folder.is_png_folder(self.path):
                return self._png_items
            raise RecordingError(
                f"{self.path}: not a recording folder "
                "(no recording.toml, INDEX.txt, depth.txt, *.png or *.pgm)",
                hint="record one with `depthnav record`, or name the depth images with "
                "replay:PATH?glob=PATTERN",
            )
        if self.glob is not None:
            raise RecordingError(
                f"{self.path}: glob= picks images in a folder; this is not a folder",
                hint="write replay:FOLDER?glob=PATTERN",
            )
        if self.path.suffix.lower() == ".npz":
            return self._depthnav_items
        if self.path.suffix.lower() == ".npy":
            return self._npy_items
        if not self.path.exists():
            raise RecordingError(f"{self.path}: no such file or folder", hint="check the path")
        raise RecordingError(
            f"{self.path}: unknown recording type {self.path.suffix or '(no suffix)'!r}",
            hint="replay takes a recording folder, .npz, .npy, image folder, fakenect folder, "
            ".oni or a ROS bag (.bag, .mcap, .db3, ROS 2 bag folder)",
        )

    # --- Driver protocol -----------------------------------------------------------------
    def open(self) -> DeviceInfo:
        """Check the recording and get ready to replay it."""
        if self._is_open:
            raise DriverError(f"replay {self.path} is already open")
        check_path_length(self.path)  # a 300-byte name: one line, not OSError errno 36
        if (
            self.path.suffix.lower() == ".oni"
            and os.path.lexists(self.path)
            and not self.path.is_dir()
        ):
            from drivers.openni.driver import OpenNIDriver  # only .oni replay needs OpenNI2

            self._inner = OpenNIDriver.for_file(
                self.path,
                realtime=self.realtime,
                loop=self.loop,
                spec_text=self.spec_text,
                intrinsics_override=self.overrides,
            )
            info = self._inner.open()
        else:
            self._start()
            assert self._intrinsics is not None
            info = DeviceInfo(
                name=f"replay: {self._name}",
                serial=None,
                spec=self.spec_text,
                intrinsics=self._intrinsics,
                has_accel=self._has_accel,
                placement=self._placement,
            )
        self._is_open = True
        with ReplayDriver._count_lock:
            ReplayDriver.open_count += 1
        try:
            self._skip(self.start)
        except BaseException:
            self.close()
            raise
        return info

    def _skip(self, count: int) -> None:
        for skipped in range(count):
            if self._inner is not None:
                item: object = self._inner.read_frame(5.0)
            else:
                item = self._next_item()
            if item is None:
                raise RecordingError(
                    f"{self.path}: start={count} is beyond the end ({skipped} frames)",
                    hint="choose a smaller start",
                )

    def read_frame(self, timeout_s: float = 1.0) -> Frame | None:
        """The next recorded frame, paced when ``rate=realtime``; None at the end."""
        if not self._is_open:
            raise DriverError(f"replay {self.path} is not open", hint="call open() first")
        if self._inner is not None:
            frame = self._inner.read_frame(timeout_s)
            if frame is None:
                return None
            # seq counts from 0 after a start skip; OpenNI loops the file and shifts time itself
            t_s = self._clock.time(frame.timestamp_s, self._seq, shift=False)
            frame = dataclasses.replace(frame, seq=self._seq, timestamp_s=t_s)
            self._seq += 1
            return frame
        assert self._intrinsics is not None
        item = self._next_item()
        if item is None and self.loop and self._seq > 0:
            self._clock.next_pass()
            self._start()
            item = self._next_item()
        if item is None:
            return None
        stamp, depth, accel, tilt, odom = item
        t_s = self._clock.time(stamp, self._seq)
        if self.realtime:
            self._pacer.wait(t_s, timeout_s)
        frame = Frame(
            seq=self._seq,
            timestamp_s=t_s,
            # no copy: a recording's frames are never written, and Frame makes this view
            # read-only (copying an already decoded frame cost 10-19 % of the loop)
            depth_mm=np.ascontiguousarray(depth, dtype=np.uint16).view(),
            intrinsics=self._intrinsics,
            accel_mps2=accel,
            tilt=tilt,
            odom=odom,
        )
        self._seq += 1
        return frame

    def _next_item(self) -> Item | None:
        """The next recorded item of this pass; its stamp noted for the loop offset."""
        assert self._items is not None
        item = next(self._items, None)
        if item is not None:
            self._clock.note(item[0])
        return item

    def close(self) -> None:
        """Stop replaying. Safe to call twice."""
        if self._inner is not None:
            self._inner.close()
            self._inner = None
        items, self._items = self._items, None
        if hasattr(items, "close"):
            items.close()  # a ROS bag's generator closes its reader
        self._recording = None
        self._clock.close()
        if self._is_open:
            self._is_open = False
            with ReplayDriver._count_lock:
                ReplayDriver.open_count -= 1
