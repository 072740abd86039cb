"""The rerun sink's 3-D view (``/world``, the robot's base frame, x forward, y left, z up, floor
z = 0): the sensor's frustum, the scan and the cliff scan as lines on the floor, each drop-off's
lower floor as a filled mesh from its edge, the memory's cells and its 360 deg scan. Colours as the
top-down view's (amber while the mount is not trusted)."""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

import numpy as np

from depthnav_daemon.plots.overlays import area_polygon, memory_cells_xy, scan_strips
from depthnav_daemon.sinks.rerun import topdown

if TYPE_CHECKING:
    from depthnav_daemon.pipeline import Result
    from depthnav_daemon.pipeline.scan import LaserScan
    from depthnav_daemon.plots.overlays import DropoffAreas
    from drivers.base import Intrinsics

DEPTH = "/world/sensor/depth"
SCAN_Z_M = 0.01  # scan hits are drawn just above the floor, like a footprint map
AREA_Z_M = 0.004  # drop-off areas lie on the floor, under the scans
FRUSTUM_DEPTH_M = 0.5


def _xy_to_points3d(x: np.ndarray, y: np.ndarray, z: float) -> np.ndarray:
    return np.stack([x, y, np.full_like(x, z)], axis=1).astype(np.float32)


def scan_points(scan: LaserScan, z: float = SCAN_Z_M) -> np.ndarray:
    """(K, 3) float32 points of a scan's finite ranges, level frame at the sensor's foot."""
    r = np.asarray(scan.ranges, dtype=np.float64)
    ok = np.isfinite(r)
    a = scan.angles[ok]
    return _xy_to_points3d(r[ok] * np.cos(a), r[ok] * np.sin(a), z)


def log_intrinsics(rr: Any, rec: Any, intr: Intrinsics) -> None:
    """The pinhole of the depth image and the sensor's frustum in 3-D (static; again on change)."""
    rec.log(
        DEPTH,
        rr.Pinhole(
            focal_length=[intr.fx, intr.fy],
            principal_point=[intr.cx, intr.cy],
            width=intr.width,
            height=intr.height,
            camera_xyz=rr.ViewCoordinates.FLU,
            image_plane_distance=FRUSTUM_DEPTH_M,
        ),
        static=True,
    )
    # corners of the image at FRUSTUM_DEPTH_M, sensor body frame (x forward, y left, z up)
    u = (np.array([0.0, intr.width, intr.width, 0.0]) - 0.5 - intr.cx) / intr.fx
    v = (np.array([0.0, 0.0, intr.height, intr.height]) - 0.5 - intr.cy) / intr.fy
    d = FRUSTUM_DEPTH_M
    corners = np.stack([np.full(4, d), -u * d, -v * d], axis=1)
    strips = [[[0.0, 0.0, 0.0], c] for c in corners.tolist()]
    strips.append([*corners.tolist(), corners[0].tolist()])
    rec.log(
        "/world/sensor/fov",
        rr.LineStrips3D(strips, radii=0.004, colors=[[74, 144, 217]]),
        static=True,
    )


def log_world(rr: Any, rec: Any, result: Result, areas: DropoffAreas) -> None:
    color = topdown.scan_rgb(result)
    rec.log("/world/scan", rr.Points3D(scan_points(result.scan), radii=0.02, colors=[color]))
    strips = [_xy_to_points3d(s[:, 0], s[:, 1], SCAN_Z_M) for s in scan_strips(result.scan)]
    rec.log("/world/scan/line", rr.LineStrips3D(strips, radii=0.008, colors=[color]))
    _log_world_memory(rr, rec, result)
    cliff = result.cliff
    if cliff is None:
        return
    pts = np.asarray(cliff.points_m, dtype=np.float32).reshape(-1, 2)
    drop = topdown.cliff_rgb(result)
    rec.log(
        "/world/cliff/points",
        rr.Points3D(_xy_to_points3d(pts[:, 0], pts[:, 1], 0.0), radii=0.01, colors=[drop]),
    )
    verts, tris = area_mesh(areas)
    rec.log(
        "/world/cliff/area",
        rr.Mesh3D(
            vertex_positions=verts,
            triangle_indices=tris,
            albedo_factor=[*drop, 150],
        ),
    )
    cs = [_xy_to_points3d(s[:, 0], s[:, 1], 0.02) for s in scan_strips(cliff.scan)]
    rec.log("/world/cliff/scan", rr.LineStrips3D(cs, radii=0.02, colors=[drop]))


def area_mesh(areas: DropoffAreas) -> tuple[np.ndarray, np.ndarray]:
    """The drop-off areas as one triangle mesh on the floor: (V, 3) float32 vertices, (T, 3)
    uint32 triangles, two per pair of neighbouring columns (near i, near i+1, far i+1, far i)."""
    verts, tris, base = [], [], 0
    for near, far in areas.areas:
        k = len(near)
        poly = area_polygon(near, far)[:-1]  # near 0..k-1, far k-1..0
        verts.append(_xy_to_points3d(poly[:, 0], poly[:, 1], AREA_Z_M))
        i = np.arange(k - 1)
        far_i, far_j = 2 * k - 1 - i, 2 * k - 2 - i  # far i, far i+1
        tris.append(np.stack([i, i + 1, far_j], 1) + base)
        tris.append(np.stack([i, far_j, far_i], 1) + base)
        base += 2 * k
    if not verts:
        return np.zeros((0, 3), np.float32), np.zeros((0, 3), np.uint32)
    return np.concatenate(verts), np.concatenate(tris).astype(np.uint32)


def _log_world_memory(rr: Any, rec: Any, result: Result) -> None:
    """The memory's cells (flat boxes) and its 360 deg scan on the 3-D floor."""
    obstacles, cliffs, cell = memory_cells_xy(result)
    for name, xy, color in (
        ("obstacles", obstacles, topdown.MEMORY_OBSTACLE_RGB),
        ("cliffs", cliffs, topdown.MEMORY_CLIFF_RGB),
    ):
        rec.log(
            f"/world/memory/{name}",
            rr.Boxes3D(
                centers=_xy_to_points3d(xy[:, 0], xy[:, 1], 0.002),
                half_sizes=np.tile([cell / 2, cell / 2, 0.002], (len(xy), 1)),
                colors=[color],
                fill_mode=rr.components.FillMode.Solid,
            ),
        )
    scan = result.memory.scan if result.memory is not None else None
    strips = [] if scan is None else scan_strips(scan)
    rec.log(
        "/world/memory/scan",
        rr.LineStrips3D(
            [_xy_to_points3d(s[:, 0], s[:, 1], SCAN_Z_M) for s in strips],
            radii=0.006,
            colors=[topdown.MEMORY_SCAN_RGB],
        ),
    )
