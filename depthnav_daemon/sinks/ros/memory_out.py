"""The obstacle memory as the ``rosbag``, ``ros2`` and ``foxglove`` sinks send it.

Read from ``Result.memory`` only (pipeline.memory_io.MemoryResult: the pose the memory used, its
360 deg scan and a copy of its grid, :class:`GridSnapshot`), never from the memory's own code:

- :func:`occupancy`: the grid as occupancy values in the odometry frame, row-major with rows
  along y (``nav_msgs/OccupancyGrid``'s and ``foxglove.Grid``'s layout): 100 where an obstacle
  or a drop-off is remembered, 0 where the memory knows the floor is free, -1 unknown. The grid
  is the memory's own size (``[memory] size_m / cell_m`` cells a side: 160 x 160 = 25,600 cells
  for the default 8 m at 5 cm; at most 2048 a side);
- :func:`cliff_cells_xy`: the remembered drop-off cells' centres in the base frame (the robot
  at the memory's pose), for a PointCloud2 Nav2 can mark (at most one point per cell);
- :class:`GridClock`: when the next grid is due (``grid_rate``, per second of frame time);
- :class:`MemoryMessages`: the ROS messages (``/memory/grid``, ``/memory/scan``, ``/tf``
  odom -> base, ``/memory/cliff/points``) for the rosbag and ros2 sinks.

Known free: ``GridSnapshot`` holds the occupied cells (0 = not occupied: free or unknown) and
``known`` (1 = known free, window order as ``grid``). A snapshot without ``known`` sends every
cell that is not occupied as -1 (unknown), never as free: the grid claims no free floor it cannot
show (the safety contract).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np
import numpy.typing as npt

if TYPE_CHECKING:
    from depthnav_daemon.pipeline import Result
    from depthnav_daemon.pipeline.memory_io import GridSnapshot, MemoryResult
    from depthnav_daemon.sinks.ros.messages import MessageBuilder

# GridSnapshot.grid's values (pipeline.memory_kernels; sinks do not import kernel modules)
OBSTACLE, CLIFF = 1, 2
OCCUPIED, FREE, UNKNOWN = 100, 0, -1  # nav_msgs/OccupancyGrid's values
I8 = npt.NDArray[np.int8]
# a viewer's colours (r, g, b, a) per cell: unknown, known free, obstacle, drop-off
RGBA = np.array(
    [(0, 0, 0, 0), (90, 200, 110, 50), (230, 40, 25, 230), (255, 60, 255, 230)], np.uint8
)


@dataclass(frozen=True, slots=True)
class Occupancy:
    """The memory's grid as occupancy values.

    Attributes:
        cells: (rows, cols) int8 OCCUPIED / FREE / UNKNOWN; ``cells[r, c]`` covers odometry
            x in [origin_x + c * cell_m, + cell_m), y in [origin_y + r * cell_m, + cell_m).
        kinds: (rows, cols) uint8 as ``GridSnapshot.grid`` (0, OBSTACLE, CLIFF), same layout.
        origin_m: (x, y) of the grid's corner in the odometry frame, metres.
        cell_m: cell side, metres.
        known_free: whether FREE cells come from the memory's known-free layer (else there are
            none: every cell not occupied is UNKNOWN).
    """

    cells: I8
    kinds: npt.NDArray[np.uint8]
    origin_m: tuple[float, float]
    cell_m: float
    known_free: bool


def occupancy(snap: GridSnapshot) -> Occupancy:
    """Occupancy values of a grid snapshot (module docstring); a copy, rows along y."""
    kinds = np.ascontiguousarray(snap.grid.T)  # snapshot [i, j] is (x, y): rows along y
    cells = np.full(kinds.shape, UNKNOWN, np.int8)
    known = snap.known  # None: no known-free layer given, nothing is sent as free
    if known is not None:
        cells[np.asarray(known).T != 0] = FREE
    cells[kinds != 0] = OCCUPIED  # obstacles and drop-offs alike
    ox, oy = snap.origin_m
    return Occupancy(cells, kinds, (float(ox), float(oy)), float(snap.cell_m), known is not None)


def occupancy_rgba(occ: Occupancy) -> npt.NDArray[np.uint8]:
    """(rows, cols, 5) uint8 per cell: the occupancy value's byte (int8), then red, green, blue,
    alpha (:data:`RGBA`: obstacles red, drop-offs magenta, known free faint green, unknown
    clear), for ``foxglove.Grid``."""
    kind = (occ.cells == FREE).astype(np.uint8)
    kind[occ.kinds == OBSTACLE] = 2
    kind[occ.kinds == CLIFF] = 3
    out = np.empty((*occ.cells.shape, 5), np.uint8)
    out[..., 0] = occ.cells.view(np.uint8)
    out[..., 1:] = RGBA[kind]
    return out


def cliff_cells_xy(memory: MemoryResult) -> npt.NDArray[np.float32]:
    """(K, 2) float32 x, y (metres) in the base frame of the remembered drop-off cells' centres,
    the robot at the memory's pose; empty without a grid or pose. A point may lie up to half a
    cell's diagonal from the remembered edge (2.5 cm x sqrt 2 at 5 cm cells)."""
    snap, pose = memory.grid, memory.pose
    if snap is None or pose is None:
        return np.empty((0, 2), np.float32)
    i, j = np.nonzero(snap.grid == CLIFF)
    x, y, yaw = pose
    ox = snap.origin_m[0] + (i + 0.5) * snap.cell_m - x  # odometry frame, robot at the origin
    oy = snap.origin_m[1] + (j + 0.5) * snap.cell_m - y
    c, s = math.cos(yaw), math.sin(yaw)
    xy = np.empty((i.size, 2), np.float32)
    xy[:, 0] = c * ox + s * oy  # into the base frame
    xy[:, 1] = -s * ox + c * oy
    return xy


