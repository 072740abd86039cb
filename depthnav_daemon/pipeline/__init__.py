"""The per-frame pipeline: scan and cliff stages composed into one Result per frame.

Stages are pure functions over numpy arrays (no I/O, no clock, no globals). The daemon owns the
state: it decides when to run the floor pose stage (``pose.estimate_pose``), updates the mount
from it, then calls :func:`process` with that mount. Whatever a sink shows (the scan's row band,
the obstacle mask) is on the Result, so sinks never call stage code.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np
import numpy.typing as npt

from depthnav_daemon.pipeline.cliff import CliffParams, CliffResult, detect_cliffs
from depthnav_daemon.pipeline.geometry import Mount
from depthnav_daemon.pipeline.scan import (
    LaserScan,
    ScanParams,
    depth_to_scan,
    obstacle_pixels,
)
from depthnav_daemon.pipeline.scan_table import scan_rows

if TYPE_CHECKING:
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


@dataclass(frozen=True, slots=True, kw_only=True)
class Result:
    """Everything depthnav computed for one frame.

    Attributes:
        seq: the frame's sequence number.
        timestamp_s: the frame's timestamp, seconds.
        intrinsics: intrinsics of the frame.
        mount: the sensor height/tilt/roll the stages used for this frame.
        mount_source: where that mount came from ("config", "accel", "serial" or "floor").
        scan: obstacles per bearing (level frame, REP 117).
        scan_band: [first, stop) image rows the scan read.
        cliff: drop-offs (floor points and a polar cliff scan), or None when the stage is off.
        pose: a floor pose estimate made on this frame, or None when none ran.
        obstacle_mask: (H, W) bool, the pixels the exact scan counts as obstacles, when asked for
            (StageParams.obstacle_mask) and the method is exact; else None.
        timings_s: seconds spent per stage on this frame ("pose", "scan", "cliff").
        warning: a one-line note about this frame (e.g. "no valid depth"), or None.
    """

    seq: int
    timestamp_s: float
    intrinsics: Intrinsics
    mount: Mount
    mount_source: str
    scan: LaserScan
    scan_band: tuple[int, int] = (0, 0)
    cliff: CliffResult | None = None
    pose: PoseEstimate | None = None
    obstacle_mask: npt.NDArray[np.bool_] | None = None
    timings_s: dict[str, float] = field(default_factory=dict)
    warning: str | None = None


def process(
    frame: Frame,
    mount: Mount,
    params: StageParams,
    *,
    mount_source: str = "config",
    pose: PoseEstimate | None = None,
    clock: Callable[[], float] | None = None,
    timings_s: dict[str, float] | None = None,
) -> Result:
    """Run the scan and cliff stages on one frame with a given mount.

    Args:
        frame: the depth frame.
        mount: sensor height, tilt and roll the stages use.
        params: which stages run and their parameters.
        mount_source: where ``mount`` came from, copied into the result.
        pose: a floor pose estimate the caller made on this frame, copied into the result.
        clock: a monotonic clock (seconds) to time the stages with, or None for no timings.
        timings_s: timings the caller already took on this frame (e.g. "pose"), kept in the
            result's ``timings_s``.

    Returns:
        The frame's Result; a frame without any valid reading gives all-NaN scans and a warning.
    """
    depth, intr = frame.depth_mm, frame.intrinsics
    tick = clock or (lambda: 0.0)
    timings: dict[str, float] = dict(timings_s or {})
    t0 = tick()
    scan = depth_to_scan(depth, intr, mount, params.scan)
    timings["scan"] = tick() - t0
    cliff = None
    if params.cliff is not None:
        t0 = tick()
        cliff = detect_cliffs(
            depth, intr, mount, params.cliff, scan.angle_min, scan.angle_increment, scan.ranges.size
        )
        timings["cliff"] = tick() - t0
    mask = None
    if params.obstacle_mask and params.scan.method == "exact":
        mask = obstacle_pixels(depth, intr, mount, params.scan)
    rows = scan_rows(intr, params.scan)
    # the scan already visited every used pixel: all-NaN means none of them had a reading
    warning = "no valid depth in this frame (all pixels 0)" if np.isnan(scan.ranges).all() else None
    return Result(
        seq=frame.seq,
        timestamp_s=frame.timestamp_s,
        intrinsics=intr,
        mount=mount,
        mount_source=mount_source,
        scan=scan,
        scan_band=(rows.start, min(rows.stop, intr.height)),
        cliff=cliff,
        pose=pose,
        obstacle_mask=mask,
        timings_s=timings if clock else dict(timings_s or {}),
        warning=warning,
    )


def prepare(intr: Intrinsics, mount: Mount, params: StageParams) -> None:
    """Build the scan's and cliff detector's tables for this camera and mount, and cache them.

    What the first frame with this mount would build (tens of ms at 640x480): the stages run on
    an empty frame, so the tables and their cache keys are exactly those ``process`` uses.

    Raises:
        ConfigError: parameters that do not fit this camera and mount (as ``process`` would).
    """
    blank = np.zeros((intr.height, intr.width), dtype=np.uint16)
    scan = depth_to_scan(blank, intr, mount, params.scan)
    if params.cliff is not None:
        detect_cliffs(
            blank, intr, mount, params.cliff, scan.angle_min, scan.angle_increment, scan.ranges.size
        )
