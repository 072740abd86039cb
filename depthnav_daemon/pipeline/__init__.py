"""The per-frame pipeline: scan, cliff and pose stages, composed into one Result per frame.

Stages are pure functions over numpy arrays (no I/O, no clock, no globals); the daemon owns state
such as the smoothed mount and when to re-estimate the pose.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING

from depthnav_daemon.pipeline.geometry import Mount
from depthnav_daemon.pipeline.scan import LaserScan

if TYPE_CHECKING:
    from depthnav_daemon.pipeline.cliff import CliffResult
    from depthnav_daemon.pipeline.pose import PoseEstimate
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
