"""RunReport: what one run of the frame loop did, filled in by the one-sensor loop (loop.py), the
several-sensor loop (multi.py) and the helpers they share (frames.py, outputs.py)."""

from __future__ import annotations

from dataclasses import dataclass, field

from depthnav_daemon.pipeline import Result


@dataclass
class RunReport:
    """What a run did, for the CLI's summary and the tests."""

    frames: int = 0
    reconnects: int = 0
    dropped_sinks: list[str] = field(default_factory=list)
    rejected_pose_jumps: int = 0
    memory_resets: int = 0
    lost_sensors: list[str] = field(default_factory=list)
    last_result: Result | None = None
    stopped: bool = False  # ended by the stop event rather than by the source
