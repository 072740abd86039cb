"""What the rerun sink shows: the entities it logs per frame and the default layout (blueprint).

The layout puts depthnav's results first: a top-down view (the paper's costmap figures: what a
costmap receives, with the obstacle memory; with odometry a second one in the odometry frame, the
robot moving through its memory, shown first), the depth image in the figures' palette under
strong colours, a 3-D view from behind and above the robot without rerun's point cloud of the
whole depth image (hidden, one toggle away in the blueprint panel), and plots of the mount against
its configured value and of the stage timings after each stage's first run.

The layout follows what the frames show: it is sent again (a new blueprint, made active) when
odometry first comes, when the mount's trust changes (the top-down view's title says it; the Log
tab comes to the front while it is not trusted) and when a mount or floor estimate leaves the pose
plots' range. The drawings are in ``depth``, ``topdown`` and ``world``; the entity paths are
listed in ``sinks/rerun/rerun.py``; every rerun call of depthnav lives in these modules (the API
moves between releases).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np

from depthnav_daemon.pipeline.geometry import Mount, rot_x, rot_y, rot_z
from depthnav_daemon.plots import rgb
from depthnav_daemon.plots.overlays import (
    SOURCE_NAMES,
    dropoff_areas,
    footprint_xy,
    to_odom,
    untrusted,
)
from depthnav_daemon.sinks.rerun import topdown, world
from depthnav_daemon.sinks.rerun.depth import CLASSES, log_depth

if TYPE_CHECKING:
    from depthnav_daemon.pipeline import MountTrust, Result
    from depthnav_daemon.sinks.base import SinkContext
    from drivers.base import Frame, Intrinsics

DEPTH = "/world/sensor/depth"
STATS = "/stats"
STEADY_TIMING = f"{STATS}/timing_after_warmup"
SCAN_RGB = topdown.SCAN_RGB
CLIFF_RGB = topdown.CLIFF_RGB
CONFIG_RGB = (150, 150, 150)
FLOOR_RGB = rgb("floor")  # floor estimates: one contrasting colour and marker on every plot
# pose series: (key, unit, colour of the mount in use); the floor estimate and the configured
# value share the view, as crosses and a grey line
POSE_SERIES = (
    ("height", "m", (255, 128, 0)),
    ("tilt", "deg", (0, 160, 255)),
    ("roll", "deg", (160, 80, 255)),
)
POSE_UNKNOWN = {"height": (0.0, 1.0), "tilt": (-10.0, 45.0), "roll": (-10.0, 10.0)}  # no mount
POSE_SPAN = {"height": 0.25, "tilt": 8.0, "roll": 8.0}  # a pose plot's half range at least
POSE_STEP = {"height": 0.25, "tilt": 5.0, "roll": 5.0}  # ranges are rounded out to these
STAGE_COLORS = {
    "scan": (0, 200, 80),
    "cliff": (230, 0, 230),
    "pose": (255, 170, 0),
    "memory": (31, 168, 168),
}
DEPTH_VIEW = "Depth: red obstacle, magenta drop-off, blue-grey no reading"
UNTRUSTED_VIEW = "Top down [m]: mount NOT trusted, drop-offs and scan amber"
UNTRUSTED_ODOM_VIEW = "Odometry frame [m]: mount NOT trusted, drop-offs and scan amber"
PATH_MIN_STEP_M = 0.02  # the odometry path keeps a point every 2 cm


@dataclass
class LayoutState:
    """The sink's drawing settings, what was last logged as static (logged again only when it
    changes) and what the layout depends on (sent again when it changes).

    Attributes:
        footprint_m: the robot's length and width drawn behind the sensor, metres.
        outline: (K, 2) the robot drawn in the top-down views: the [robot] outline when
            configured, else the footprint_m box.
        reach_m: the scan's range_max (the top-down view's extent, the depth palette's far end).
        block_size: the configured cliff block side, pixels (when a result carries none).
        configured: the configured mount, plotted beside the mount in use; None if unknown.
        context: what the sink was opened with (for the layout sent again).
        frames: frames logged so far.
        intrinsics, scan_layout: what the pinhole and the field of view were last logged for.
        trust: the mount trust last logged to /log (logged again when it changes).
        stages: stages whose first run (tables, compilation) was logged: later runs go to the
            steady timing plot.
        config_source: the configured mount's series name last logged.
        half_fov_rad: half the scan's field of view (the top-down view's width).
        odom_start: the first odometry pose (x, y, yaw) of the memory, or None before.
        path: the odometry path, (x, y) points in the odometry frame.
        untrusted: whether the layout was last sent for an untrusted mount.
        pose_ranges: each pose plot's (lo, hi) in the layout last sent.
        layouts: blueprints sent so far (the first at open).
    """

    footprint_m: tuple[float, float] = topdown.DEFAULT_FOOTPRINT_M
    outline: np.ndarray = field(default_factory=lambda: footprint_xy(*topdown.DEFAULT_FOOTPRINT_M))
    reach_m: float = 5.0
    block_size: int = 16
    configured: Mount | None = None
    context: SinkContext | None = None
    frames: int = 0
    intrinsics: Intrinsics | None = None
    scan_layout: tuple[float, float, int] | None = None
    trust: MountTrust | None = None
    stages: set[str] = field(default_factory=set)
    config_source: str | None = None
    half_fov_rad: float = 0.6
    odom_start: tuple[float, float, float] | None = None
    path: list[tuple[float, float]] = field(default_factory=list)
    untrusted: bool = False
    pose_ranges: dict[str, tuple[float, float]] = field(default_factory=dict)
    layouts: int = 0


def pose_ranges(state: LayoutState, values: dict[str, list[float]]) -> dict[str, tuple]:
    """Each pose plot's range: around the configured value and every value given (the mount in
    use, floor estimates), at least POSE_SPAN either side, rounded out to POSE_STEP so it changes
    seldom. With no configured mount, wide enough for any usual mount (POSE_UNKNOWN)."""
    out = {}
    for key, unit, _ in POSE_SERIES:
        m = state.configured
        seen = list(values.get(key, []))
        if m is not None:
            seen.append(getattr(m, f"{key}_{unit}"))
        span, step = POSE_SPAN[key], POSE_STEP[key]
        lo, hi = POSE_UNKNOWN[key] if not seen else (min(seen) - span, max(seen) + span)
        lo, hi = math.floor(lo / step) * step, math.ceil(hi / step) * step
        if key == "height":
            lo = max(0.0, lo)
        out[key] = (lo, hi)
    return out


def blueprint(context: SinkContext | None = None, state: LayoutState | None = None) -> Any:
    """The layout: top down (a third of the width), depth and 3-D above; mount and timing plots
    below. ``state`` (what the frames showed so far) adds the odometry-frame view, the trust in
    the top-down title and wider pose ranges."""
    import rerun.blueprint as rrb

    state = state or LayoutState(configured=context.mount if context is not None else None)
    reach = context.scan_params.range_max_m if context is not None else state.reach_m
    base = topdown.view(reach, state.half_fov_rad, UNTRUSTED_VIEW if state.untrusted else "")
    top: Any = base
    if state.odom_start is not None:
        odom = topdown.odom_view(
            state.odom_start, reach, UNTRUSTED_ODOM_VIEW if state.untrusted else ""
        )
        top = rrb.Tabs(odom, base, active_tab=0)
    views = rrb.Horizontal(
        top,
        rrb.Spatial2DView(name=DEPTH_VIEW, origin=DEPTH),
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
        column_shares=[4, 3, 3],
    )
    ranges = state.pose_ranges or pose_ranges(state, {})
    plots = rrb.Horizontal(
        *(_pose_view(rrb, key, unit, ranges[key]) for key, unit, _ in POSE_SERIES),
        rrb.Tabs(
            _timing_view(rrb),
            rrb.TextLogView(name="Log", origin="/log"),
            active_tab=1 if state.untrusted else 0,
        ),
    )
    return rrb.Blueprint(
        rrb.Vertical(views, plots, row_shares=[3, 1]),
        rrb.BlueprintPanel(state="collapsed"),
        rrb.SelectionPanel(state="collapsed"),
        rrb.TimePanel(timeline="frame", state="collapsed"),
    )


def _pose_view(rrb: Any, key: str, unit: str, lo_hi: tuple[float, float]) -> Any:
    """One pose value: in use, floor estimates and configured, on a range around their values
    (metres and degrees never share an axis)."""
    return rrb.TimeSeriesView(
        name=f"{key.capitalize()} [{unit}]",
        origin=f"{STATS}/pose",
        contents=[
            f"+ $origin/{key}_{unit}",
            f"+ $origin/{key}_floor_{unit}",
            f"+ $origin/{key}_config_{unit}",
        ],
        axis_y=rrb.ScalarAxis(range=lo_hi, zoom_lock=False),
        plot_legend=rrb.PlotLegend("RightTop"),
    )


def _timing_view(rrb: Any) -> Any:
    """Stage timings after each stage's first run, which builds the tables and compiles (100s of
    ms; the memory's comes with the first odometry).

    A separate copy: a visible time range hides the first run's points, but rerun 0.41 still
    scales the y axis to them, which flattens every later value to zero.
    """
    return rrb.TimeSeriesView(
        name="Timing [ms], after warm-up",
        origin=STEADY_TIMING,
        plot_legend=rrb.PlotLegend("RightTop"),
    )


def update_layout(rr: Any, rec: Any, result: Result, state: LayoutState) -> bool:
    """Send the layout again when what it depends on changed with this frame: odometry came, the
    trust changed, or a mount value left its plot's range. Whether it was sent."""
    changed = False
    mem = result.memory
    if state.odom_start is None and mem is not None and mem.pose is not None:
        state.odom_start = mem.pose
        reach = min(state.reach_m, topdown.MAX_REACH_M)
        # its legend: left of where the robot looks at first, beside its start
        corner = topdown.uv(to_odom(np.array([[-0.3, 0.3 * reach + 0.3]]), mem.pose))[0]
        height = min(3.0, 0.6 * reach)
        topdown.log_legend(
            rr, rec, f"{topdown.ODOM}/legend", (corner[0], corner[1] - height), height
        )
        changed = True
    bad = untrusted(result)
    if bad != state.untrusted:
        state.untrusted = bad
        changed = True
    values: dict[str, list[float]] = {}
    m, pose = result.mount, result.pose
    for key, unit, _ in POSE_SERIES:
        values[key] = [getattr(m, f"{key}_{unit}")]
        if pose is not None and pose.ok:
            values[key].append(getattr(pose, f"{key}_{unit}"))
    ranges = pose_ranges(state, values)
    if not state.pose_ranges:
        state.pose_ranges = pose_ranges(state, {})
    if any(
        ranges[k][0] < state.pose_ranges[k][0] or ranges[k][1] > state.pose_ranges[k][1]
        for k in ranges
    ):
        state.pose_ranges = {
            k: (
                min(ranges[k][0], state.pose_ranges[k][0]),
                max(ranges[k][1], state.pose_ranges[k][1]),
            )
            for k in ranges
        }
        changed = True
    if changed:
        rec.send_blueprint(blueprint(state.context, state), make_active=True, make_default=True)
        state.layouts += 1
    return changed


