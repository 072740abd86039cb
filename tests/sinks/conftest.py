"""Real Frames and Results for the sink tests: synthetic scenes through the real stages."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest

from depthnav_daemon import __version__
from depthnav_daemon.pipeline import MountState, Result, StageParams, process
from depthnav_daemon.pipeline.cliff import CliffParams
from depthnav_daemon.pipeline.geometry import Mount
from depthnav_daemon.pipeline.pose import PoseEstimate
from depthnav_daemon.pipeline.scan import ScanParams
from depthnav_daemon.sim.synthetic import Box, Scene, render, step_down
from depthnav_daemon.sinks import SinkContext
from drivers.base import DeviceInfo, Frame, Intrinsics

# Asymmetric on purpose (fx != fy, cx != W/2, cy != H/2) so swapped axes fail loudly.
ASYM_640 = Intrinsics(640, 480, 575.0, 555.0, 331.0, 228.0)
SCAN = ScanParams(range_min_m=0.4, range_max_m=5.0)
CLIFF = CliffParams()
# a box ahead-left, a thin post ahead-right, a step down 2.2 m ahead
SCENE = Scene(
    boxes=(Box(1.6, 0.35, 0.3, 0.3, 0.4), Box(1.2, -0.3, 0.04, 0.04, 0.6)),
    holes=(step_down(2.2, 0.3),),
)

MOUNT = Mount(0.5, 12.0, 1.5)  # a little roll, so swapped signs show


def make_pair(
    seq: int,
    mount: Mount = MOUNT,
    *,
    scene: Scene = SCENE,
    intr: Intrinsics = ASYM_640,
    cliff: bool = True,
    pose: object | None = None,
    warning: str | None = None,
) -> tuple[Frame, Result]:
    """Render ``scene`` and run the real scan (and cliff) stage on it: one (Frame, Result)."""
    view = render(scene, intr, mount)
    frame = Frame(seq, 100.0 + seq / 30.0, view.depth_mm, intr)
    params = StageParams(scan=SCAN, cliff=CLIFF if cliff else None, obstacle_mask=True)
    result = process(frame, MountState(mount=mount, pose=pose), params)
    result = replace(
        result,
        timings_s={"scan": 0.004 + seq * 1e-4, "cliff": 0.002},
        warning=warning,
    )
    return frame, result


@pytest.fixture(scope="session")
def pairs() -> list[tuple[Frame, Result]]:
    """Five frames whose mount height changes a little each frame (so time series are checkable)."""
    out = []
    for seq in range(5):
        pose = (
            PoseEstimate(True, 0.5 + seq * 0.01, 12.0, 1.5, 900, 0.9, 0.004, 1000)
            if seq == 2
            else None
        )
        out.append(
            make_pair(
                seq,
                Mount(0.5 + seq * 0.01, 12.0, 1.5),
                pose=pose,
                warning="low valid depth" if seq == 3 else None,
            )
        )
    return out


@pytest.fixture(scope="session")
def context() -> SinkContext:
    """What the daemon hands to open()."""
    return SinkContext(
        DeviceInfo("synthetic", None, "replay:synthetic", ASYM_640),
        SCAN,
        CLIFF.block_size,
        __version__,
    )


def with_ranges(result: Result, ranges: np.ndarray) -> Result:
    """``result`` with its scan's ranges replaced (same layout length required)."""
    scan = replace(result.scan, ranges=np.asarray(ranges, dtype=np.float32))
    return replace(result, scan=scan)


def radians(deg: float) -> float:
    return math.radians(deg)


def with_memory(result: Result, pose: tuple[float, float, float] = (1.0, -0.5, 0.3)) -> Result:
    """``result`` with the obstacle memory after one real update from it (the daemon's path)."""
    from depthnav_daemon.config.loader import MemorySettings, OdometrySettings
    from depthnav_daemon.daemon.memory_keeper import MemoryKeeper

    keeper = MemoryKeeper(MemorySettings(), OdometrySettings(), None)
    frame = Frame(
        result.seq,
        result.timestamp_s,
        np.zeros((1, 1), np.uint16),
        Intrinsics(1, 1, 1.0, 1.0, 0.0, 0.0),
        odom=pose,
    )
    params = StageParams(scan=SCAN, cliff=CLIFF if result.cliff is not None else None)
    return replace(result, memory=keeper.step(frame, 0.0, [(result, params)]))
