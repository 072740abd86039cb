"""libfreenect (Kinect 360 depth) reached with ctypes: the real library or Debian's fakenect.

Only the C calls depthnav needs are bound. A background thread runs
``freenect_process_events_timeout``; the depth callback copies each frame into a small queue.
Debian's fakenect (``/usr/lib/<arch>/fakenect/libfreenect.so.0.5``) has the same API and plays a
recording named by the ``FAKENECT_PATH`` environment variable; its state is process-global, so
play one fakenect recording per process.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import logging
import queue
import threading
import time
from pathlib import Path

import numpy as np
import numpy.typing as npt

from drivers.errors import DeviceOpenError, DriverNotAvailable, OpenFailure
from drivers.native import NATIVE_LIB_DIRS

log = logging.getLogger(__name__)

LIB_NAME = "libfreenect.so.0.5"
WIDTH, HEIGHT = 640, 480

RESOLUTION_MEDIUM = 1
DEPTH_11BIT, DEPTH_MM = 0, 5
DEVICE_MOTOR, DEVICE_CAMERA = 0x01, 0x02
LIBUSB_ERROR_INTERRUPTED = -10


class FrameMode(ctypes.Structure):
    """``freenect_frame_mode``."""

    _fields_ = [
        ("reserved", ctypes.c_uint32),
        ("resolution", ctypes.c_int),
        ("format", ctypes.c_int32),
        ("bytes", ctypes.c_int32),
        ("width", ctypes.c_int16),
        ("height", ctypes.c_int16),
        ("data_bits_per_pixel", ctypes.c_int8),
        ("padding_bits_per_pixel", ctypes.c_int8),
        ("framerate", ctypes.c_int8),
        ("is_valid", ctypes.c_int8),
    ]


class RawTiltState(ctypes.Structure):
    """``freenect_raw_tilt_state``: accelerometer counts, tilt half-degrees, status."""

    _fields_ = [
        ("accelerometer_x", ctypes.c_int16),
        ("accelerometer_y", ctypes.c_int16),
        ("accelerometer_z", ctypes.c_int16),
        ("tilt_angle", ctypes.c_int8),
        ("tilt_status", ctypes.c_int),
    ]


class TimeVal(ctypes.Structure):
    """``struct timeval``."""

    _fields_ = [("tv_sec", ctypes.c_long), ("tv_usec", ctypes.c_long)]


DEPTH_CB = ctypes.CFUNCTYPE(None, ctypes.c_void_p, ctypes.c_void_p, ctypes.c_uint32)


def find_library(fakenect: bool = False) -> Path | None:
    """The real libfreenect (or Debian's fakenect build), or None."""
    for folder in NATIVE_LIB_DIRS:
        path = Path(folder) / ("fakenect" if fakenect else "") / LIB_NAME
        if path.exists():
            return path
    if not fakenect:
        name = ctypes.util.find_library("freenect")
        return Path(name) if name else None
    return None


def load(path: Path) -> ctypes.CDLL:
    """Load a libfreenect build and declare the functions used."""
    try:
        lib = ctypes.CDLL(str(path))
    except OSError as exc:
        raise DriverNotAvailable(
            f"cannot load libfreenect at {path}: {exc}", hint="apt-get install libfreenect0.5"
        ) from None
    vp, pp = ctypes.c_void_p, ctypes.POINTER(ctypes.c_void_p)
    signatures = {
        "freenect_init": ([pp, vp], ctypes.c_int),
        "freenect_shutdown": ([vp], ctypes.c_int),
        "freenect_select_subdevices": ([vp, ctypes.c_int], None),
        "freenect_num_devices": ([vp], ctypes.c_int),
        "freenect_open_device": ([vp, pp, ctypes.c_int], ctypes.c_int),
        "freenect_close_device": ([vp], ctypes.c_int),
        "freenect_find_depth_mode": ([ctypes.c_int, ctypes.c_int], FrameMode),
        "freenect_set_depth_mode": ([vp, FrameMode], ctypes.c_int),
        "freenect_set_depth_callback": ([vp, DEPTH_CB], None),
        "freenect_start_depth": ([vp], ctypes.c_int),
        "freenect_stop_depth": ([vp], ctypes.c_int),
        "freenect_process_events_timeout": ([vp, ctypes.POINTER(TimeVal)], ctypes.c_int),
        "freenect_update_tilt_state": ([vp], ctypes.c_int),
        "freenect_get_tilt_state": ([vp], ctypes.POINTER(RawTiltState)),
    }
    for name, (args, res) in signatures.items():
        try:
            func = getattr(lib, name)
        except AttributeError:
            raise DriverNotAvailable(
                f"{path} lacks {name}; not a libfreenect 0.5 build",
                hint="apt-get install libfreenect0.5",
            ) from None
        func.argtypes, func.restype = args, res
    return lib


class FreenectDepth:
    """Depth frames from one device through libfreenect.

    Args:
        lib_path: the library to load (real or fakenect).
        index: device index.
        use_motor: let libfreenect open the motor too (for its tilt API); False leaves the
            motor device free for pyusb.
        want_mm: ask libfreenect for millimetres (its registration with the device's own
            constants); fakenect 0.5.3 aborts on that request, so pass False for it.
        max_events: stop after this many successful event calls (fakenect: its index length).
    """

    def __init__(
        self,
        lib_path: Path,
        index: int = 0,
        use_motor: bool = False,
        want_mm: bool = True,
        max_events: int | None = None,
    ) -> None:
        self.lib_path = lib_path
        self.max_events = max_events
        self.want_mm = want_mm
        self.index = index
        self.use_motor = use_motor
        self.is_mm = False
        self._lib: ctypes.CDLL | None = None
        self._ctx = ctypes.c_void_p()
        self._dev = ctypes.c_void_p()
        self._queue: queue.Queue[tuple[float, npt.NDArray[np.uint16]]] = queue.Queue(maxsize=4)
        self._stop = threading.Event()
        self.ended = threading.Event()
        self.end_status = 0
        self._thread: threading.Thread | None = None
        self._callback = DEPTH_CB(self._on_depth)  # keep a reference for the C side

    def open(self) -> None:
        """Initialise, open the device and start the depth stream."""
        lib = self._lib = load(self.lib_path)
        if lib.freenect_init(ctypes.byref(self._ctx), None) < 0:
            raise DeviceOpenError(
                "libfreenect failed to initialise (no USB access?)",
                hint="check udev rules for 045e:02ae",
                reason=OpenFailure.PERMISSION,
            )
        lib.freenect_select_subdevices(
            self._ctx, DEVICE_CAMERA | (DEVICE_MOTOR if self.use_motor else 0)
        )
        count = lib.freenect_num_devices(self._ctx)
        if count <= self.index:
            self.close()
            raise DeviceOpenError(
                f"no Kinect found (045e:02ae/02b0) at index {self.index} ({count} found): "
                "plugged in? "
                "udev rules? run `depthnav devices`",
                reason=OpenFailure.NOT_FOUND,
            )
        if lib.freenect_open_device(self._ctx, ctypes.byref(self._dev), self.index) < 0:
            self.close()
            raise DeviceOpenError(
                f"could not open Kinect {self.index} (busy or no permission)",
                hint="close other Kinect programs; check udev rules",
                reason=OpenFailure.BUSY,
            )
        if self.want_mm:
            mode = lib.freenect_find_depth_mode(RESOLUTION_MEDIUM, DEPTH_MM)
            self.is_mm = bool(mode.is_valid) and lib.freenect_set_depth_mode(self._dev, mode) == 0
        if not self.is_mm:  # fakenect 0.5.3 gives 11-bit disparity only
            mode = lib.freenect_find_depth_mode(RESOLUTION_MEDIUM, DEPTH_11BIT)
            if not mode.is_valid or lib.freenect_set_depth_mode(self._dev, mode) < 0:
                self.close()
                raise DeviceOpenError(
                    "libfreenect refused the 640x480 depth mode", reason=OpenFailure.UNSUPPORTED
                )
        lib.freenect_set_depth_callback(self._dev, self._callback)
        if lib.freenect_start_depth(self._dev) < 0:
            self.close()
            raise DeviceOpenError("libfreenect could not start the depth stream")
        self._thread = threading.Thread(target=self._pump, name="freenect-events", daemon=True)
        self._thread.start()

    def _on_depth(self, _dev: int | None, data: int | None, _timestamp: int) -> None:
        if not data:
            return
        buf = (ctypes.c_uint16 * (WIDTH * HEIGHT)).from_address(data)
        frame = (
            np.frombuffer(buf, dtype=np.uint16).reshape(HEIGHT, WIDTH).copy()
        )  # C reuses the buffer
        item = (time.monotonic(), frame)
        try:
            self._queue.put_nowait(item)
        except queue.Full:  # the reader is slow: drop the oldest frame, keep the newest
            try:
                self._queue.get_nowait()
            except queue.Empty:
                pass
            self._queue.put_nowait(item)

    def _pump(self) -> None:
        assert self._lib is not None
        tv = TimeVal(0, 100_000)
        done = 0
        while not self._stop.is_set():
            if self.max_events is not None and done >= self.max_events:
                break
            status = self._lib.freenect_process_events_timeout(self._ctx, ctypes.byref(tv))
            if status == LIBUSB_ERROR_INTERRUPTED:  # a signal arrived; not a device problem
                continue
            if status < 0:
                self.end_status = status
                break
            done += 1
        self.ended.set()

    def get(self, timeout_s: float) -> tuple[float, npt.NDArray[np.uint16]] | None:
        """The next (host time s, (480, 640) uint16) frame, or None if none came in time."""
        deadline = time.monotonic() + timeout_s
        while True:
            try:
                return self._queue.get(timeout=min(0.05, max(deadline - time.monotonic(), 0.001)))
            except queue.Empty:
                if self.ended.is_set() and self._queue.empty():
                    return None
                if time.monotonic() >= deadline:
                    return None

    def tilt_state(self) -> tuple[int, int, int, int, int]:
        """(x, y, z counts, tilt half-degrees, status) from libfreenect's tilt API."""
        assert self._lib is not None
        self._lib.freenect_update_tilt_state(self._dev)
        st = self._lib.freenect_get_tilt_state(self._dev).contents
        return (
            st.accelerometer_x,
            st.accelerometer_y,
            st.accelerometer_z,
            st.tilt_angle,
            st.tilt_status,
        )

    def close(self, wait_s: float = 2.0) -> None:
        """Stop the event thread and release the device. Safe to call twice.

        Args:
            wait_s: how long to wait for the event thread. One still inside the library after
                that (fakenect sleeps there until the next recorded event) is left alone, and so
                is the library: tearing it down under the thread could crash the process.
        """
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=wait_s)
            if self._thread.is_alive():
                say = log.debug if wait_s < 1.0 else log.warning  # fakenect: expected
                say("libfreenect event thread still busy after %.1f s; left to end", wait_s)
                self._thread = None
                self._lib = None  # no call into the library while the thread may be in it
                return
            self._thread = None
        lib, self._lib = self._lib, None
        if lib is None:
            return
        if self._dev:
            lib.freenect_stop_depth(self._dev)
            lib.freenect_close_device(self._dev)
            self._dev = ctypes.c_void_p()
        if self._ctx:
            lib.freenect_shutdown(self._ctx)
            self._ctx = ctypes.c_void_p()
