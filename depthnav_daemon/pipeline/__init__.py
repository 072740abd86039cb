"""The per-frame pipeline: scan, cliff and pose stages, composed into one Result per frame.

Stages are pure functions over numpy arrays (no I/O, no clock, no globals); the daemon owns state
such as the smoothed mount and when to re-estimate the pose.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np

from depthnav_daemon.pipeline.geometry import Mount
from depthnav_daemon.pipeline.scan import LaserScan, ScanParams, depth_to_scan
from drivers.base import Frame

if TYPE_CHECKING:
    from depthnav_daemon.pipeline.cliff import CliffParams, CliffResult
    from depthnav_daemon.pipeline.pose import PoseEstimate, PoseParams
    from drivers.base import Intrinsics

# where the mount used for a frame came from
POSE_SOURCES = ("config", "accel", "serial", "floor")


@dataclass(frozen=True, slots=True)
class Result:
    """Everything depthnav computed for one frame.

    Attributes:
        seq: the frame's sequence number.
        timestamp_s: the frame's timestamp, seconds.
        intrinsics: intrinsics of the frame.
        mount: the sensor height/tilt/roll the stages used for this frame.
        mount_source: where that mount came from, one of POSE_SOURCES.
        scan: obstacles per bearing (level frame, REP 117).
        cliff: drop-offs (floor points and a polar cliff scan), or None when the stage is off.
        pose: a floor pose estimate made on this frame, or None when none ran.
        timings_s: seconds spent per stage on this frame ("scan", "cliff", "pose").
        warning: a one-line note about this frame (e.g. "no valid depth"), or None.
    """

    seq: int
    timestamp_s: float
    intrinsics: Intrinsics
    mount: Mount
    mount_source: str
    scan: LaserScan
    cliff: CliffResult | None = None
    pose: PoseEstimate | None = None
    timings_s: dict[str, float] = field(default_factory=dict)
    warning: str | None = None


def process(
    frame: Frame,
    mount: Mount,
    scan_params: ScanParams,
    cliff_params: CliffParams | None = None,
    pose_params: PoseParams | None = None,
    rng: np.random.Generator | None = None,
    mount_source: str = "config",
    clock: Callable[[], float] | None = None,
    on_pose: Callable[[PoseEstimate], tuple[Mount, str]] | None = None,
) -> Result:
    """Run the stages on one frame: the floor pose (when asked), then the scan, then the cliffs.

    Args:
        frame: the depth frame.
        mount: sensor height, tilt and roll the scan and cliff stages use.
        scan_params: scan parameters.
        cliff_params: cliff parameters, or None to skip the cliff stage.
        pose_params: pose parameters, or None to skip the floor pose estimate on this frame.
        rng: random generator for RANSAC; required with ``pose_params``.
        mount_source: where ``mount`` came from, copied into the result.
        clock: a monotonic clock (seconds) to time the stages with, or None for no timings.
        on_pose: given this frame's pose estimate, returns the (mount, source) to use from now on,
            so a new floor estimate already serves the frame it was made on.

    Returns:
        The frame's Result; a frame without any valid reading gives all-NaN scans and a warning.
    """
    from depthnav_daemon.pipeline.cliff import detect_cliffs
    from depthnav_daemon.pipeline.pose import estimate_pose

    depth, intr = frame.depth_mm, frame.intrinsics
    tick = clock or (lambda: 0.0)
    timings: dict[str, float] = {}

    pose = None
    if pose_params is not None:
        if rng is None:
            raise ValueError("process() with pose_params needs an rng (numpy.random.Generator)")
        t0 = tick()
        pose = estimate_pose(depth, intr, pose_params, rng)
        timings["pose"] = tick() - t0
        if on_pose is not None:
            mount, mount_source = on_pose(pose)
    t0 = tick()
    scan = depth_to_scan(depth, intr, mount, scan_params)
    timings["scan"] = tick() - t0
    cliff = None
    if cliff_params is not None:
        t0 = tick()
        cliff = detect_cliffs(
            depth, intr, mount, cliff_params, scan.angle_min, scan.angle_increment, scan.ranges.size
        )
        timings["cliff"] = tick() - t0
    # the scan already visited every used pixel: all-NaN means none of them had a reading
    warning = "no valid depth in this frame (all pixels 0)" if np.isnan(scan.ranges).all() else None
    return Result(
        frame.seq,
        frame.timestamp_s,
        intr,
        mount,
        mount_source,
        scan,
        cliff,
        pose,
        timings if clock else {},
        warning,
    )


def prepare(
    intr: Intrinsics,
    mount: Mount,
    scan_params: ScanParams,
    cliff_params: CliffParams | None = None,
) -> None:
    """Build the scan's and cliff detector's tables for this camera and mount, and cache them.

    What the first frame with this mount would build (tens of ms at 640x480): the stages run on
    an empty frame, so the tables and their cache keys are exactly those ``process`` uses.

    Raises:
        ConfigError: parameters that do not fit this camera and mount (as ``process`` would).
    """
    from depthnav_daemon.pipeline.cliff import detect_cliffs

    blank = np.zeros((intr.height, intr.width), dtype=np.uint16)
    scan = depth_to_scan(blank, intr, mount, scan_params)
    if cliff_params is not None:
        detect_cliffs(
            blank, intr, mount, cliff_params, scan.angle_min, scan.angle_increment, scan.ranges.size
        )
