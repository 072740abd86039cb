"""The daemon's side of the obstacle memory: which odometry pose goes with each frame, and whether
the memory may use it.

The memory (pipeline/memory.py) is only as good as the odometry it is given, so this module never
lets a doubtful pose in:
- no odometry at all (no source, frames without ``odom``): the memory is off, said once;
- a source that has not spoken for ``timeout_s``: off until it does, said once;
- odometry older than ``stale_s`` at a frame: the memory is frozen (not updated, nothing read back),
  said once per stale spell; it resumes when fresh odometry comes back (the odometry frame is
  continuous, so what it holds is still right);
- odometry that moves more than ``max_jump_m`` / ``max_jump_deg`` between two frames: the memory
  is forgotten and restarted with the frame (a relocalisation or a restarted odometry is not
  motion), said every time;
- a pose outside the odometry limits (drivers.base.check_odom_pose: a recording's NaN or 1e19,
  or anything a source let through): the memory is frozen for that frame; refusals are counted
  per kind with the source's own and go out with every frame (``odometry_rejected``).
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Callable, Sequence

from depthnav_daemon.config.loader import MemorySettings, OdometrySettings
from depthnav_daemon.pipeline import Result, StageParams
from depthnav_daemon.pipeline.cliff import CliffParams
from depthnav_daemon.pipeline.memory import (
    MemoryResult,
    SensorView,
    new_state,
    read_scan,
    reset,
    snapshot,
    update,
)
from depthnav_daemon.pipeline.scan_table import scan_rows
from drivers.base import Frame, OdomRefusal, check_odom_pose
from drivers.odometry import OdometrySource, OdomRefusals
from drivers.values import short_repr

log = logging.getLogger(__name__)

Pose = tuple[float, float, float]


def sensor_view(result: Result, params: StageParams) -> SensorView:
    """What the memory needs of one sensor's Result: its level-frame scans, the rows each stage
    read (the memory clears only the floor those rows see, coverage.floor_extent) and the row
    margins of what they found.

    The memory's blind radius and range_max (pipeline.memory.scan_limits) follow from these views'
    mounts and scans unless [memory] sets them. ``short_free`` / ``cliff_short_free`` stay None:
    the Result does not say which of its NaN bins are the coverage rule's over floor seen free,
    so those bins clear nothing (safe; the view's edge bins add no free knowledge).
    """
    rows = scan_rows(result.intrinsics, params.scan)
    cliff = result.level_cliff
    cp = params.cliff
    return SensorView(
        result.mount,
        result.intrinsics,
        result.level_scan,
        None if cliff is None else cliff.scan,
        (rows.start, rows.stop, rows.step or 1),
        scan_margin_rows=rows.step or 1,
        cliff_margin_rows=1 if cp is None else cp.block_size + cp.row_step,
        cliff_rows=None if cp is None else cliff_rows(result.intrinsics.height, cp),
    )


def cliff_rows(height: int, cp: CliffParams) -> tuple[int, int, int]:
    """(start, stop, step) covering the image rows the cliff stage samples: from its top sample
    row (blocks counted from the image bottom, ``cliff_table``) to the bottom, every row in
    between (the floor they see lies between the samples'). The cliff table builds the floor
    extent of these very rows (coverage.floor_extent, cached): the memory reuses it."""
    used = min(cp.used_depth_height, height)
    blocks = max(1, used // cp.block_size)
    last = (cp.block_size - 1) // cp.row_step * cp.row_step  # a block's top sample row offset
    top = height - 1 - ((blocks - 1) * cp.block_size + last)
    return (max(0, top), height, 1)


class MemoryKeeper:
    """Owns the memory's state and the odometry checks; one per daemon.

    Args:
        settings: [memory].
        odometry: [odometry].
        source: a started odometry source, or None (frames may still carry ``odom``).
        clock: the arrival clock (host monotonic seconds), for the source-silence check.
    """

    def __init__(
        self,
        settings: MemorySettings,
        odometry: OdometrySettings,
        source: OdometrySource | None,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self.settings = settings
        self.odometry = odometry
        self.source = source
        self._params = settings.params()
        self.state = new_state(self._params)
        self._clock = clock
        self._started = clock()
        self._said: set[str] = set()
        # frames without a pose of their own leave the memory as it is: it is off, or it has no
        # odometry source and has said so (a frame's call cost the loop ~2 % even then)
        self._idle = not self.enabled
        self._last_pose: Pose | None = None
        self._stale = False
        self.resets = 0
        self.frozen_frames = 0
        # poses refused here: the frames' own (recordings, drives), or a source's past its checks
        self.refusals = OdomRefusals("in the frames (odom)" if source is None else source.name)

    @property
    def enabled(self) -> bool:
        return self.settings.enabled is not False

    def idle_for(self, frame: Frame) -> bool:
        """Whether :meth:`step` would leave the memory as it is for ``frame`` with nothing to
        say: the memory is off, or there is no odometry source (already said) and the frame
        carries no pose."""
        return self._idle and (frame.odom is None or not self.enabled)

    def step(
        self, frame: Frame, arrival_s: float, results: Sequence[tuple[Result, StageParams]]
    ) -> MemoryResult | None:
        """Update the memory with the views of one frame time; what goes out with it, or None when
        the memory is off."""
        if not self.enabled:
            return None
        got = self._pose(frame, arrival_s)
        p = self._params
        if got is None:
            return None
        if isinstance(got, str):  # stale: frozen
            self.frozen_frames += 1
            counts = read_scan(self.state, self._last_pose) if self._last_pose else None
            return MemoryResult(
                "frozen",
                None,
                counts.obstacle_cells if counts else 0,
                counts.cliff_cells if counts else 0,
                None,
                None,
                p.size_m,
                p.cell_m,
                got,
                self.rejected(),
            )
        status, note = "on", None
        if self._last_pose is not None:
            jump = _jump(self._last_pose, got)
            if jump[0] > self.odometry.max_jump_m or jump[1] > self.odometry.max_jump_deg:
                note = (
                    f"odometry jumped {jump[0]:.2f} m / {jump[1]:.1f} deg between two frames; "
                    "the memory is forgotten and starts again"
                )
                log.warning("memory: %s", note)
                reset(self.state)
                self.resets += 1
                status = "reset"
        self._last_pose = got
        views = [sensor_view(r, sp) for r, sp in results]
        update(self.state, got, frame.timestamp_s, views)
        read = read_scan(self.state, got)
        return MemoryResult(
            status,
            read.scan,
            read.obstacle_cells,
            read.cliff_cells,
            got,
            snapshot(self.state),
            p.size_m,
            p.cell_m,
            note,
            self.rejected(),
            read.hidden,
        )

    def rejected(self) -> dict[str, int]:
        """Odometry samples refused so far, per kind: the source's and the frames' together."""
        counts = self.refusals.counts()
        if self.source is not None:
            for kind, n in self.source.refusals.counts().items():
                counts[kind] = counts.get(kind, 0) + n
        return counts

    def _say_once(self, key: str, message: str, level: int = logging.WARNING) -> None:
        if key not in self._said:
            self._said.add(key)
            log.log(level, "memory: %s", message)

    def _pose(self, frame: Frame, arrival_s: float) -> Pose | str | None:
        """The frame's odometry pose; a note (str) when it is stale or refused; None when there is
        none."""
        if frame.odom is not None:
            return self._checked(frame.odom, frame)
        src = self.source
        if src is None:
            level = logging.WARNING if self.settings.enabled is True else logging.INFO
            self._say_once(
                "none",
                "off: no odometry (set [odometry] source, or replay a recording with odom)",
                level,
            )
            self._idle = True
            return None
        if src.buffer.count == 0:
            if self._clock() - self._started > self.odometry.timeout_s:
                refused = src.refusals.total
                self._say_once(
                    "silent",
                    f"odometry {src.name} has sent nothing"
                    + (f" usable ({refused} samples refused)" if refused else "")
                    + f" for {self.odometry.timeout_s:g} s; the memory is off until it speaks",
                )
            return None
        if "silent" in self._said and "spoke" not in self._said:
            self._say_once("spoke", f"odometry {src.name} speaks; the memory starts", logging.INFO)
        t = arrival_s if src.uses_arrival_clock else frame.timestamp_s
        at = src.buffer.pose_at(t)
        if at is None:
            return None  # the frame is older than the first odometry sample
        pose, age = at
        if age > self.odometry.stale_s:
            note = f"odometry {src.name} is {age:.1f} s old; the memory is frozen"
            if not self._stale:
                log.warning("memory: %s", note)
            self._stale = True
            return note
        if self._stale:
            log.info("memory: odometry %s is fresh again; the memory resumes", src.name)
            self._stale = False
        return self._checked(pose, frame)

    def _checked(self, pose: Pose, frame: Frame) -> Pose | str:
        """``pose`` within the odometry limits (yaw wrapped), or a note: refused, so the memory
        is frozen for this frame (counted; the first of each kind said)."""
        try:
            checked = check_odom_pose(*pose)
        except TypeError:  # not three values
            checked = OdomRefusal("malformed", f"odom={short_repr(pose)} is not x_m, y_m, yaw_rad")
        if isinstance(checked, OdomRefusal):
            self.refusals.note(checked, f"frame {frame.seq}")
            return f"odometry refused ({checked.reason}); the memory is frozen for this frame"
        return checked


def _jump(a: Pose, b: Pose) -> tuple[float, float]:
    """(distance m, |yaw change| deg) between two poses."""
    d = math.hypot(b[0] - a[0], b[1] - a[1])
    return d, abs(math.degrees(math.remainder(b[2] - a[2], 2 * math.pi)))


def open_odometry(settings: OdometrySettings) -> OdometrySource | None:
    """Start the configured odometry source, or None when there is none.

    The spec was checked with the configuration (a bad one is a usage error, exit 2); a source
    that cannot open (a busy port, a path that is no serial port) ends the start-up like a device
    or a serial tilt source that cannot (DeviceOpenError, exit 1): the robot asked for the memory.
    """
    if not settings.source:
        return None
    from drivers.odometry import create_odometry

    source = create_odometry(settings.source)
    source.start()
    log.info("odometry from %s", source.name)
    return source
