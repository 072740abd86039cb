"""What the rerun sink shows: the entities it logs per frame and the default layout (blueprint).

The layout puts depthnav's results first: a top-down view (the paper's costmap figures), the depth
image with strong colours over a grey palette, a 3-D view from behind and above the robot without
rerun's point cloud of the whole depth image (hidden, one toggle away in the blueprint panel), and
plots of the mount against its configured value and of the stage timings after the warm-up frame.
The entity paths are listed in ``sinks/rerun/rerun.py``; every rerun call of depthnav lives in
these two modules (the API moves between releases).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from depthnav_daemon.pipeline.geometry import rot_x, rot_y, rot_z
from depthnav_daemon.sinks.rerun import topdown
from depthnav_daemon.sinks.rerun.depth import CLASS_CLIFF, CLASS_OBSTACLE, CLIFF_RGBA, log_depth

if TYPE_CHECKING:
    from depthnav_daemon.pipeline import MountTrust, Result
    from depthnav_daemon.pipeline.geometry import Mount
    from depthnav_daemon.pipeline.scan import LaserScan
    from depthnav_daemon.sinks.base import SinkContext
    from drivers.base import Frame, Intrinsics

DEPTH = "/world/sensor/depth"
STATS = "/stats"
STEADY_TIMING = f"{STATS}/timing_after_warmup"
SCAN_Z_M = 0.01  # scan hits are drawn just above the floor, like a footprint map
SCAN_RGB = topdown.SCAN_RGB
CLIFF_RGB = topdown.CLIFF_RGB
OBSTACLE_RGBA = (255, 30, 30, 230)
CONFIG_RGB = (150, 150, 150)
FRUSTUM_DEPTH_M = 0.5
# pose series: (key, unit, colour of the mount in use); the floor estimate and the configured
# value share the view, as points and a grey line
POSE_SERIES = (
    ("height", "m", (255, 128, 0)),
    ("tilt", "deg", (0, 160, 255)),
    ("roll", "deg", (160, 80, 255)),
)
POSE_DEFAULT = {"height": 0.5, "tilt": 0.0, "roll": 0.0}  # scales when no mount is configured
STAGE_COLORS = {"scan": (0, 200, 80), "cliff": (230, 0, 230), "pose": (255, 170, 0)}


@dataclass
class LayoutState:
    """The sink's drawing settings, and what was last logged as static (logged again only when
    it changes).

    Attributes:
        footprint_m: the robot's length and width drawn behind the sensor, metres.
        reach_m: the scan's range_max (the top-down view's extent, the depth palette's far end).
        block_size: the configured cliff block side, pixels (when a result carries none).
        configured: the configured mount, plotted beside the mount in use; None if unknown.
        frames: frames logged so far (the first one is the warm-up).
        intrinsics, scan_layout: what the pinhole and the field of view were last logged for.
        trust: the mount trust last logged to /log (logged again when it changes).
    """

    footprint_m: tuple[float, float] = topdown.DEFAULT_FOOTPRINT_M
    reach_m: float = 5.0
    block_size: int = 16
    configured: Mount | None = None
    frames: int = 0
    intrinsics: Intrinsics | None = None
    scan_layout: tuple[float, float, int] | None = None
    trust: MountTrust | None = None


def _xy_to_points3d(x: np.ndarray, y: np.ndarray, z: float) -> np.ndarray:
    return np.stack([x, y, np.full_like(x, z)], axis=1).astype(np.float32)


def scan_points(scan: LaserScan, z: float = SCAN_Z_M) -> np.ndarray:
    """(K, 3) float32 points of a scan's finite ranges, level frame at the sensor's foot."""
    r = np.asarray(scan.ranges, dtype=np.float64)
    ok = np.isfinite(r)
    a = scan.angles[ok]
    return _xy_to_points3d(r[ok] * np.cos(a), r[ok] * np.sin(a), z)


def blueprint(context: SinkContext | None = None) -> Any:
    """The default layout: top down, depth and 3-D above; mount and timing plots below."""
    import rerun.blueprint as rrb

    reach = context.scan_params.range_max_m if context is not None else 5.0
    views = rrb.Horizontal(
        topdown.view(reach),
        rrb.Spatial2DView(
            name="Depth: red obstacle, magenta drop-off, green scan pixel", origin=DEPTH
        ),
        rrb.Spatial3DView(
            name="3D",
            origin="/world",
            line_grid=rrb.LineGrid3D(visible=False),  # /world/floor is the grid
            eye_controls=rrb.EyeControls3D(
                position=[-2.6, -1.0, 2.4], look_target=[2.0, 0.0, 0.0], eye_up=[0.0, 0.0, 1.0]
            ),
            # the depth image as a point cloud: one click on its eye in the blueprint panel
            overrides={DEPTH: rrb.EntityBehavior(visible=False)},
        ),
        column_shares=[2, 3, 3],
    )
    mount = context.mount if context is not None else None
    plots = rrb.Horizontal(
        *(_pose_view(rrb, key, unit, mount) for key, unit, _ in POSE_SERIES),
        rrb.Tabs(_timing_view(rrb), rrb.TextLogView(name="Log", origin="/log"), active_tab=0),
    )
    return rrb.Blueprint(
        rrb.Vertical(views, plots, row_shares=[3, 1]),
        rrb.BlueprintPanel(state="collapsed"),
        rrb.SelectionPanel(state="collapsed"),
        rrb.TimePanel(timeline="frame", state="collapsed"),
    )


def _pose_view(rrb: Any, key: str, unit: str, mount: Mount | None) -> Any:
    """One pose value: in use, floor estimates and configured, on a scale around the configured
    value (metres and degrees never share an axis)."""
    c = getattr(mount, f"{key}_{unit}", None) if mount is not None else None
    c = c if c is not None else POSE_DEFAULT[key]
    # wide enough for a mount far from its configured value, narrow enough to see a drift
    lo, hi = {
        "height": (0.0, max(1.0, 2.0 * c)),
        "tilt": (min(-5.0, c - 10.0), max(45.0, c + 10.0)),
        "roll": (min(-10.0, c - 10.0), max(10.0, c + 10.0)),
    }[key]
    return rrb.TimeSeriesView(
        name=f"{key.capitalize()} [{unit}]",
        origin=f"{STATS}/pose",
        contents=[
            f"+ $origin/{key}_{unit}",
            f"+ $origin/{key}_floor_{unit}",
            f"+ $origin/{key}_config_{unit}",
        ],
        axis_y=rrb.ScalarAxis(range=(lo, hi), zoom_lock=False),
        plot_legend=rrb.PlotLegend("RightTop"),
    )


def _timing_view(rrb: Any) -> Any:
    """Stage timings after the first frame, which builds the tables and compiles (100s of ms).

    A separate copy: a visible time range hides the first frame's points, but rerun 0.41 still
    scales the y axis to them, which flattens every later value to zero.
    """
    return rrb.TimeSeriesView(
        name="Timing [ms], after warm-up",
        origin=STEADY_TIMING,
        plot_legend=rrb.PlotLegend("RightTop"),
    )


def log_static(rr: Any, rec: Any, context: SinkContext, state: LayoutState) -> None:
    """The scene that never changes: frame conventions, floor grid, robot, colours and styles."""
    rec.log("/world", rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)
    lines = [[[x, -4.0, 0.0], [x, 4.0, 0.0]] for x in range(7)]
    lines += [[[0.0, y, 0.0], [6.0, y, 0.0]] for y in range(-4, 5)]
    rec.log(
        "/world/floor", rr.LineStrips3D(lines, radii=0.004, colors=[110, 110, 110]), static=True
    )
    length, width = state.footprint_m
    height = context.mount.height_m if context.mount is not None else 0.5
    rec.log(
        "/world/robot",
        rr.Boxes3D(
            mins=[[-length, -width / 2, 0.0]],
            sizes=[[length, width, height]],
            colors=[[180, 180, 180]],
            labels=["robot"],
        ),
        static=True,
    )
    rec.log(
        f"{DEPTH}/obstacles",
        # class 0 must be transparent explicitly, or rerun tints the whole depth image
        rr.AnnotationContext(
            [
                (0, "", (0, 0, 0, 0)),
                (CLASS_OBSTACLE, "obstacle (scan)", OBSTACLE_RGBA),
                (CLASS_CLIFF, "drop-off block", CLIFF_RGBA),
            ]
        ),
        static=True,
    )
    _log_series_styles(rr, rec)
    topdown.log_static(rr, rec, context.scan_params.range_max_m, state.footprint_m)
    rec.log(
        "/meta",
        rr.AnyValues(version=context.version, device=context.device.name, spec=context.device.spec),
        static=True,
    )


def _log_series_styles(rr: Any, rec: Any) -> None:
    for key, unit, color in POSE_SERIES:
        path = f"{STATS}/pose/{key}"
        rec.log(
            f"{path}_{unit}", rr.SeriesLines(colors=[color], names="in use", widths=2), static=True
        )
        rec.log(
            f"{path}_floor_{unit}",
            rr.SeriesPoints(
                colors=[color], names="floor estimate", markers="circle", marker_sizes=3
            ),
            static=True,
        )
        rec.log(
            f"{path}_config_{unit}",
            rr.SeriesLines(colors=[CONFIG_RGB], names="configured", widths=1),
            static=True,
        )
    for stage, color in STAGE_COLORS.items():
        if stage == "pose":  # runs every N frames: points, not a line between far-apart runs
            style = rr.SeriesPoints(colors=[color], names=stage, markers="diamond", marker_sizes=4)
        else:
            style = rr.SeriesLines(colors=[color], names=stage, widths=1.5)
        for folder in (f"{STATS}/timing", STEADY_TIMING):
            rec.log(f"{folder}/{stage}_ms", style, static=True)


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


def log_frame(
    rr: Any, rec: Any, frame: Frame, result: Result, state: LayoutState, image: bool
) -> None:
    """Everything of one frame (the timelines are set by the caller)."""
    m = result.mount
    # sensor body (FLU) -> base frame, geometry.py's order; the sensor sits where [mount] puts it
    # on the robot, as the base-frame scan and cliff points drawn beside it assume
    rot = rot_z(m.yaw_rad) @ rot_y(m.tilt_rad) @ rot_x(m.roll_rad)
    rec.log("/world/sensor", rr.Transform3D(translation=[m.x_m, m.y_m, m.height_m], mat3x3=rot))
    if image:
        if frame.intrinsics != state.intrinsics:
            log_intrinsics(rr, rec, frame.intrinsics)
            state.intrinsics = frame.intrinsics
        log_depth(rr, rec, frame, result, state)
    _log_world(rr, rec, result)
    layout = (result.scan.angle_min, result.scan.angle_max, result.scan.ranges.size)
    if layout != state.scan_layout:
        topdown.log_fov(rr, rec, result.scan, state.reach_m)
        state.scan_layout = layout
    topdown.log_frame(rr, rec, result)
    _log_stats(rr, rec, result, state.configured, warmup=state.frames == 0)
    if result.mount_trust != state.trust and result.mount_trust is not None:
        rec.log("/log", trust_text(rr, result))
        state.trust = result.mount_trust
    state.frames += 1


def trust_text(rr: Any, result: Result) -> Any:
    """A TextLog saying where the mount came from and whether drop-offs are trusted (WARN while
    they are not; amber drop-offs then)."""
    t = result.mount_trust
    assert t is not None
    head = f"frame {result.seq}: mount from {t.source}{' (pinned)' if t.pinned else ''}, "
    if t.dropoffs_trusted:
        return rr.TextLog(head + f"floor {t.floor}: drop-offs trusted", level="INFO")
    return rr.TextLog(head + f"{t.note} (drawn amber)", level="WARN")


def _log_world(rr: Any, rec: Any, result: Result) -> None:
    from depthnav_daemon.plots.overlays import cliff_cell_sizes_m, scan_strips

    rec.log("/world/scan", rr.Points3D(scan_points(result.scan), radii=0.02, colors=[SCAN_RGB]))
    strips = [_xy_to_points3d(s[:, 0], s[:, 1], SCAN_Z_M) for s in scan_strips(result.scan)]
    rec.log("/world/scan/line", rr.LineStrips3D(strips, radii=0.008, colors=[SCAN_RGB]))
    cliff = result.cliff
    if cliff is None:
        return
    pts = np.asarray(cliff.points_m, dtype=np.float32).reshape(-1, 2)
    rgb = topdown.cliff_rgb(result)
    rec.log(
        "/world/cliff/points",
        rr.Points3D(_xy_to_points3d(pts[:, 0], pts[:, 1], 0.0), radii=0.01, colors=[rgb]),
    )
    sides = cliff_cell_sizes_m(result)
    rec.log(
        "/world/cliff/cells",
        rr.Boxes3D(
            centers=_xy_to_points3d(pts[:, 0], pts[:, 1], 0.003),
            half_sizes=np.stack([sides / 2, sides / 2, np.full_like(sides, 0.003)], axis=1),
            colors=[rgb],
            fill_mode=rr.components.FillMode.Solid,
        ),
    )
    rec.log(
        "/world/cliff/scan",
        rr.Points3D(scan_points(cliff.scan, 0.02), radii=0.025, colors=[[255, 60, 60]]),
    )


def _log_stats(rr: Any, rec: Any, result: Result, configured: Mount | None, warmup: bool) -> None:
    m, pose = result.mount, result.pose
    for key, unit, _ in POSE_SERIES:
        path = f"{STATS}/pose/{key}"
        rec.log(f"{path}_{unit}", rr.Scalars(getattr(m, f"{key}_{unit}")))
        if pose is not None and pose.ok:
            rec.log(f"{path}_floor_{unit}", rr.Scalars(getattr(pose, f"{key}_{unit}")))
        if configured is not None:
            rec.log(f"{path}_config_{unit}", rr.Scalars(getattr(configured, f"{key}_{unit}")))
    for stage, seconds in result.timings_s.items():
        rec.log(f"{STATS}/timing/{stage}_ms", rr.Scalars(seconds * 1000.0))
        if not warmup:
            rec.log(f"{STEADY_TIMING}/{stage}_ms", rr.Scalars(seconds * 1000.0))
    if result.warning:
        rec.log("/log", rr.TextLog(f"frame {result.seq}: {result.warning}", level="WARN"))
    if pose is not None and not pose.ok:
        rec.log(
            "/log",
            rr.TextLog(f"frame {result.seq}: floor estimate rejected: {pose.reason}", level="INFO"),
        )