def closed_outline(body_m: tuple[tuple[float, float], ...]) -> np.ndarray:
    """(K + 1, 2) the [robot] outline, closed (its first vertex again at the end)."""
    xy = np.asarray(body_m, dtype=float)
    return np.vstack([xy, xy[:1]])


def _prism(rr: Any, outline: np.ndarray, mount: Mount | None, height_m: float) -> Any:
    """The robot's body as the edges of its outline's prism, from the floor to its top
    (the [robot] height is not on the context: the sensor's height stands in for it)."""
    top = height_m if mount is None else min(height_m, mount.height_m)
    floor = [[x, y, 0.0] for x, y in outline]
    roof = [[x, y, top] for x, y in outline]
    posts = [[[x, y, 0.0], [x, y, top]] for x, y in outline[:-1]]
    return rr.LineStrips3D([floor, roof, *posts], radii=0.006, colors=[[180, 180, 180]])


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
    if context.body_m:  # the configured [robot] outline (its readings ignored), as a prism
        state.outline = closed_outline(context.body_m)
        rec.log("/world/robot", _prism(rr, state.outline, context.mount, height), static=True)
    else:  # a box of the drawing's size behind the sensor
        state.outline = footprint_xy(length, width)
        rec.log(
            "/world/robot",
            rr.Boxes3D(
                mins=[[-length, -width / 2, 0.0]],
                sizes=[[length, width, height]],
                colors=[[180, 180, 180]],
            ),
            static=True,
        )
    rec.log(f"{DEPTH}/obstacles", rr.AnnotationContext(list(CLASSES)), static=True)
    _log_series_styles(rr, rec)
    topdown.log_static(rr, rec, context.scan_params.range_max_m, state.outline)
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
                colors=[FLOOR_RGB], names="floor estimate", markers="cross", marker_sizes=5
            ),
            static=True,
        )
    for stage, color in STAGE_COLORS.items():
        if stage == "pose":  # runs every N frames: points, not a line between far-apart runs
            style = rr.SeriesPoints(colors=[color], names=stage, markers="diamond", marker_sizes=4)
        else:
            style = rr.SeriesLines(colors=[color], names=stage, widths=1.5)
        for folder in (f"{STATS}/timing", STEADY_TIMING):
            rec.log(f"{folder}/{stage}_ms", style, static=True)


