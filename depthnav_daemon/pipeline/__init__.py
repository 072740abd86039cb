"""The per-frame pipeline: scan and cliff stages composed into one Result per frame.

Stages are pure functions over numpy arrays (no I/O, no clock, no globals). The daemon owns the
state: it decides when to run the floor pose stage (``pose.estimate_pose``), updates the mount
from it, then calls :func:`process` with a :class:`MountState` (the mount, its source, its trust
and the frame's floor estimate). Whatever a sink shows (the scan's row band, the obstacle mask) is
on the Result, so sinks never call stage code.

Modules: ``geometry`` (the frame conventions), ``params`` (each stage's parameters),
``laser_scan``; the stages ``scan`` (+ ``scan_table``, ``scan_paper``, ``scan_blocks``),
``cliff`` (+ ``cliff_table``), ``pose`` (+ ``pose_fit``), ``mount_planner``; the robot's view
``placement`` (base frame), ``merge`` (several sensors), ``memory`` (the obstacle memory);
``lens`` (distortion); ``*_kernels`` the compiled loops.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np
import numpy.typing as npt

from depthnav_daemon.pipeline.cliff import CliffParams, CliffResult, detect_cliffs
from depthnav_daemon.pipeline.coverage import floor_extent
from depthnav_daemon.pipeline.geometry import Mount, depth_to_mm
from depthnav_daemon.pipeline.placement import base_layout, points_to_base, scan_to_base
from depthnav_daemon.pipeline.placement_pixels import pixel_table, pixels_to_base
from depthnav_daemon.pipeline.scan import (
    LaserScan,
    ScanParams,
    depth_to_scan,
    obstacle_pixels,
)
from depthnav_daemon.pipeline.scan_table import exact_table, scan_rows

if TYPE_CHECKING:
    from depthnav_daemon.pipeline.memory import MemoryResult
    from depthnav_daemon.pipeline.merge import SensorState
    from depthnav_daemon.pipeline.pose import PoseEstimate
    from drivers.base import Frame, Intrinsics


@dataclass(frozen=True, slots=True, kw_only=True)
class StageParams:
    """What :func:`process` runs on each frame.

    Attributes:
        scan: scan parameters.
        cliff: cliff parameters, or None to skip the cliff stage.
        obstacle_mask: also return the (H, W) mask of obstacle pixels (exact method; for sinks
            that draw it, at the cost of one more pass over the image).
    """

    scan: ScanParams
    cliff: CliffParams | None = None
    obstacle_mask: bool = False


MOUNT_SOURCES = ("default", "config", "accel", "serial", "floor")
FLOOR_VERDICTS = ("confirmed", "contradicted", "unknown")


@dataclass(frozen=True, slots=True, kw_only=True)
class MountTrust:
    """How far the mount a frame was processed with can be trusted (the daemon decides it).

    Attributes:
        source: where the mount's values came from: "default" (the built-in 0.5 m, tilt 0 deg,
            not pinned: nothing was configured), "config" (a config file, ``--set``, the mount
            flags or a ``depthnav calibrate`` file), "accel" / "serial" (a tilt sensor's tilt and
            roll, the configured height), or "floor" (the floor estimate).
        pinned: the mount is pinned (``daemon.tilt_source = "config"``, as the mount flags set):
            floor estimates check it but never replace it.
        floor: "confirmed" (the latest confident floor estimate agrees with the mount within
            ``daemon.max_jump_m`` / ``max_jump_deg``), "contradicted" (it does not), or
            "unknown" (no confident floor estimate yet).
        floor_height_m, floor_tilt_deg, floor_roll_deg: the floor's estimate while it
            contradicts the mount; else None.
        dropoffs_trusted: drop-offs (the cliff stage) rest on a trustworthy mount: the floor
            confirms it, or no floor estimate yet and the mount was configured. False while the
            floor contradicts the mount or while the built-in default is unconfirmed.
        trusted: the mount is known at all: configured, or found by the floor. False while
            nobody configured it and no floor estimate has given it yet (the built-in 0.5 m,
            perhaps with a tilt sensor's tilt): the daemon then reports every range of the
            scan and the cliff scan as unknown (NaN), and ``dropoffs_trusted`` is False too.
        note: one line for people while drop-offs are not trusted, else None.
    """

    source: str = "config"
    pinned: bool = False
    floor: str = "unknown"
    floor_height_m: float | None = None
    floor_tilt_deg: float | None = None
    floor_roll_deg: float | None = None
    dropoffs_trusted: bool = True
    trusted: bool = True
    note: str | None = None


@dataclass(frozen=True, slots=True, kw_only=True)
class MountState:
    """The mount a frame is processed with and what the daemon knows of it, as one value: the
    daemon builds it before the stages run, :func:`process` carries it into the Result.

    Attributes:
        mount: the sensor's height, tilt and roll the stages use, and its placement on the robot.
        source: where the mount's values came from ("default", "config", "accel", "serial" or
            "floor"; see :class:`MountTrust`).
        trust: the daemon's verdict on the mount, or None when nobody assessed it (``process``
            called outside the daemon with a bare Mount).
        pose: the floor pose estimate made on this frame, or None when none ran.
        pose_s: seconds that estimate took (the Result's ``timings_s["pose"]``), or None.
    """

    mount: Mount
    source: str = "config"
    trust: MountTrust | None = None
    pose: PoseEstimate | None = None
    pose_s: float | None = None


@dataclass(frozen=True, slots=True, kw_only=True)
class Result:
    """Everything depthnav computed for one frame.

    Attributes:
        seq: the frame's sequence number.
        timestamp_s: the frame's timestamp, seconds.
        intrinsics: intrinsics of the frame.
        mount_state: the mount the stages used for this frame (height/tilt/roll and placement
            on the robot), where it came from, its trust and the floor estimate made on this
            frame; read through the ``mount``, ``mount_source``, ``mount_trust`` and ``pose``
            properties.
        scan: obstacles per bearing in the robot's base frame (ranges from the base origin,
            bearings from the robot's forward axis; REP 117). With the default placement (x = y =
            yaw = 0) the base frame is the level frame at the sensor.
        scan_band: [first, stop) image rows the scan read.
        cliff: drop-offs (floor points and a polar cliff scan) in the base frame, or None when
            the stage is off.
        sensor_scan: the scan in the sensor's level frame (what the memory ray-casts from the
            sensor); the same object as ``scan`` when the sensor sits at the base origin.
        sensor_cliff: the cliff result in the sensor's level frame (likewise), or None.
        memory: the obstacle memory after this frame (the daemon adds it when odometry allows),
            or None: a 360 deg memory scan, cell counts and the grid for a viewer.
        sensors: several sensors: each one's name, status, age and latest Result (``scan`` and
            ``cliff`` are then the merge of those in it); () with one sensor.
        obstacle_mask: (H, W) bool, the pixels the exact scan counts as obstacles, when asked for
            (StageParams.obstacle_mask) and the method is exact; else None.
        timings_s: seconds spent per stage on this frame ("pose", "scan", "cliff").
        warning: a one-line note about this frame (e.g. "no valid depth", or why its
            drop-offs are not trusted), or None.
    """

    seq: int
    timestamp_s: float
    intrinsics: Intrinsics
    mount_state: MountState
    scan: LaserScan
    scan_band: tuple[int, int] = (0, 0)
    cliff: CliffResult | None = None
    obstacle_mask: npt.NDArray[np.bool_] | None = None
    timings_s: dict[str, float] = field(default_factory=dict)
    warning: str | None = None
    sensor_scan: LaserScan | None = None
    sensor_cliff: CliffResult | None = None
    memory: MemoryResult | None = None
    sensors: tuple[SensorState, ...] = ()

    @property
    def mount(self) -> Mount:
        """The mount the stages used for this frame."""
        return self.mount_state.mount

    @property
    def mount_source(self) -> str:
        """Where that mount came from."""
        return self.mount_state.source

    @property
    def mount_trust(self) -> MountTrust | None:
        """How far the mount can be trusted, or None when nobody assessed it."""
        return self.mount_state.trust

    @property
    def pose(self) -> PoseEstimate | None:
        """The floor pose estimate made on this frame, or None when none ran."""
        return self.mount_state.pose

    @property
    def level_scan(self) -> LaserScan:
        """The scan in the sensor's level frame."""
        return self.scan if self.sensor_scan is None else self.sensor_scan

    @property
    def level_cliff(self) -> CliffResult | None:
        """The cliff result in the sensor's level frame."""
        return self.cliff if self.sensor_cliff is None else self.sensor_cliff


