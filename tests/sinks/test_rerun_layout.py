"""The rerun sink's default layout and pictures, read back from a real .rrd with rerun's reader:
the views exist, the 3-D view hides the raw depth cloud (one toggle away), the top-down view and
the depth overlays carry exactly the Result's scan and drop-offs, the timing plot leaves out the
warm-up frame, and the mount is plotted beside its configured value."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from depthnav_daemon.pipeline import StageParams, process
from depthnav_daemon.pipeline.geometry import Mount
from depthnav_daemon.pipeline.scan import ScanParams
from depthnav_daemon.plots.overlays import scan_source_pixels
from depthnav_daemon.sim.synthetic import render
from drivers.base import Frame
from tests.sinks.conftest import CLIFF, SCENE, make_pair
from tests.sinks.test_rerun import column, offline_rerun, record, temporal

rrchunk = pytest.importorskip("rerun.chunk")
__all__ = ["offline_rerun"]  # the autouse fixture: rerun's files stay out of the real home

CONFIGURED = Mount(0.45, 10.0, 0.0)


def blueprint_rows(path) -> dict[str, dict[str, list]]:
    """Blueprint entity path -> {component column: first row's value}."""
    reader = rrchunk.RrdReader(str(path))
    out: dict[str, dict[str, list]] = {}
    for chunk in reader.stream(store=reader.blueprints()[0]):
        rb = chunk.to_record_batch()
        cols = {n: rb.column(n).to_pylist()[0] for n in rb.schema.names if ":" in n}
        out.setdefault(chunk.entity_path, {}).update(cols)
    return out


def views(path) -> dict[str, tuple[str, str, str]]:
    """View name -> (kind, origin, blueprint path)."""
    out = {}
    for entity, cols in blueprint_rows(path).items():
        if "ViewBlueprint:display_name" in cols:
            out[cols["ViewBlueprint:display_name"][0]] = (
                cols["ViewBlueprint:class_identifier"][0],
                cols["ViewBlueprint:space_origin"][0],
                entity,
            )
    return out


def static_rows(path) -> dict[str, object]:
    """entity -> record batch of its static chunk."""
    return {
        c.entity_path: c.to_record_batch()
        for c in rrchunk.RrdReader(str(path)).stream()
        if c.is_static
    }


@pytest.fixture
def rrd(tmp_path, pairs, context):
    path = tmp_path / "run.rrd"
    record(path, pairs, replace(context, mount=CONFIGURED))
    return path


def test_3d_view_shows_results_without_the_raw_depth_cloud(rrd) -> None:
    kind, origin, view = views(rrd)["3D"]
    assert (kind, origin) == ("3D", "/world")
    bp = blueprint_rows(rrd)
    # the depth image is in the view's contents (so its cloud is one toggle away) ...
    assert bp[f"{view}/ViewContents"]["ViewContents:query"] == ["$origin/**"]
    # ... but hidden by default, with its overlays painted into the frustum
    hidden = bp[f"{view}/ViewContents/overrides/world/sensor/depth/visualizers"]
    assert hidden["EntityBehavior:visible"] == [False]
    assert bp[f"{view}/LineGrid3D"]["LineGrid3D:visible"] == [False]  # /world/floor is the grid
    eye = bp[f"{view}/EyeControls3D"]
    (x, _, z), (tx, _, tz) = eye["EyeControls3D:position"][0], eye["EyeControls3D:look_target"][0]
    assert x < -1.0 and z > 1.5 and tx > 1.0 and tz == 0.0  # behind and above, looking ahead
    # what the 3-D view shows instead: the scan as a line, drop-offs as filled cells, the robot
    ent = temporal(rrd)
    assert {"/world/scan/line", "/world/cliff/cells"} <= set(ent)
    assert column(ent["/world/cliff/cells"], "Boxes3D:fill_mode")[0] == [3]  # Solid
    assert {"/world/robot", "/world/sensor/fov"} <= set(static_rows(rrd))


def test_top_down_view_draws_the_scan_and_drop_offs(rrd, pairs) -> None:
    kind, origin, _ = views(rrd)["Top down [m]: scan, drop-offs, robot"]
    assert (kind, origin) == ("2D", "/topdown")
    ent = temporal(rrd)
    _, result = pairs[1]
    r = result.scan.ranges.astype(np.float64)
    ok = np.isfinite(r)
    a = result.scan.angles[ok]
    want = np.stack([-r[ok] * np.sin(a), -r[ok] * np.cos(a)], axis=1)  # (u, v) = (-y, -x)
    strips = column(ent["/topdown/scan"], "LineStrips2D:strips")[1]
    got = np.concatenate([np.asarray(s, dtype=np.float64) for s in strips])
    np.testing.assert_allclose(got, want, atol=1e-4)
    cliff = np.asarray(column(ent["/topdown/cliff"], "Boxes2D:centers")[1])
    pts = result.cliff.points_m
    np.testing.assert_allclose(cliff, np.stack([-pts[:, 1], -pts[:, 0]], axis=1), atol=1e-5)
    static = static_rows(rrd)
    robot = np.asarray(static["/topdown/robot"].column("LineStrips2D:strips").to_pylist()[0][0])
    assert robot[:, 1].max() == pytest.approx(0.45)  # the default 0.45 m robot, behind the sensor
    labels = static["/topdown/rings/labels"].column("Points2D:labels").to_pylist()[0]
    assert labels == ["1 m", "2 m", "3 m", "4 m", "5 m"]  # range_max_m = 5


def test_depth_overlays_fill_drop_off_blocks_and_mark_scan_pixels(rrd, pairs) -> None:
    ent = temporal(rrd)
    frame, result = pairs[1]
    seg = np.frombuffer(
        bytes(column(ent["/world/sensor/depth/obstacles"], "SegmentationImage:buffer")[1][0]),
        np.uint8,
    ).reshape(frame.depth_mm.shape)
    blocks = np.zeros(frame.depth_mm.shape, dtype=bool)
    bs = result.cliff.block_size
    for r, c in result.cliff.blocks:
        blocks[r : r + bs, c : c + bs] = True
    assert blocks.any() and np.array_equal(seg == 2, blocks & ~result.obstacle_mask)
    pix = np.asarray(column(ent["/world/sensor/depth/scan_pixels"], "Points2D:positions")[1])
    want = scan_source_pixels(frame.depth_mm, result)
    np.testing.assert_array_equal(pix[:, ::-1], want)  # (x, y) = (col, row)
    assert result.obstacle_mask[want[:, 0], want[:, 1]].all()
    # the exact scan reads every row: no box around the whole image
    assert column(ent["/world/sensor/depth/band"], "Boxes2D:half_sizes")[1] in ([], None)
    ctx = static_rows(rrd)["/world/sensor/depth/obstacles"]
    assert "drop-off block" in str(ctx.to_pylist())


def test_the_paper_methods_row_band_is_drawn(tmp_path, context) -> None:
    mount = Mount(0.5, 12.0, 1.5)
    intr = context.device.intrinsics
    frame = Frame(0, 0.0, render(SCENE, intr, mount).depth_mm, intr)
    params = StageParams(scan=ScanParams(method="paper", scan_height=100), cliff=CLIFF)
    result = process(frame, mount, params)
    path = tmp_path / "paper.rrd"
    record(path, [(frame, result)], context)
    ent = temporal(path)
    first, stop = result.scan_band
    assert stop - first == 100
    sizes = column(ent["/world/sensor/depth/band"], "Boxes2D:half_sizes")[0]
    assert np.allclose(sizes, [[intr.width / 2, 50.0]])


def test_timing_plot_leaves_out_the_warm_up_frame(rrd, pairs) -> None:
    ent = temporal(rrd)
    every = column(ent["/stats/timing/scan_ms"], "Scalars:scalars")
    steady = ent["/stats/timing_after_warmup/scan_ms"]
    assert len(every) == len(pairs)
    assert column(steady, "frame") == [r.seq for _, r in pairs[1:]]
    assert [v[0] for v in column(steady, "Scalars:scalars")] == pytest.approx(
        [r.timings_s["scan"] * 1000 for _, r in pairs[1:]]
    )


def test_mount_is_plotted_beside_the_configured_value(rrd, pairs) -> None:
    ent = temporal(rrd)
    config = [v[0] for v in column(ent["/stats/pose/height_config_m"], "Scalars:scalars")]
    assert config == pytest.approx([CONFIGURED.height_m] * len(pairs))
    floor = ent["/stats/pose/tilt_floor_deg"]  # only frame 2 ran the pose stage
    assert column(floor, "frame") == [2]
    assert column(floor, "Scalars:scalars")[0][0] == pytest.approx(pairs[2][1].pose.tilt_deg)
    bp = blueprint_rows(rrd)
    found = views(rrd)
    names = ("Height [m]", "Tilt [deg]", "Roll [deg]")
    assert all(found[n][:2] == ("TimeSeries", "/stats/pose") for n in names)
    height_axis = bp[f"{found['Height [m]'][2]}/ScalarAxis"]["ScalarAxis:range"][0]
    assert height_axis[0] == 0.0 and height_axis[1] >= 2 * CONFIGURED.height_m
    tilt_axis = bp[f"{found['Tilt [deg]'][2]}/ScalarAxis"]["ScalarAxis:range"][0]
    assert tilt_axis[0] < CONFIGURED.tilt_deg < tilt_axis[1]


def test_log_is_a_tab_not_an_empty_pane(rrd) -> None:
    bp = blueprint_rows(rrd)
    log_view = views(rrd)["Log"][2].lstrip("/")
    timing_view = views(rrd)["Timing [ms], after warm-up"][2].lstrip("/")
    tabs = [cols for cols in bp.values() if log_view in cols.get("ContainerBlueprint:contents", [])]
    assert len(tabs) == 1 and tabs[0]["ContainerBlueprint:active_tab"] == [timing_view]


def test_robot_footprint_option(tmp_path, context) -> None:
    frame, result = make_pair(0)
    path = tmp_path / "robot.rrd"
    record(path, [(frame, result)], context, "?robot_length_m=0.8&robot_width_m=0.6")
    robot = static_rows(path)["/world/robot"]
    assert np.allclose(robot.column("Boxes3D:half_sizes").to_pylist()[0][0][:2], [0.4, 0.3])


@pytest.mark.xfail(
    strict=True,
    reason="issue 31: with the cliff edge refinement the memory holds a drop-off cell about 1 m "
    "behind the robot on the drive_step fixture (a false drop-off, not yet explained)",
)
def test_top_down_draws_the_obstacle_memory_in_the_base_frame(tmp_path) -> None:
    """The drive fixture (odometry per frame): the remembered step edge 3 m ahead of the start
    is drawn where it is relative to the robot at the last frame, as filled muted cells."""
    import json
    import subprocess
    import sys
    from pathlib import Path

    root = Path(__file__).resolve().parents[2]
    path = tmp_path / "drive.rrd"
    device = f"replay:{root / 'fixtures' / 'drive_step'}?rate=max"
    proc = subprocess.run(
        [
            sys.executable,
            "-m",
            "depthnav_daemon",
            "run",
            "-q",
            "--device",
            device,
            "--sink",
            f"rerun:{path}",
            "--sink",
            "stdout",
        ],
        capture_output=True,
        text=True,
        cwd=root,
        timeout=300,
    )
    assert proc.returncode == 0, proc.stderr
    last = json.loads(proc.stdout.splitlines()[-1])["memory"]
    ent = temporal(path)
    cliffs = column(ent["/topdown/memory/cliffs"], "Boxes2D:centers")[-1]
    assert len(cliffs) == last["cells"]["cliff"] > 0
    # view (u, v) = (-y, -x): the step edge is ahead of the robot at 3 m - odometry x
    ahead_m = 3.0 - last["odom"]["x_m"]
    xs = sorted(-v for _, v in cliffs)
    assert xs[0] == pytest.approx(ahead_m, abs=0.1)