def _log_config_style(rr: Any, rec: Any, key: str, unit: str, name: str) -> None:
    rec.log(
        f"{STATS}/pose/{key}_config_{unit}",
        rr.SeriesLines(colors=[CONFIG_RGB], names=name, widths=1),
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
    layout = (result.scan.angle_min, result.scan.angle_max, result.scan.ranges.size)
    if layout != state.scan_layout:
        state.half_fov_rad = max(abs(result.scan.angle_min), abs(result.scan.angle_max))
        topdown.log_fov(rr, rec, result.scan, state.reach_m)
        state.scan_layout = layout
    update_layout(rr, rec, result, state)
    areas = dropoff_areas(frame.depth_mm, result, min(state.reach_m, topdown.MAX_REACH_M))
    if image:
        if frame.intrinsics != state.intrinsics:
            world.log_intrinsics(rr, rec, frame.intrinsics)
            state.intrinsics = frame.intrinsics
        log_depth(rr, rec, frame, result, state, areas)
    world.log_world(rr, rec, result, areas)
    topdown.log_frame(rr, rec, result, areas)
    mem = result.memory
    if mem is not None and mem.pose is not None:
        x, y, _ = mem.pose
        if not state.path or math.dist(state.path[-1], (x, y)) >= PATH_MIN_STEP_M:
            state.path.append((x, y))
            del state.path[: max(0, len(state.path) - topdown.PATH_POINTS)]
        topdown.log_odom_frame(rr, rec, result, areas, state.path, state.outline)
    _log_stats(rr, rec, result, state)
    if result.mount_trust != state.trust and result.mount_trust is not None:
        rec.log("/log", trust_text(rr, result))
        state.trust = result.mount_trust
    state.frames += 1


def trust_text(rr: Any, result: Result) -> Any:
    """A TextLog saying where the mount came from and whether drop-offs are trusted (WARN while
    they are not; amber drop-offs and scan then)."""
    t = result.mount_trust
    assert t is not None
    source = SOURCE_NAMES.get(t.source, t.source) if t.source == "default" else t.source
    head = f"frame {result.seq}: mount from {source}{' (pinned)' if t.pinned else ''}, "
    if t.dropoffs_trusted:
        return rr.TextLog(head + f"floor {t.floor}: drop-offs trusted", level="INFO")
    return rr.TextLog(head + f"{t.note} (drawn amber)", level="WARN")


def _level(m: Mount) -> tuple[float, float, float]:
    return m.height_m, m.tilt_deg, m.roll_deg


def _log_stats(rr: Any, rec: Any, result: Result, state: LayoutState) -> None:
    m, pose, configured = result.mount, result.pose, state.configured
    trust = result.mount_trust
    if state.config_source is None:
        # the built-in default is no configuration: the plots' legends say so (the tracker's
        # rule: an unpinned mount at the built-in height, tilt and roll; from the first frame)
        name = "configured"
        default = configured is None or _level(configured) == _level(Mount())
        if trust is not None and default and not trust.pinned:
            name = SOURCE_NAMES["default"]
        for key, unit, _ in POSE_SERIES:
            _log_config_style(rr, rec, key, unit, name)
        state.config_source = name
    for key, unit, _ in POSE_SERIES:
        path = f"{STATS}/pose/{key}"
        rec.log(f"{path}_{unit}", rr.Scalars(getattr(m, f"{key}_{unit}")))
        floor = getattr(pose, f"{key}_{unit}") if pose is not None and pose.ok else None
        if floor is None and trust is not None:  # a contradicting estimate, on every frame
            floor = getattr(trust, f"floor_{key}_{unit}", None)
        if floor is not None:
            rec.log(f"{path}_floor_{unit}", rr.Scalars(floor))
        if configured is not None:
            rec.log(f"{path}_config_{unit}", rr.Scalars(getattr(configured, f"{key}_{unit}")))
    for stage, seconds in result.timings_s.items():
        rec.log(f"{STATS}/timing/{stage}_ms", rr.Scalars(seconds * 1000.0))
        if stage in state.stages:  # each stage's first run builds tables and compiles
            rec.log(f"{STEADY_TIMING}/{stage}_ms", rr.Scalars(seconds * 1000.0))
        state.stages.add(stage)
    if result.warning:
        rec.log("/log", rr.TextLog(f"frame {result.seq}: {result.warning}", level="WARN"))
    if pose is not None and not pose.ok:
        rec.log(
            "/log",
            rr.TextLog(f"frame {result.seq}: floor estimate rejected: {pose.reason}", level="INFO"),
        )
