"""Obstacle memory: a rolling grid around the robot in the odometry frame (the costmap layer).

The paper's cliff detector "maps the obstacles to a dedicated layer in a costmap" (sec. 2.3;
depth_nav_tools' ``nav_layer_from_points`` keeps points for 0.75 s). Here the layer keeps what the
sensors can no longer see: a grid of ``size_m`` x ``size_m`` with cells of ``cell_m`` (default
8 x 8 m at 5 cm) follows the robot, in the odometry frame (x, y, yaw of the robot's base frame).

A cell is unknown (never seen, left the window, forgotten), known free, or occupied (OBSTACLE or
CLIFF, keeping where in it its last point was, so the memory scan is not rounded to cells). Each
sensor view (its level-frame scan, cliff scan and placement on the robot) updates only what it saw:
- on each scan bin the image sees the floor between ``near`` and ``far`` (coverage.floor_extent:
  its lower dead zone, and where the bearing leaves the image); the floor seen free is
  [near, min(far, what the bin hit minus a margin)] (+inf bin: out to min(far, range_max); NaN or
  -inf bin: nothing). Remembered points there are cleared (a person who walked away disappears)
  and the cells there become known free; never beyond ``far``, never along a whole bearing;
- obstacle cells are marked at the scan's points, cliff cells at the cliff scan's (the nearest
  drop-off floor point per bearing, i.e. the edge); a -inf bin (too close) marks an obstacle at
  the scan's range_min on its bearing (it is there or nearer);
- what a bin saw beyond its point (up to its farthest obstacle pixel, LaserScan.far: a face seen
  edge-on, a wall above a low box) is not kept: the never-seen cells there become a SHADOW (from
  1.5 cells behind the point; memory_update_kernels.shadow_view);
- cells it does not see (dead zones, behind, beside, beyond ``far``) keep their state; with
  ``max_age_s`` > 0 a cell not seen again for that long (occupied or free) becomes unknown.

The memory scan (:func:`read_scan`) follows REP 117 around the robot: a finite range is the
nearest remembered point on the bearing, unless a SHADOW cell lies in front of it (by more than
:func:`hole_m`): then NaN, and MemoryScan.hidden says so (cells never seen before the point are
not judged); +inf = every cell the bearing's bin touches from ``blind_m`` (no sensor sees under the
robot) out to ``range_max_m`` is known free; NaN = unknown.

State lives in :class:`MemoryState`, owned by the caller and passed to every call (no globals);
``update`` changes it in place (copying the grid every frame would cost more than the update) and
returns what it did. ``read_scan`` reads it. The daemon decides when odometry is good enough.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
import numpy.typing as npt

from depthnav_daemon.pipeline.coverage import floor_extent
from depthnav_daemon.pipeline.geometry import F32, check_range
from depthnav_daemon.pipeline.laser_scan import LaserScan
from depthnav_daemon.pipeline.memory_io import (
    GridSnapshot,
    MemoryResult,
    MemoryScan,
    SensorView,
    UpdateReport,
)
from depthnav_daemon.pipeline.memory_kernels import (
    CLIFF,
    KNOWN_FREE,
    OBSTACLE,
    clear_lines,
    expire,
    expire_free,
)
from depthnav_daemon.pipeline.memory_read_kernels import BLOCK, memory_read
from depthnav_daemon.pipeline.memory_update_kernels import update_view
from drivers.base import OdomRefusal, check_odom_pose

MAX_CELLS = 2048  # cells per side
DEFAULT_RANGE_MAX_M = 4.0  # how far the memory scan's +inf claims known free, at most
HOLE_CELLS = 0.5 * math.sqrt(2.0)  # hole_m: a cell's half diagonal, in cells
HOLE_MARGIN_M = 0.02  # hole_m: the obstacles' stated error
_EMPTY = np.empty(0, np.float32)
_EMPTY_U8 = np.empty(0, np.uint8)


@dataclass(frozen=True, slots=True)
class MemoryParams:
    """Memory parameters.

    Attributes:
        size_m: side of the square grid around the robot, metres.
        cell_m: cell side, metres.
        max_age_s: forget a cell (occupied or free) not seen again for this long (0 = keep it
            until it leaves the grid or a sensor sees it otherwise).
        scan_increment_deg: bin width of the 360 deg memory scan, degrees (divides 360).
        range_max_m: the memory scan's range_max: how far its +inf claims known free, metres.
            None: the smallest of 4 m, the grid's reach (half its side less two cells: 3.9 m
            for the default 8 m grid) and the sensors' scan range_max.
        blind_m: radius around the base origin the memory scan does not judge (no sensor sees
            under the robot), metres. None: from the sensors' mounts (:func:`scan_limits`).
    """

    size_m: float = 8.0
    cell_m: float = 0.05
    max_age_s: float = 0.0
    scan_increment_deg: float = 1.0
    range_max_m: float | None = None
    blind_m: float | None = None

    def __post_init__(self) -> None:
        check_range("memory.cell_m", self.cell_m, 0.005, 1.0, " m")
        check_range("memory.size_m", self.size_m, 2 * self.cell_m, MAX_CELLS * self.cell_m, " m")
        check_range("memory.max_age_s", self.max_age_s, 0.0, 86400.0, " s")
        check_range("memory.scan_increment_deg", self.scan_increment_deg, 0.1, 10.0, " deg")
        if self.range_max_m is not None:
            check_range(
                "memory.range_max_m", self.range_max_m, self.cell_m, self.grid_reach_m, " m"
            )
        if self.blind_m is not None:
            check_range("memory.blind_m", self.blind_m, 0.0, 10.0, " m")

    @property
    def cells(self) -> int:
        """Cells per side (a multiple of 8: the kernels read the arrays 8 bytes at a time, and
        the read-back in blocks of 8 x 8 cells)."""
        return BLOCK * max(1, round(self.size_m / self.cell_m / BLOCK))

    @property
    def grid_reach_m(self) -> float:
        """How far the memory scan can judge on every bearing, metres: half the grid's side less
        two cells (the robot may sit anywhere in its cell, and a cell is judged while its
        circumscribed disc reaches within range_max)."""
        return (self.cells // 2 - 2) * self.cell_m

    @property
    def scan_bins(self) -> int:
        return round(360.0 / self.scan_increment_deg)


@dataclass(slots=True)
class MemoryState:
    """The grid and where it is; see the module docstring. Create with :func:`new_state`.

    Attributes:
        grid: (n, n) uint8 FREE / OBSTACLE / CLIFF, toroidal: global cell (gx, gy) at index
            (gx mod n, gy mod n).
        stamp: (n, n) float32 seconds since ``epoch_s`` each occupied cell was last marked.
        offx, offy: (n, n) float32 position of each cell's last point inside it, metres.
        known: (n, n) uint8 1 = known free (then grid is FREE), 0 = unknown or occupied.
        free_t: (n, n) float32 seconds since ``epoch_s`` each known-free cell was last seen free.
        wx0, wy0: global cell index of the window's first column and row.
        epoch_s: time origin of ``stamp`` and ``free_t`` (the first update's time).
        blind_by_sensor: per sensor placement (x_m, y_m, yaw_deg), the farthest point of its lower
            dead zone straight ahead from the base origin, metres (for ``blind_m`` = None).
        sensor_range_max_m: the largest scan range_max of the views so far, metres (0: none).
        noted: per sensor placement, the floor table its entry in ``blind_by_sensor`` is from.
    """

    params: MemoryParams
    grid: npt.NDArray[np.uint8]
    stamp: F32
    offx: F32
    offy: F32
    known: npt.NDArray[np.uint8]
    free_t: F32
    wx0: int = 0
    wy0: int = 0
    epoch_s: float | None = None
    updates: int = 0
    blind_by_sensor: dict[tuple[float, float, float], float] = field(default_factory=dict)
    sensor_range_max_m: float = 0.0
    noted: dict[tuple[float, float, float], F32] = field(default_factory=dict)


def new_state(params: MemoryParams) -> MemoryState:
    """An empty memory: every cell unknown."""
    n = params.cells
    return MemoryState(
        params,
        np.zeros((n, n), np.uint8),
        np.zeros((n, n), np.float32),
        np.zeros((n, n), np.float32),
        np.zeros((n, n), np.float32),
        np.zeros((n, n), np.uint8),
        np.zeros((n, n), np.float32),
    )


def reset(state: MemoryState) -> None:
    """Forget everything (a jump in the odometry): every cell unknown."""
    state.grid[:] = 0
    state.known[:] = 0
    state.epoch_s = None


def scan_limits(state: MemoryState) -> tuple[float, float]:
    """(blind_m, range_max_m) of the memory scan: the params' where set; else the largest
    distance from the base origin to a point of a sensor's lower dead zone straight ahead (0
    before any view), and the smallest of 4 m, the grid's reach and the views' scan range_max."""
    p = state.params
    blind = p.blind_m
    if blind is None:
        blind = max(state.blind_by_sensor.values(), default=0.0)
    rmax = p.range_max_m
    if rmax is None:
        rmax = min(DEFAULT_RANGE_MAX_M, p.grid_reach_m)
        if state.sensor_range_max_m > 0:
            rmax = min(rmax, state.sensor_range_max_m)
    return float(blind), float(rmax)


def _recentre(state: MemoryState, x_m: float, y_m: float) -> None:
    n, cell = state.grid.shape[0], state.params.cell_m
    nx0 = math.floor(x_m / cell) - n // 2
    ny0 = math.floor(y_m / cell) - n // 2
    if nx0 != state.wx0 or ny0 != state.wy0:
        if state.updates == 0:
            state.grid[:] = 0
            state.known[:] = 0
        else:
            clear_lines(state.grid, state.known, state.wx0, state.wy0, nx0, ny0)
        state.wx0, state.wy0 = nx0, ny0


def _bin_mask(bins: npt.NDArray[np.intp] | None, n: int) -> npt.NDArray[np.uint8]:
    """(n,) uint8 1 at ``bins``, or an empty array for None (no bin)."""
    if bins is None:
        return _EMPTY_U8
    out = np.zeros(n, np.uint8)
    out[bins] = 1
    return out


def _note_sensor(state: MemoryState, v: SensorView, near: F32) -> None:
    """Remember the view's dead zone straight ahead (for ``blind_m``) and its range_max; only
    when its floor table changed (a new mount or layout)."""
    m, sc = v.mount, v.scan
    key = (m.x_m, m.y_m, m.yaw_deg)
    if state.noted.get(key) is near:
        return
    state.noted[key] = near
    state.sensor_range_max_m = max(state.sensor_range_max_m, float(sc.range_max))
    i0 = round(-float(sc.angle_min) / float(sc.angle_increment))
    if not 0 <= i0 < near.size or not math.isfinite(float(near[i0])):
        state.blind_by_sensor.pop(key, None)
        return  # it sees no floor straight ahead: no dead zone to speak of
    d = float(near[i0])
    tip = (m.x_m + d * math.cos(m.yaw_rad), m.y_m + d * math.sin(m.yaw_rad))
    # + 1.5 cell diagonals: the fill marks a cell known free only whole, so the cells within a
    # diagonal of the dead zone's edge stay unknown (memory_update_kernels.fill_view), and the
    # read-back judges every cell reaching beyond blind_m (half a diagonal)
    edge = max(math.hypot(m.x_m, m.y_m), math.hypot(*tip))
    state.blind_by_sensor[key] = edge + 1.5 * math.sqrt(2.0) * state.params.cell_m


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
        margin_m: a remembered point this close to what a sensor sees now is kept, and the floor
            this close to it is not known free (default a fifth of a cell), or the floor spanned
            by the view's margin rows if that is more.

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
    g = state
    for v in views:
        m, sc = v.mount, v.scan
        n = sc.ranges.size
        a0, inc = float(sc.angle_min), float(sc.angle_increment)
        level = m.level_part()
        near, far = floor_extent(v.intrinsics, level, a0, inc, n, v.rows)
        cs = v.cliff_scan
        cnear, cfar, cliff, crmin, crmax = near, far, _EMPTY, 0.0, 0.0
        if cs is not None:
            cliff = np.ascontiguousarray(cs.ranges, dtype=np.float32)
            crmin, crmax = float(cs.range_min), float(cs.range_max)
            crows = v.rows if v.cliff_rows is None else v.cliff_rows
            if crows != v.rows:
                cnear, cfar = floor_extent(v.intrinsics, level, a0, inc, n, crows)
        free_nan, cfree_nan = _bin_mask(v.short_free, n), _bin_mask(v.cliff_short_free, n)
        sx, sy, syaw = x + c * m.x_m - s * m.y_m, y + s * m.x_m + c * m.y_m, yaw + m.yaw_rad
        k, j, _ = update_view(
            g.grid, g.stamp, g.offx, g.offy, g.known, g.free_t, g.wx0, g.wy0, p.cell_m, sx, sy,
            syaw, np.ascontiguousarray(sc.ranges, dtype=np.float32), free_nan, cliff, cfree_nan,
            near, far, cnear, cfar, a0, inc, float(sc.range_min), float(sc.range_max), crmin,
            crmax, margin, 1.0 / (m.height_m * v.intrinsics.fy), m.height_m**2,
            float(v.scan_margin_rows), float(v.cliff_margin_rows), t_rel,
            _EMPTY if sc.far is None else np.ascontiguousarray(sc.far, dtype=np.float32),
        )  # fmt: skip
        cleared += k
        marked += j
        _note_sensor(state, v, near)
    expired = forgotten = 0
    if p.max_age_s > 0:
        oldest = np.float32(t_rel - p.max_age_s)
        expired = expire(g.grid, g.stamp, oldest)
        forgotten = expire_free(g.known, g.free_t, oldest)
    state.updates += 1
    return UpdateReport(int(cleared), int(marked), int(expired), None, int(forgotten))


def read_scan(state: MemoryState, pose: tuple[float, float, float]) -> MemoryScan:
    """The memory scan around the robot at ``pose`` (odometry frame), in the base frame.

    Per bin: the nearest remembered point covering it within range_max, NaN if a SHADOW cell lies
    in front of it (:func:`hole_m`; cells never seen are not judged); else +inf if every cell the
    bin touches between ``blind_m`` and range_max (:func:`scan_limits`) is known free; else NaN.
    Every bearing is NaN for a pose outside the odometry limits.
    """
    p = state.params
    nb = p.scan_bins
    out = np.empty(nb, np.float32)
    hidden = np.zeros(nb, np.uint8)
    counts = np.zeros(3, np.int64)
    blind, rmax = scan_limits(state)
    checked = check_odom_pose(*pose)
    if isinstance(checked, OdomRefusal):
        out[:] = np.nan
        counts[1:] = np.bincount(state.grid.reshape(-1), minlength=3)[1:3]  # as the kernel
    else:
        g = state
        memory_read(
            g.grid, g.offx, g.offy, g.known, g.wx0, g.wy0, p.cell_m, *checked, blind, rmax,
            hole_m(p), out, hidden, counts,
        )  # fmt: skip
    inc = 2.0 * math.pi / nb
    scan = LaserScan(-math.pi, -math.pi + (nb - 1) * inc, inc, 0.0, rmax, out)
    return MemoryScan(scan, int(counts[OBSTACLE]), int(counts[CLIFF]), blind, hidden.view(np.bool_))


def hole_m(params: MemoryParams) -> float:
    """How much nearer than a remembered point a shadow cell's centre must lie for the memory
    scan to read that point's bins NaN, metres: a cell's half diagonal and the obstacles' stated
    error. What stands in a cell whose centre lies nearer than the point by less is at most a
    cell's diagonal and that error nearer (the memory's stated error: it keeps one point per
    cell)."""
    return HOLE_CELLS * params.cell_m + HOLE_MARGIN_M


def snapshot(state: MemoryState) -> GridSnapshot:
    """A copy of the grid and its known-free layer in window order (for drawing, sinks)."""
    n, cell = state.params.cells, state.params.cell_m
    shift, axes = (-(state.wx0 % n), -(state.wy0 % n)), (0, 1)
    g = np.roll(state.grid, shift, axis=axes)
    known = (np.roll(state.known, shift, axis=axes) == KNOWN_FREE).view(np.uint8)
    g.setflags(write=False)
    known.setflags(write=False)
    return GridSnapshot(g, (state.wx0 * cell, state.wy0 * cell), cell, known)


__all__ = [
    "GridSnapshot",
    "MemoryParams",
    "MemoryResult",
    "MemoryScan",
    "MemoryState",
    "SensorView",
    "UpdateReport",
    "new_state",
    "read_scan",
    "reset",
    "scan_limits",
    "snapshot",
    "update",
]
