"""Which mount the stages use for a frame, so that a small mount change never stalls the loop.

The scan and cliff stages precompute tables per camera and mount (30-70 ms at 640x480). When the
mount tracker moves the mount by a little (the smoothed floor estimate drifting), the tables for
the new mount are built on a worker thread while the frames go on with the mount whose tables
exist; the new mount is used from the first frame after they are ready. A large change (the
first floor estimate, a confirmed jump, a new tilt source) is used at once: then a frame late by
the build beats a frame processed with a wrong mount.
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable
from dataclasses import dataclass

from depthnav_daemon.pipeline.geometry import Mount
from drivers.base import Intrinsics

log = logging.getLogger(__name__)

# the stages keep the tables of their 16 latest mounts (functools.lru_cache); remembering fewer
# keeps "ready" true, and the memory of a long run with a drifting mount bounded
KEEP_READY = 8


@dataclass(frozen=True, slots=True)
class SmallChange:
    """A mount change at most this large may wait for its tables (metres, degrees)."""

    height_m: float = 0.01
    angle_deg: float = 0.5

    def holds(self, a: Mount, b: Mount) -> bool:
        """True if ``a`` and ``b`` differ by no more than this."""
        return (
            abs(a.height_m - b.height_m) <= self.height_m
            and abs(a.tilt_deg - b.tilt_deg) <= self.angle_deg
            and abs(a.roll_deg - b.roll_deg) <= self.angle_deg
        )


class StageTables:
    """Picks the mount for each frame and builds tables for small changes off the frame loop.

    Args:
        prepare: builds (and caches) the stages' tables for (intrinsics, mount); may raise.
        small: which changes may wait for their tables.
    """

    def __init__(
        self, prepare: Callable[[Intrinsics, Mount], None], small: SmallChange | None = None
    ) -> None:
        self._prepare = prepare
        self._small = small or SmallChange()
        self._ready: list[tuple[Intrinsics, Mount]] = []  # latest last
        self._applied: tuple[Intrinsics, Mount] | None = None
        self._job: tuple[tuple[Intrinsics, Mount], threading.Thread] | None = None
        self._failed: set[tuple[Intrinsics, Mount]] = set()  # a worker's build raised
        self._lock = threading.Lock()

    def mount_for(self, intr: Intrinsics, wanted: Mount) -> Mount:
        """The mount to process a frame of camera ``intr`` with, given the tracker's ``wanted``."""
        self._collect()
        key = (intr, wanted)
        applied = self._applied
        if (
            applied is None
            or applied[0] != intr
            or key in self._ready
            or key in self._failed  # the frame loop meets the error itself, as without a worker
            or not self._small.holds(applied[1], wanted)
        ):
            self._mark_ready(key)  # built now by the stages, on this frame
            self._applied = key
            return wanted
        if self._job is None:
            self._start(key)
        return applied[1]

    def close(self, timeout_s: float = 5.0) -> None:
        """Wait for a running build (it holds no resource; this only keeps shutdown tidy)."""
        if self._job is not None:
            self._job[1].join(timeout_s)

    def _start(self, key: tuple[Intrinsics, Mount]) -> None:
        def build() -> None:
            try:
                self._prepare(*key)
            except Exception as exc:
                log.debug("building the tables for %s failed: %s", key[1], exc)
                with self._lock:
                    self._failed.add(key)

        thread = threading.Thread(target=build, name="depthnav-tables", daemon=True)
        self._job = (key, thread)
        thread.start()

    def _collect(self) -> None:
        """Note a finished build."""
        if self._job is None or self._job[1].is_alive():
            return
        key = self._job[0]
        self._job = None
        with self._lock:
            if key not in self._failed:
                self._mark_ready(key)

    def _mark_ready(self, key: tuple[Intrinsics, Mount]) -> None:
        if key in self._ready:
            self._ready.remove(key)
        self._ready.append(key)
        del self._ready[:-KEEP_READY]