def process(
    frame: Frame,
    mount_state: MountState | Mount,
    params: StageParams,
    clock: Callable[[], float] | None = None,
) -> Result:
    """Run the scan and cliff stages on one frame with a given mount.

    Args:
        frame: the depth frame.
        mount_state: the mount the stages use, with its source, trust and the floor estimate
            made on this frame (all carried into the Result); a bare Mount is a configured
            mount nobody assessed (source "config", no trust, no estimate).
        params: which stages run and their parameters.
        clock: a monotonic clock (seconds) to time the stages with, or None for no timings
            (the estimate's ``pose_s`` is kept either way).

    Returns:
        The frame's Result; a frame without any valid reading gives all-NaN scans and a warning;
        while drop-offs are not trusted the trust's note is the frame's warning (unless the frame
        has a worse one).
    """
    state = mount_state if isinstance(mount_state, MountState) else MountState(mount=mount_state)
    mount, mount_trust = state.mount, state.trust
    depth, intr = frame.depth_mm, frame.intrinsics
    tick = clock or (lambda: 0.0)
    timings: dict[str, float] = {} if state.pose_s is None else {"pose": state.pose_s}
    given = dict(timings)
    level = mount.level_part()
    t0 = tick()
    scan = depth_to_scan(depth, intr, level, params.scan)
    timings["scan"] = tick() - t0
    cliff = None
    if params.cliff is not None:
        t0 = tick()
        cliff = detect_cliffs(
            depth, intr, level, params.cliff, scan.angle_min, scan.angle_increment, scan.ranges.size
        )
        timings["cliff"] = tick() - t0
        if params.cliff.method == "exact":
            _unread_behind_obstacles(cliff.scan.ranges, scan.ranges)
    mask = None
    if params.obstacle_mask and params.scan.method == "exact":
        mask = obstacle_pixels(depth, intr, level, params.scan)
    rows = scan_rows(intr, params.scan)
    # the scan already visited every used pixel: all-NaN means none of them had a reading, or
    # none of the bins was seen out to range_max (a steep mount over open floor: the safety
    # contract's coverage rule), which a look at the frame tells apart
    no_depth = _all_nan(scan.ranges) and not depth.any()
    warning = "no valid depth in this frame (all pixels 0)" if no_depth else None
    if warning is None and mount_trust is not None and not mount_trust.dropoffs_trusted:
        warning = mount_trust.note
    base_scan, base_cliff = scan, cliff
    if mount.placed:
        t0 = tick()
        base_scan, base_cliff = to_base_frame(scan, cliff, mount, params, intr, depth)
        timings["placement"] = tick() - t0
    return Result(
        seq=frame.seq,
        timestamp_s=frame.timestamp_s,
        intrinsics=intr,
        mount_state=state,
        scan=base_scan,
        scan_band=(rows.start, min(rows.stop, intr.height)),
        cliff=base_cliff,
        obstacle_mask=mask,
        timings_s=timings if clock else given,
        warning=warning,
        sensor_scan=scan if mount.placed else None,
        sensor_cliff=cliff if mount.placed else None,
    )