def live_memory(result: Result) -> MemoryResult | None:
    """``result.memory`` when it has something to send (updated with this frame: status "on" or
    "reset"); None when the memory is off or frozen (stale or refused odometry)."""
    mem = result.memory
    if mem is None or mem.pose is None or mem.scan is None:
        return None
    return mem


class GridClock:
    """When the next grid is due: the first at once, then one per ``1 / rate_hz`` seconds of
    frame time (a frame time that goes back restarts the count). ``rate_hz`` 0: never."""

    def __init__(self, rate_hz: float) -> None:
        self.period_s = math.inf if rate_hz <= 0 else 1.0 / rate_hz
        self._last: float | None = None

    def due(self, t_s: float) -> bool:
        """Whether a grid goes out at frame time ``t_s`` (seconds); counts it when it does."""
        if math.isinf(self.period_s):
            return False
        last = self._last
        # a frame within 1 ms of the period counts as on time (frame times carry jitter)
        if last is None or t_s < last or t_s - last >= self.period_s - 1e-3:
            self._last = t_s
            return True
        return False


def yaw_quaternion(yaw_rad: float) -> tuple[float, float, float, float]:
    """(x, y, z, w) of a turn by ``yaw_rad`` about z, w >= 0."""
    half = math.remainder(yaw_rad, 2.0 * math.pi) / 2.0
    return 0.0, 0.0, math.sin(half), math.cos(half)


