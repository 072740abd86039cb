"""Frames from the SDK's threads to the driver's reader: the depth queue, the accelerometer
samples, and the waits with their end, timeout and unplug conditions.

The SDK calls ``on_depth``/``on_accel`` on its own threads; they only queue. Live, the depth
queue keeps the newest ``LIVE_QUEUE`` frames (a slow daemon sees fresh ones). From a file the
playback runs in non-real-time mode and ``on_depth`` waits for room, which paces the SDK's reader
so no frame is dropped (a ``frame_queue`` handed to ``sensor.start`` instead would block inside
the binding while holding the GIL, and the reader could never empty it: a deadlock).
"""

from __future__ import annotations

import collections
import math
import queue
import threading
import time
from collections.abc import Callable
from typing import Any

from drivers.errors import DeviceLost, FrameTimeout

LIVE_QUEUE = 2  # frames kept for a slow reader: the newest win
FILE_QUEUE = 8  # frames read ahead from a file before the SDK's reader waits
# ... until the reader has taken it down to this many: one wake-up per few frames (waking the
# SDK's thread on every frame cost ~50 us of the reader's time a frame)
FILE_QUEUE_LOW = 4
ACCEL_KEEP = 1024  # accelerometer samples kept until a depth frame's time passes them
POLL_S = 0.05  # how often a wait looks at the device-lost and end-of-file flags
PUT_WAIT_S = 0.1  # how long the callback waits for room before looking at the closing flag
END_GRACE_S = 0.3  # after the SDK's reader stopped: a frame still being dispatched arrives by then
# a file's accelerometer samples come on another SDK thread than its depth: a frame waits this
# long at most for the samples up to its time (so frame 0 gets the sample recorded before it)
ACCEL_CATCHUP_S = 0.05
IDENTITY = ((1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0))

Vec3 = tuple[float, float, float]


class SdkStream:
    """The depth frames and accelerometer samples the SDK's callbacks deliver.

    Args:
        live: a camera (newest frames win) rather than a file (every frame, in order).
        what: the spec, for messages.
    """

    def __init__(self, live: bool, what: str) -> None:
        self.live = live
        self.what = what
        self.closing = threading.Event()
        self.lost = threading.Event()
        self._queue: queue.Queue[Any] = queue.Queue(LIVE_QUEUE if live else FILE_QUEUE)
        self._room = threading.Event()  # a file's queue is down to FILE_QUEUE_LOW
        self._accel: collections.deque[tuple[float, Vec3]] = collections.deque(maxlen=ACCEL_KEEP)
        self._accel_now: Vec3 | None = None
        self._accel_newest_ms = -math.inf
        self.accel_open = False  # set by the driver once the accelerometer stream runs
        self.rotation: tuple[tuple[float, ...], ...] = IDENTITY  # accel axes -> depth axes

    # --- SDK threads -----------------------------------------------------------------------
    def on_depth(self, frame: Any) -> None:
        """The SDK's depth callback."""
        if self.closing.is_set():
            return
        if self.live:
            while True:
                try:
                    self._queue.put_nowait(frame)
                    return
                except queue.Full:
                    try:
                        self._queue.get_nowait()  # drop the oldest
                    except queue.Empty:
                        pass
        while not self.closing.is_set():  # a file: wait for room (paces the SDK's reader)
            try:
                self._queue.put_nowait(frame)
                return
            except queue.Full:
                self._room.clear()
            try:  # the reader may have made room between the two
                self._queue.put_nowait(frame)
                return
            except queue.Full:
                self._room.wait(PUT_WAIT_S)  # a wake-up missed costs PUT_WAIT_S, never a hang

    def on_accel(self, frame: Any) -> None:
        """The SDK's accelerometer callback: (timestamp ms, specific force m/s^2) kept."""
        data = frame.as_motion_frame().get_motion_data()
        t_ms = float(frame.get_timestamp())
        self._accel.append((t_ms, (data.x, data.y, data.z)))
        self._accel_newest_ms = t_ms

    # --- the reader ------------------------------------------------------------------------
    def next_frame(self, timeout_s: float, stopped: Callable[[], bool] | None) -> Any:
        """The next SDK depth frame; None at the end of a file.

        Args:
            timeout_s: how long to wait for a frame.
            stopped: for a file, whether the SDK's reader has reached the end.

        Raises:
            DeviceLost: the camera was unplugged (``lost`` set).
            FrameTimeout: no frame within ``timeout_s``.
        """
        deadline = time.monotonic() + max(timeout_s, 0.0)
        stopped_at: float | None = None
        while True:
            if self.lost.is_set():
                raise DeviceLost(
                    f"{self.what}: the camera was unplugged", hint="re-plug it (a USB 3 port)"
                )
            try:  # a frame is usually waiting: no timed wait then
                return self._taken(self._queue.get_nowait())
            except queue.Empty:
                pass
            try:
                return self._taken(self._queue.get(timeout=POLL_S))
            except queue.Empty:
                pass
            now = time.monotonic()
            if stopped is not None and stopped():
                stopped_at = stopped_at or now
                if now - stopped_at >= END_GRACE_S:
                    return None
            elif now >= deadline:
                raise FrameTimeout(
                    f"{self.what}: no depth frame within {timeout_s:g} s",
                    hint="is the camera on a USB 3 port, and not covered?",
                )

    def _taken(self, frame: Any) -> Any:
        if not self.live and not self._room.is_set() and self._queue.qsize() <= FILE_QUEUE_LOW:
            self._room.set()
        return frame

    def accel_at(self, t_ms: float, stopped: Callable[[], bool] | None = None) -> Vec3 | None:
        """The newest accelerometer sample at or before ``t_ms`` (the SDK's clock, ms), in the
        depth axes; the one before when none is newer; None before the first.

        From a file (``stopped`` given) it first waits, up to ACCEL_CATCHUP_S, for a sample
        after ``t_ms`` or the end of the file: the samples up to this frame are then in.
        """
        if stopped is not None and self.accel_open and self._accel_newest_ms <= t_ms:
            until = time.monotonic() + ACCEL_CATCHUP_S
            while self._accel_newest_ms <= t_ms and time.monotonic() < until and not stopped():
                time.sleep(0.001)
        samples = self._accel
        latest = None
        while samples and samples[0][0] <= t_ms:
            latest = samples.popleft()[1]
        if latest is not None:
            # plain floats: numpy's matmul and isfinite on 3 values cost ~40 us a frame
            (a, b, c), (d, e, f), (g, h, i) = self.rotation
            x, y, z = latest
            vec = (a * x + b * y + c * z, d * x + e * y + f * z, g * x + h * y + i * z)
            if all(map(math.isfinite, vec)):
                self._accel_now = (vec[0] + 0.0, vec[1] + 0.0, vec[2] + 0.0)  # no -0.0
        return self._accel_now

    def close(self) -> None:
        """Release waiting callbacks and drop the queued frames (the SDK's buffers)."""
        self.closing.set()
        self._room.set()
        while True:
            try:
                self._queue.get_nowait()
            except queue.Empty:
                return