def to_base_frame(
    scan: LaserScan,
    cliff: CliffResult | None,
    mount: Mount,
    params: StageParams,
    intr: Intrinsics,
    depth: np.ndarray | None = None,
) -> tuple[LaserScan, CliffResult | None]:
    """A sensor's level-frame scan and cliff result in the robot's base frame (one layout for
    both, see ``placement``); ``intr`` is the sensor's camera (what its view sees decides where
    the base scans may say clear); ``depth``: the frame the exact scan read, whose obstacle
    pixels give the base scan's ranges at pixel resolution (``placement_pixels``; None: from
    the level scan's bins only, up to a wedge's range spread farther)."""
    rmin, rmax = scan.range_min, scan.range_max
    if params.cliff is not None:
        rmin, rmax = min(rmin, params.cliff.range_min_m), max(rmax, params.cliff.range_max_m)
    layout = base_layout(
        scan.angle_min,
        scan.angle_increment,
        scan.ranges.size,
        mount.x_m,
        mount.y_m,
        mount.yaw_rad,
        rmin,
        rmax,
    )
    rows = scan_rows(intr, params.scan)
    row_span = (rows.start, rows.stop, rows.step or 1)
    pixels = None
    if depth is not None and params.scan.method == "exact" and (mount.x_m or mount.y_m):
        level = mount.level_part()
        table = exact_table(intr, level, params.scan)
        ptable = pixel_table(intr, level, row_span, params.scan.col_step, mount.yaw_rad)
        pixels = pixels_to_base(depth_to_mm(depth, intr), table, ptable, mount, layout)
    base_scan = scan_to_base(scan, mount, layout, intr, row_span, pixels)
    if cliff is None:
        return base_scan, None
    assert params.cliff is not None
    cliff_rows = (max(0, intr.height - params.cliff.used_depth_height), intr.height, 1)
    base_cliff = CliffResult(
        points_to_base(cliff.points_m, mount),
        cliff.blocks,
        cliff.block_size,
        scan_to_base(cliff.scan, mount, layout, intr, cliff_rows, drop_offs=True),
    )
    return base_scan, base_cliff