class MemoryMessages:
    """The memory's ROS messages of one frame for the rosbag and ros2 sinks.

    Topics (names are the sinks' options, see sinks/ros/messages.py): ``/memory/grid``
    (nav_msgs/OccupancyGrid in ``odom_frame``, at ``grid_rate``), ``/memory/scan``
    (sensor_msgs/LaserScan: the memory scan as the pipeline gives it, in ``scan_frame`` like
    ``/scan``: ranges from the base origin, the base's axes), ``/tf`` (odom -> base, its own
    TFMessage, unless ``tf=0`` or ``odom_tf=0``) and ``/memory/cliff/points`` (PointCloud2 in
    the base frame at ``cliff_z``, like ``/cliff/points``).

    Args:
        builder: the sink's message builder (its typestore, names and headers).
    """

    def __init__(self, builder: MessageBuilder) -> None:
        self.builder = builder
        self.names = builder.names
        self.t = builder.store.types
        self.clock = GridClock(self.names.grid_rate)

    def msgtypes(self) -> dict[str, str]:
        """topic -> message type of every memory topic this sink may write."""
        n = self.names
        out = {
            n["memory_scan_topic"]: "sensor_msgs/msg/LaserScan",
            n["memory_cliff_points_topic"]: "sensor_msgs/msg/PointCloud2",
        }
        if n.grid_rate > 0:
            out[n["memory_grid_topic"]] = "nav_msgs/msg/OccupancyGrid"
        if n.tf and n.odom_tf:
            out[n["tf_topic"]] = "tf2_msgs/msg/TFMessage"
        return out

    def messages(self, result: Result, t_ns: int) -> list[tuple[str, Any]]:
        """[(topic, message)] of the memory with this frame, stamped ``t_ns``: none when the
        memory is off or frozen; the grid only when due."""
        mem = live_memory(result)
        if mem is None:
            return []
        assert mem.scan is not None and mem.pose is not None
        n, b = self.names, self.builder
        out: list[tuple[str, Any]] = []
        if n.tf and n.odom_tf:
            out.append((n["tf_topic"], self.odom_tf(mem.pose, t_ns)))
        if mem.grid is not None and self.clock.due(result.timestamp_s):
            out.append((n["memory_grid_topic"], self.grid(occupancy(mem.grid), t_ns)))
        out.append((n["memory_scan_topic"], b.laser_scan(mem.scan, t_ns)))
        xyz = np.empty((0, 3), "<f4")
        xy = cliff_cells_xy(mem)
        if xy.size:
            xyz = np.empty((len(xy), 3), "<f4")
            xyz[:, :2] = xy
            xyz[:, 2] = np.float32(n.cliff_z)
        out.append((n["memory_cliff_points_topic"], b.points(xyz, t_ns)))
        return out

    def odom_tf(self, pose: tuple[float, float, float], t_ns: int) -> Any:
        """/tf: odom -> base, the robot at the memory's odometry pose (x, y m, yaw rad)."""
        t = self.t
        x, y, z, w = yaw_quaternion(pose[2])
        transform = t["geometry_msgs/msg/TransformStamped"](
            header=self.builder.header(t_ns, self.names["odom_frame"]),
            child_frame_id=self.names["base_frame"],
            transform=t["geometry_msgs/msg/Transform"](
                translation=t["geometry_msgs/msg/Vector3"](x=pose[0], y=pose[1], z=0.0),
                rotation=t["geometry_msgs/msg/Quaternion"](x=x, y=y, z=z, w=w),
            ),
        )
        return t["tf2_msgs/msg/TFMessage"](transforms=[transform])

    def grid(self, occ: Occupancy, t_ns: int) -> Any:
        """nav_msgs/OccupancyGrid in the odometry frame."""
        t = self.t
        rows, cols = occ.cells.shape
        origin = t["geometry_msgs/msg/Pose"](
            position=t["geometry_msgs/msg/Point"](x=occ.origin_m[0], y=occ.origin_m[1], z=0.0),
            orientation=t["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0, w=1.0),
        )
        header = self.builder.header(t_ns, self.names["odom_frame"])
        info = t["nav_msgs/msg/MapMetaData"](
            map_load_time=header.stamp, resolution=occ.cell_m, width=cols, height=rows,
            origin=origin,
        )  # fmt: skip
        return t["nav_msgs/msg/OccupancyGrid"](header=header, info=info, data=occ.cells.ravel())
