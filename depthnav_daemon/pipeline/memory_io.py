"""The obstacle memory's inputs and outputs (``memory.py``): what a sensor view brings, what an
update did, and what goes out with a frame (the memory scan, the grid for viewers)."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import numpy.typing as npt

from depthnav_daemon.pipeline.geometry import Mount
from depthnav_daemon.pipeline.laser_scan import LaserScan
from drivers.base import Intrinsics


@dataclass(frozen=True, slots=True)
class SensorView:
    """What one sensor saw on one frame, as the memory needs it.

    Attributes:
        mount: the sensor's mount (height, tilt, roll) and placement on the robot.
        intrinsics: its camera.
        scan: the level-frame scan at the sensor (Result.level_scan).
        cliff_scan: the level-frame cliff scan in the same bins, or None without a cliff stage.
        rows: (start, stop, step) image rows the scan read (stop -1: to the bottom).
        scan_margin_rows: image rows between the last floor row the scan read and an obstacle
            (its row stride).
        cliff_margin_rows: image rows between the last floor row and the first drop-off the cliff
            stage counts (a block plus a sample stride: a block straddling the edge may not reach
            the threshold).
        short_free: (K,) indices of scan bins that read NaN only because the view does not reach
            range_max (the coverage rule) while their pixels saw no obstacle: seen free out to
            ``far``. None: not known, such bins clear nothing.
        cliff_rows: (start, stop, step) image rows the cliff stage samples, or None: ``rows``.
        cliff_short_free: as ``short_free`` for the cliff scan: bins NaN only because its rows
            do not see the floor out to its range_max, while they read floor and no drop-off.
    """

    mount: Mount
    intrinsics: Intrinsics
    scan: LaserScan
    cliff_scan: LaserScan | None = None
    rows: tuple[int, int, int] = (0, -1, 1)
    scan_margin_rows: int = 1
    cliff_margin_rows: int = 1
    short_free: npt.NDArray[np.intp] | None = None
    cliff_rows: tuple[int, int, int] | None = None
    cliff_short_free: npt.NDArray[np.intp] | None = None


@dataclass(frozen=True, slots=True)
class UpdateReport:
    """What one update did: occupied cells cleared, marked and expired, free cells forgotten
    (max_age_s); ``refused`` says why the pose was not used (outside the odometry limits: nothing
    changed), else None."""

    cleared: int = 0
    marked: int = 0
    expired: int = 0
    refused: str | None = None
    forgotten_free: int = 0


@dataclass(frozen=True, slots=True)
class MemoryScan:
    """The memory read back around the robot.

    Attributes:
        scan: 360 deg LaserScan in the base frame (REP 117): the nearest remembered obstacle or
            drop-off per bearing; +inf = known free from ``blind_m`` out to the scan's
            range_max; NaN = unknown.
        obstacle_cells, cliff_cells: remembered cells of each kind.
        blind_m: the radius around the base origin the scan did not judge, metres.
        hidden: (N,) bool per bin of ``scan``: NaN because a cell in a view's shadow, never seen
            free, lies in front of the bin's nearest remembered point (something may stand
            there: a pooled output must not report that point for it); None: not known.
    """

    scan: LaserScan
    obstacle_cells: int
    cliff_cells: int
    blind_m: float = 0.0
    hidden: npt.NDArray[np.bool_] | None = None


@dataclass(frozen=True, slots=True)
class GridSnapshot:
    """The grid for a viewer, in window order: cell [i, j] covers odometry x in
    [origin_x + i * cell, + cell), y likewise.

    Attributes:
        grid: (n, n) uint8 FREE (0) / OBSTACLE (1) / CLIFF (2), a copy.
        origin_m: (x, y) odometry coordinates of the grid's corner, metres.
        cell_m: cell side, metres.
        known: (n, n) uint8 1 where a FREE cell is known free (seen free, not expired), 0
            unknown, a copy in the same order; None where not given.
    """

    grid: npt.NDArray[np.uint8]
    origin_m: tuple[float, float]
    cell_m: float
    known: npt.NDArray[np.uint8] | None = None


@dataclass(frozen=True, slots=True)
class MemoryResult:
    """The memory as it goes out with a frame (Result.memory).

    Attributes:
        status: "on" (updated with this frame), "reset" (odometry jumped: forgotten, then updated
            with this frame) or "frozen" (odometry stale: not updated, nothing read back).
        scan: the 360 deg memory scan in the base frame (REP 117), or None when frozen.
        obstacle_cells, cliff_cells: remembered cells of each kind.
        pose: (x_m, y_m, yaw_rad) of the robot in the odometry frame used, or None when frozen.
        grid: the grid for a viewer (window order, origin, cell), or None when frozen.
        size_m, cell_m: the grid's side and cell, metres.
        note: why the status is not "on", or None.
        odometry_rejected: odometry samples refused so far, per kind (drivers.base
            ODOM_REFUSAL_KINDS).
        hidden: MemoryScan.hidden of ``scan`` (None when frozen or not known).
    """

    status: str
    scan: LaserScan | None
    obstacle_cells: int
    cliff_cells: int
    pose: tuple[float, float, float] | None
    grid: GridSnapshot | None
    size_m: float
    cell_m: float
    note: str | None = None
    odometry_rejected: dict[str, int] = field(default_factory=dict)
    hidden: npt.NDArray[np.bool_] | None = None


__all__ = ["GridSnapshot", "MemoryResult", "MemoryScan", "SensorView", "UpdateReport"]