@functools.lru_cache(maxsize=4)
def _blank(height: int, width: int) -> npt.NDArray[np.uint16]:
    """A frame without readings, shared (the stages never write their input): allocating and
    zeroing it held the interpreter lock for 1-2 ms at 1280x720 (a C call) on the worker of
    every mount change. Writable on purpose: a read-only array is another type to the compiled
    kernels (a compile on the worker, holding the lock for seconds, on a cold cache)."""
    return np.zeros((height, width), dtype=np.uint16)


def prepare(intr: Intrinsics, mount: Mount, params: StageParams) -> None:
    """Build the scan's and cliff detector's tables for this camera and mount, and cache them.

    What the first frame with this mount would build (tens of ms at 640x480): the stages run on
    an empty frame, so the tables and their cache keys are exactly those ``process`` uses.

    Raises:
        ConfigError: parameters that do not fit this camera and mount (as ``process`` would).
    """
    blank = _blank(intr.height, intr.width)
    level = mount.level_part()
    scan = depth_to_scan(blank, intr, level, params.scan)
    cliff = None
    if params.cliff is not None:
        cliff = detect_cliffs(
            blank, intr, level, params.cliff, scan.angle_min, scan.angle_increment, scan.ranges.size
        )
    if mount.placed:
        to_base_frame(scan, cliff, mount, params, intr, blank)
    # what this mount's view covers on the floor per bin (the memory's clearing, the contract's
    # clear claims): the exact scan built it already; the paper method did not
    rows = scan_rows(intr, params.scan)
    floor_extent(
        intr,
        level,
        float(scan.angle_min),
        float(scan.angle_increment),
        int(scan.ranges.size),
        (rows.start, rows.stop, rows.step or 1),
    )


def _unread_behind_obstacles(cliff: npt.NDArray[np.float32], scan: npt.NDArray[np.float32]) -> None:
    """Cliff bins that found no drop-off (+inf) where the scan found an obstacle (finite or -inf)
    are unknown (NaN), in place: the obstacle hides the floor behind it, so "no drop-off out to
    range_max" was not seen (the safety contract). Same layout (the cliff uses the scan's)."""
    hidden = np.isposinf(cliff) & (np.isfinite(scan) | np.isneginf(scan))
    cliff[hidden] = np.float32(np.nan)


def _all_nan(ranges: npt.NDArray[np.floating]) -> bool:
    """Whether every range is NaN (none of an empty scan's is not). The first bin answers for
    nearly every frame (a bin with a reading), without a pass over the scan."""
    if ranges.size and not math.isnan(ranges.item(0)):
        return False
    return bool(np.isnan(ranges).all())
