"""Obstacle memory: a rolling grid around the robot in the odometry frame (the costmap layer).

The paper's cliff detector "maps the obstacles to a dedicated layer in a costmap" (sec. 2.3;
depth_nav_tools' ``nav_layer_from_points`` keeps points for 0.75 s). Here the layer keeps what the
sensors can no longer see: a grid of ``size_m`` x ``size_m`` with cells of ``cell_m`` (default
8 x 8 m at 5 cm) follows the robot, in the odometry frame (x, y, yaw of the robot's base frame).

Each sensor view (its level-frame scan, cliff scan and placement on the robot) updates it:
- what the sensor sees now wins: a remembered cell inside the view (beyond the sensor's lower dead
  zone, i.e. the nearest floor its image shows on that bearing) and nearer than what the sensor
  sees on that bearing (the nearest obstacle or drop-off, or range_max when it sees floor all the
  way) is cleared: a person who walked away disappears;
- obstacle cells are marked at the scan's points, cliff cells at the cliff scan's (the nearest
  drop-off floor point per bearing, i.e. the edge);
- cells it does not see (dead zones, behind, beside) keep their state; with ``max_age_s`` > 0 a cell
  not marked again for that long is forgotten.
A cell keeps where in it its last point was, so the memory scan is not rounded to cells.

State lives in :class:`MemoryState`, owned by the caller and passed to every call (no globals);
``update`` changes it in place (copying the grid every frame would cost more than the update) and
returns what it did. ``memory_scan`` reads it. The daemon decides when odometry is good enough.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
import numpy.typing as npt

from depthnav_daemon.pipeline.geometry import (
    F32,
    Mount,
    cam_to_level,
    check_range,
    pixel_rays,
)
from depthnav_daemon.pipeline.memory_kernels import (
    CLIFF,
    OBSTACLE,
    clear_lines,
    expire,
    memory_scan,
    update_view,
)
from depthnav_daemon.pipeline.near_kernels import near_limits_kernel
from depthnav_daemon.pipeline.scan import LaserScan
from drivers.base import Intrinsics, OdomRefusal, check_odom_pose

MAX_CELLS = 2048  # cells per side
NEAR_STRIDE = 2  # pixels between the samples of the near-limit table


@dataclass(frozen=True, slots=True)
class MemoryParams:
    """Memory parameters.

    Attributes:
        size_m: side of the square grid around the robot, metres.
        cell_m: cell side, metres.
        max_age_s: forget a cell not marked again for this long (0 = keep it until it leaves the
            grid or a sensor sees it free).
        scan_increment_deg: bin width of the 360 deg memory scan, degrees (divides 360).
    """

    size_m: float = 8.0
    cell_m: float = 0.05
    max_age_s: float = 0.0
    scan_increment_deg: float = 1.0

    def __post_init__(self) -> None:
        check_range("memory.cell_m", self.cell_m, 0.005, 1.0, " m")
        check_range("memory.size_m", self.size_m, 2 * self.cell_m, MAX_CELLS * self.cell_m, " m")
        check_range("memory.max_age_s", self.max_age_s, 0.0, 86400.0, " s")
        check_range("memory.scan_increment_deg", self.scan_increment_deg, 0.1, 10.0, " deg")

    @property
    def cells(self) -> int:
        """Cells per side (a multiple of 4: the kernels read the grid 8 bytes at a time)."""
        return 4 * max(1, round(self.size_m / self.cell_m / 4))

    @property
    def scan_bins(self) -> int:
        return round(360.0 / self.scan_increment_deg)


@dataclass(slots=True)
class MemoryState:
    """The grid and where it is; see the module docstring. Create with :func:`new_state`.

    Attributes:
        grid: (n, n) uint8 FREE / OBSTACLE / CLIFF, toroidal: global cell (gx, gy) at index
            (gx mod n, gy mod n).
        stamp: (n, n) float32 seconds since ``epoch_s`` each cell was last marked.
        offx, offy: (n, n) float32 position of each cell's last point inside it, metres.
        wx0, wy0: global cell index of the window's first column and row.
        epoch_s: time origin of ``stamp`` (the first update's time).
    """

    params: MemoryParams
    grid: npt.NDArray[np.uint8]
    stamp: F32
    offx: F32
    offy: F32
    wx0: int = 0
    wy0: int = 0
    epoch_s: float | None = None
    updates: int = 0


def new_state(params: MemoryParams) -> MemoryState:
    """An empty memory."""
    n = params.cells
    return MemoryState(
        params,
        np.zeros((n, n), np.uint8),
        np.zeros((n, n), np.float32),
        np.zeros((n, n), np.float32),
        np.zeros((n, n), np.float32),
    )


def reset(state: MemoryState) -> None:
    """Forget everything (a jump in the odometry)."""
    state.grid[:] = 0
    state.epoch_s = None


@dataclass(frozen=True, slots=True)
class SensorView:
    """What one sensor saw on one frame, as the memory needs it.

    Attributes:
        mount: the sensor's mount (height, tilt, roll) and placement on the robot.
        intrinsics: its camera.
        scan: the level-frame scan at the sensor (Result.level_scan).
        cliff_scan: the level-frame cliff scan in the same bins, or None without a cliff stage.
        rows: (start, stop, step) image rows the scan used (its view's lower edge).
        scan_margin_rows: image rows between the last floor row the scan read and an obstacle
            (its row stride).
        cliff_margin_rows: image rows between the last floor row and the first drop-off the cliff
            stage counts (a block plus a sample stride: a block straddling the edge may not reach
            the threshold).
    """

    mount: Mount
    intrinsics: Intrinsics
    scan: LaserScan
    cliff_scan: LaserScan | None = None
    rows: tuple[int, int, int] = (0, -1, 1)
    scan_margin_rows: int = 1
    cliff_margin_rows: int = 1


@dataclass(frozen=True, slots=True)
class UpdateReport:
    """What one update did: cells cleared, marked and expired; ``refused`` says why the pose was
    not used (outside the odometry limits: nothing changed), else None."""

    cleared: int = 0
    marked: int = 0
    expired: int = 0
    refused: str | None = None


@functools.lru_cache(maxsize=32)
def near_limits(
    intr: Intrinsics,
    mount: Mount,
    angle_min: float,
    inc: float,
    n: int,
    rows: tuple[int, int, int],
) -> F32:
    """(n,) float32: per scan bin, the nearest floor range the sensor sees (its lower dead zone,
    eq. 15 generalised to every bearing, tilt and roll), +inf where no pixel sees the floor."""
    start, stop, step = rows
    stop = intr.height if stop < 0 else min(stop, intr.height)
    out = np.empty(n)
    # compiled, releases the interpreter lock: built on the worker of a mount change while the
    # frame loop runs (numpy held the lock for parts of 30-45 ms at 1280x720)
    near_limits_kernel(
        pixel_rays(intr),
        cam_to_level(mount.tilt_rad, mount.roll_rad),
        float(mount.height_m),
        int(start),
        int(stop),
        max(1, int(step)),
        max(1, NEAR_STRIDE),
        float(angle_min),
        float(inc),
        out,
    )
    res = out.astype(np.float32)
    res.setflags(write=False)
    return res


def _recentre(state: MemoryState, x_m: float, y_m: float) -> None:
    n, cell = state.params.cells, state.params.cell_m
    nx0 = math.floor(x_m / cell) - n // 2
    ny0 = math.floor(y_m / cell) - n // 2
    if (nx0, ny0) != (state.wx0, state.wy0):
        if state.updates == 0:
            state.grid[:] = 0
        else:
            clear_lines(state.grid, state.wx0, state.wy0, nx0, ny0)
        state.wx0, state.wy0 = nx0, ny0


def update(
    state: MemoryState,
    pose: tuple[float, float, float],
    t_s: float,
    views: Sequence[SensorView],
    margin_m: float | None = None,
) -> UpdateReport:
    """Fold sensor views seen from the robot's odometry ``pose`` at time ``t_s`` into ``state``.

    Args:
        state: the memory (changed in place).
        pose: (x_m, y_m, yaw_rad) of the robot's base frame in the odometry frame.
        t_s: the views' time, seconds.
        views: what the sensors saw at that pose.
        margin_m: a remembered point this close to what a sensor sees now is kept (default a
            fifth of a cell), or the floor spanned by the view's margin rows if that is more.

    Returns:
        Cells cleared, marked and expired; a pose outside the odometry limits
        (drivers.base.check_odom_pose) leaves the memory as it is and says why (``refused``).
    """
    p = state.params
    checked = check_odom_pose(*pose)
    if isinstance(checked, OdomRefusal):  # the caller checks first; this keeps the grid safe
        return UpdateReport(refused=checked.reason)
    x, y, yaw = checked
    if state.epoch_s is None:
        state.epoch_s = t_s
    _recentre(state, x, y)
    t_rel = np.float32(t_s - state.epoch_s)
    margin = 0.2 * p.cell_m if margin_m is None else margin_m
    cleared = marked = 0
    c, s = math.cos(yaw), math.sin(yaw)
    for v in views:
        m = v.mount
        sc = v.scan
        n = sc.ranges.size
        near = near_limits(
            v.intrinsics, m.level_part(), float(sc.angle_min), float(sc.angle_increment), n, v.rows
        )
        cliff = (
            np.empty(0, np.float32)
            if v.cliff_scan is None
            else np.ascontiguousarray(v.cliff_scan.ranges, dtype=np.float32)
        )
        k, j = update_view(
            state.grid,
            state.stamp,
            state.offx,
            state.offy,
            state.wx0,
            state.wy0,
            p.cell_m,
            x + c * m.x_m - s * m.y_m,
            y + s * m.x_m + c * m.y_m,
            yaw + m.yaw_rad,
            np.ascontiguousarray(sc.ranges, dtype=np.float32),
            cliff,
            near,
            float(sc.angle_min),
            float(sc.angle_increment),
            float(sc.range_max),
            margin,
            1.0 / (m.height_m * v.intrinsics.fy),
            m.height_m**2,
            float(v.scan_margin_rows),
            float(v.cliff_margin_rows),
            t_rel,
        )
        cleared += k
        marked += j
    expired = 0
    if p.max_age_s > 0:
        expired = expire(state.grid, state.stamp, np.float32(t_rel - p.max_age_s))
    state.updates += 1
    return UpdateReport(int(cleared), int(marked), int(expired))


@dataclass(frozen=True, slots=True)
class MemoryScan:
    """The memory read back around the robot.

    Attributes:
        scan: 360 deg LaserScan in the base frame: nearest remembered obstacle or drop-off per
            bearing (REP 117: +inf = nothing remembered on that bearing within the grid).
        obstacle_cells, cliff_cells: remembered cells of each kind.
    """

    scan: LaserScan
    obstacle_cells: int
    cliff_cells: int


def read_scan(state: MemoryState, pose: tuple[float, float, float]) -> MemoryScan:
    """The nearest remembered point per bearing around the robot at ``pose`` (odometry frame);
    every bearing NaN (unknown) for a pose outside the odometry limits."""
    p = state.params
    nb = p.scan_bins
    out = np.empty(nb, np.float32)
    counts = np.zeros(3, np.int64)
    checked = check_odom_pose(*pose)
    if isinstance(checked, OdomRefusal):
        out[:] = np.nan
        counts[1:] = np.bincount(state.grid.reshape(-1), minlength=3)[1:3]  # as the kernel
    else:
        g = state
        memory_scan(g.grid, g.offx, g.offy, g.wx0, g.wy0, p.cell_m, *checked, out, counts)
    inc = 2.0 * math.pi / nb
    scan = LaserScan(-math.pi, -math.pi + (nb - 1) * inc, inc, 0.0, p.size_m * math.sqrt(0.5), out)
    return MemoryScan(scan, int(counts[OBSTACLE]), int(counts[CLIFF]))


@dataclass(frozen=True, slots=True)
class GridSnapshot:
    """The grid for a viewer, in window order: cell [i, j] covers odometry x in
    [origin_x + i * cell, + cell), y likewise.

    Attributes:
        grid: (n, n) uint8 FREE (0) / OBSTACLE (1) / CLIFF (2), a copy.
        origin_m: (x, y) odometry coordinates of the grid's corner, metres.
        cell_m: cell side, metres.
    """

    grid: npt.NDArray[np.uint8]
    origin_m: tuple[float, float]
    cell_m: float


def snapshot(state: MemoryState) -> GridSnapshot:
    """A copy of the grid in window order (for drawing)."""
    n, cell = state.params.cells, state.params.cell_m
    g = np.roll(state.grid, (-(state.wx0 % n), -(state.wy0 % n)), axis=(0, 1))
    g.setflags(write=False)
    return GridSnapshot(g, (state.wx0 * cell, state.wy0 * cell), cell)


__all__ = [
    "GridSnapshot",
    "MemoryParams",
    "MemoryResult",
    "MemoryScan",
    "MemoryState",
    "SensorView",
    "UpdateReport",
    "near_limits",
    "new_state",
    "read_scan",
    "reset",
    "snapshot",
    "update",
]


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
