"""Figures: the numbers drawn are the numbers printed (one function computes both), every bad
output path is one line with a hint, and the pictures are valid files of the expected size."""

from __future__ import annotations

import math
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from depthnav_daemon.commands.mount import format_plan, mount_plan
from depthnav_daemon.errors import ConfigError, DepthnavError
from depthnav_daemon.pipeline.mount_planner import lower_dead_zone_m, max_visible_height_m
from depthnav_daemon.plots import check_output, save
from depthnav_daemon.plots.experiment import detection_grid, draw_experiment
from depthnav_daemon.plots.mount_side import draw_side_view
from depthnav_daemon.plots.overlays import scan_source_pixels, scan_strips
from depthnav_daemon.plots.sweep import HEIGHTS_M, draw_sweep, tilts_deg
from depthnav_daemon.sim.paper_experiment import Row
from tests.sinks.conftest import make_pair

pytest.importorskip("matplotlib")
from PIL import Image  # after the skip: the figures need the plot extra

ROOT = Path(__file__).resolve().parents[1]
FIXTURE = ROOT / "fixtures" / "corridor_step"


def depthnav(*args: str, timeout: float = 120) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "depthnav_daemon", *args],
        capture_output=True,
        text=True,
        timeout=timeout,
        cwd=ROOT,
    )


def lines_by_gid(fig) -> dict[str, object]:
    return {ln.get_gid(): ln for ax in fig.axes for ln in ax.get_lines() if ln.get_gid()}


def png_size(path: Path) -> tuple[int, int]:
    with Image.open(path) as img:
        assert img.format == "PNG"
        img.verify()
        return img.size


def test_printed_and_plotted_mount_numbers_come_from_one_plan() -> None:
    plan = mount_plan(0.5, 15.0, "kinect", None, "0.5,1,2,3,4,5", robot_height_m=1.1)
    text = format_plan(plan)
    # the table: eq. 16 at each distance, eq. 15's dead zone, where the robot's height is reached
    for d, top in zip(plan.distances_m, plan.highest_m, strict=True):
        assert top == pytest.approx(float(max_visible_height_m(0.5, 15.0, 43.0, d)))
        assert f"{d:>10.2f}  {top:>24.2f}" in text
    assert plan.dead_zone_m == pytest.approx(0.5 * math.tan(math.radians(90 - 21.5 - 15)))
    assert f"{plan.dead_zone_m:.2f} m" in text
    reach = plan.robot_top_seen_m[0]
    assert float(max_visible_height_m(0.5, 15.0, 43.0, reach)) == pytest.approx(1.1)
    assert f"from {reach:.2f} m on" in text
    # the figure: the same plan's points, and eq. 15/16 curves drawn from the planner
    lines = lines_by_gid(draw_side_view(plan))
    np.testing.assert_allclose(lines["eq16_table"].get_xdata(), plan.distances_m)
    np.testing.assert_allclose(lines["eq16_table"].get_ydata(), plan.highest_m)
    x, y = lines["eq16"].get_data()
    np.testing.assert_allclose(y, max_visible_height_m(0.5, 15.0, 43.0, x))
    x, y = lines["eq15"].get_data()
    np.testing.assert_allclose(x, lower_dead_zone_m(0.5, 15.0, 43.0, y))
    assert x.max() == pytest.approx(plan.dead_zone_m)  # the lower edge reaches the floor there
    assert lines["robot_top"].get_xdata()[0] == pytest.approx(reach)


@pytest.mark.parametrize(
    ("height", "tilt", "robot", "words"),
    [
        (0.5, 15.0, 1.1, "from"),  # view rising: tall obstacles seen from some distance on
        (1.2, 50.0, 1.0, "up to"),  # view falling, sensor above the robot: seen only near
        (0.3, 40.0, 1.0, "at no distance"),  # view falling below the robot's height
    ],
)
def test_robot_height_cases(height: float, tilt: float, robot: float, words: str) -> None:
    plan = mount_plan(height, tilt, "kinect", None, "1,2", robot_height_m=robot)
    assert words in format_plan(plan)
    draw_side_view(plan)  # every case draws


def test_sweep_curves_are_eq15_and_eq16() -> None:
    plan = mount_plan(0.55, 15.0, "xtion", None, "1", robot_height_m=0.9)
    lines = lines_by_gid(draw_sweep(plan, "xtion"))
    tilts = tilts_deg(45.0)
    for h in (*HEIGHTS_M, 0.55):
        x, y = lines[f"dead_zone_{h:g}"].get_data()
        np.testing.assert_allclose(x, tilts)
        want = [float(lower_dead_zone_m(h, t, 45.0)) for t in tilts]
        np.testing.assert_allclose(y, want)
    x, y = lines["highest_2"].get_data()
    np.testing.assert_allclose(y, [float(max_visible_height_m(0.55, t, 45.0, 2.0)) for t in x])


def test_png_and_svg_by_extension(tmp_path: Path) -> None:
    plan = mount_plan(0.5, 15.0, "kinect", None, "1,2,3")
    fig = draw_side_view(plan)
    w, h = png_size(save(fig, tmp_path / "side.PNG"))
    assert w == 800 and 250 < h < 700
    svg = save(fig, tmp_path / "side.svg").read_text()
    assert svg.lstrip().startswith("<?xml") and "<svg" in svg


def test_mount_cli_writes_both_figures(tmp_path: Path) -> None:
    p = depthnav(
        "mount", "--height-m", "0.5", "--tilt-deg", "15", "--robot-height-m", "1.1",
        "--plot", str(tmp_path / "side.png"), "--sweep", str(tmp_path / "sweep.svg"),
    )  # fmt: skip
    assert p.returncode == 0, p.stderr
    assert "from 5.27 m on" in p.stdout
    assert png_size(tmp_path / "side.png")[0] == 800
    assert "<svg" in (tmp_path / "sweep.svg").read_text()


def bad_outputs(tmp_path: Path) -> list[tuple[str, int, str]]:
    (tmp_path / "dir.png").mkdir()
    (tmp_path / "full.png").symlink_to("/dev/full")
    return [
        (str(tmp_path / "side.jpg"), 2, "accepted: .png, .svg"),
        (str(tmp_path / "side"), 2, "accepted: .png, .svg"),
        ("/dev/full", 2, "not a regular file"),
        (str(tmp_path / "missing" / "side.png"), 2, "does not exist"),
        (str(tmp_path / "dir.png"), 2, "is a directory"),
        ("/proc/depthnav-side.png", 1, "cannot write"),  # no new files there, even for root
        (str(tmp_path / "full.png"), 2, "not a regular file"),  # a link to /dev/full
    ]


@pytest.mark.parametrize("option", ["--plot", "--sweep"])
def test_bad_figure_paths_are_one_line_with_a_hint(tmp_path: Path, option: str) -> None:
    for path, code, needle in bad_outputs(tmp_path):
        p = depthnav("mount", "--height-m", "0.5", "--tilt-deg", "15", option, path)
        assert p.returncode == code, (path, p.stderr)
        errors = [line for line in p.stderr.splitlines() if "error:" in line]
        assert len(errors) == 1 and needle in errors[0], (path, p.stderr)
        assert "depthnav: hint: " in p.stderr and "internal error" not in p.stderr, p.stderr
        assert "Traceback" not in p.stderr
    assert not (tmp_path / "missing").exists()


def test_check_output_fails_before_any_work(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match=r"accepted: \.png, \.svg"):
        check_output(tmp_path / "x.pdf", "--plot")
    assert check_output(tmp_path / "x.svg", "--plot")[1] == "svg"
    with pytest.raises(DepthnavError, match="No space left"):
        (tmp_path / "full.png").symlink_to("/dev/full")
        save(draw_side_view(mount_plan(0.5, 15.0, "kinect", None, "1")), tmp_path / "full.png")


def test_experiment_figure_shows_every_row() -> None:
    poses, margins, boxes = ((0.45, 15.0), (0.8, 40.0)), (0.0, 0.05), (0.40, 0.15, 0.03, 0.01)
    rows = [
        Row(m, h, t, e, tuple(b > e for b in boxes), int(e == 0) * 300 + (m == "paper") * 7)
        for m in ("paper", "exact")
        for h, t in poses
        for e in margins
    ]
    found, false_bins = detection_grid(rows, "exact", poses, margins)
    assert found.shape == (4, 4) and found[1].tolist() == [True, True, False, False]
    assert false_bins.tolist() == [300, 0, 300, 0]
    fig = draw_experiment(rows, poses, margins, boxes)
    titles = [ax.get_title() for ax in fig.axes]
    assert any("paper" in t for t in titles) and any("exact" in t for t in titles)
    shown = [t.get_text() for t in fig.axes[0].texts]
    assert shown.count("307") == 2 and shown.count("7") == 2  # paper's false bins, per row


def test_paper_experiment_plot_option_checks_the_name_first(tmp_path: Path) -> None:
    p = subprocess.run(
        [sys.executable, "-m", "depthnav_daemon.sim.paper_experiment", "--plot", "x.pdf"],
        capture_output=True,
        text=True,
        cwd=tmp_path,
        timeout=60,
    )
    assert p.returncode == 2 and "accepted: .png, .svg" in p.stderr and p.stdout == ""
    assert "Traceback" not in p.stderr


def test_scan_strips_and_source_pixels_follow_the_result() -> None:
    frame, result = make_pair(0)
    strips = scan_strips(result.scan)
    finite = np.isfinite(result.scan.ranges)
    assert sum(len(s) for s in strips) == finite.sum() > 0
    src = scan_source_pixels(frame.depth_mm, result)
    assert len(src) > 0.5 * finite.sum()  # most readings come from a pixel drawn for them
    assert result.obstacle_mask[src[:, 0], src[:, 1]].all()
    assert len({tuple(p) for p in src.tolist()}) == len(src)


def test_snapshot_of_the_fixture(tmp_path: Path) -> None:
    out = tmp_path / "snap.png"
    p = depthnav("snapshot", "--device", f"replay:{FIXTURE}", "--frame", "2", str(out))
    assert p.returncode == 0, p.stderr
    assert "frame 2 of" in p.stdout
    w, h = png_size(out)
    assert w == 800 and h == 460


def grab_fixture(name: str, index: int, sets: tuple[str, ...] = ()):
    import threading

    from depthnav_daemon.commands.snapshot import grab
    from depthnav_daemon.config.loader import build_config

    cfg = build_config([], list(sets), {"device": f"replay:{ROOT / 'fixtures' / name}?rate=max"})
    return cfg, *grab(cfg, index, threading.Event())


def texts_of(fig) -> list[str]:
    legend = [t.get_text() for lg in fig.legends for t in lg.get_texts()]
    return [fig.get_suptitle(), *legend]


def test_snapshot_runs_the_daemons_loop_and_draws_the_memory() -> None:
    """Frame 7 of the drive: the frames before it went through the loop with their odometry, so
    the memory holds the box the robot has passed; the snapshot draws its cells and its 360 deg
    scan with a legend, the cliff scan as a line and the step's lower floor as an area."""
    from matplotlib.colors import to_hex

    from depthnav_daemon.plots import COLORS
    from depthnav_daemon.plots.snapshot import draw_snapshot

    cfg, frame, result = grab_fixture("drive_step", 7)
    mem = result.memory
    assert result.seq == 7 and mem is not None and mem.status == "on"
    assert mem.obstacle_cells > 0 and mem.cliff_cells > 0  # the box beside, the step ahead
    fig = draw_snapshot(frame, result, cfg.scan.range_max_m, "drive", scan_params=cfg.scan)
    texts = texts_of(fig)
    for label in ("remembered obstacle", "remembered drop-off", "memory scan (360°)"):
        assert label in texts
    assert "cliff scan (drop-off edge)" in texts and "trusted" in texts[0]
    top = fig.axes[1]
    colors = {to_hex(ln.get_color()) for ln in top.get_lines()}
    assert {COLORS["memory_scan"], COLORS["cliff"]} <= colors
    faces = [to_hex(p.get_facecolor()) for p in top.patches]
    assert COLORS["memory_obstacle"] in faces and COLORS["cliff"] in faces


def test_dropoff_area_starts_at_the_edge() -> None:
    """The corridor's step (truth 2.0 m ahead): one area whose near side is the edge (within
    5 cm, never beyond it) and whose far side is the lower floor seen beyond."""
    from depthnav_daemon.plots.overlays import dropoff_areas

    cfg, frame, result = grab_fixture("corridor_step", 3)
    areas = dropoff_areas(frame.depth_mm, result, cfg.scan.range_max_m)
    step = [(n, f) for n, f in areas.areas if np.median(n[:, 0]) > 1.5]
    assert len(step) == 1
    near, far = step[0]
    # the floor point under the first lower-floor pixel: a pixel's footprint (1.2 cm) before
    # the edge; two where the floor pixel under it has no reading
    assert np.median(near[:, 0]) == pytest.approx(2.0, abs=0.02)
    # (a floor pixel whose reading lies within the margin of the lower floor: millimetres past)
    assert np.percentile(near[:, 0], 95) <= 2.005 and near[:, 0].max() <= 2.0 + 0.02
    beyond = np.hypot(*far.T) - np.hypot(*near.T)
    assert np.all(beyond > 0.1) and np.median(beyond) > 1.0  # less beside the walls
    assert np.all(np.hypot(*far.T) <= cfg.scan.range_max_m + 1e-6)


def test_snapshot_untrusted_too_close_and_no_reading() -> None:
    """A wrong pinned mount: the title says the results are not trusted, in amber, and the
    scan is amber; "too close" bearings are marked; no reading is blue-grey, never a depth
    colour (the palette runs light near to dark far)."""
    import dataclasses

    import matplotlib as mpl
    from matplotlib.colors import to_hex

    from depthnav_daemon.plots import COLORS, DEPTH_CMAP
    from depthnav_daemon.plots.snapshot import draw_snapshot

    sets = ("mount.height_m=0.75", "mount.tilt_deg=12", "daemon.tilt_source=config")
    cfg, frame, result = grab_fixture("corridor_step", 3, sets)
    assert not result.mount_trust.dropoffs_trusted
    ranges = result.scan.ranges.copy()
    ranges[:5] = -np.inf
    close = dataclasses.replace(result, scan=dataclasses.replace(result.scan, ranges=ranges))
    fig = draw_snapshot(frame, close, cfg.scan.range_max_m, scan_params=cfg.scan)
    title = fig.get_suptitle()
    assert "NOT trusted" in title and "contradicted by the floor (0.55 m" in title
    assert to_hex(fig._suptitle.get_color()) == COLORS["untrusted"]
    top = fig.axes[1]
    lines = top.get_lines()
    assert any(
        to_hex(ln.get_color()) == COLORS["untrusted"] and len(ln.get_xdata()) > 5 for ln in lines
    )
    marks = [ln for ln in lines if ln.get_marker() == "x"]
    assert len(marks) == 1 and len(marks[0].get_xdata()) == 5
    assert "too close (-inf)" in texts_of(fig)
    image = fig.axes[0].get_images()[0]
    cmap = image.get_cmap()
    assert to_hex(cmap.get_bad()) == COLORS["no_reading"]
    near, far = to_hex(cmap(0.0)), to_hex(cmap(1.0))
    assert near == to_hex(mpl.colormaps[DEPTH_CMAP](1.0)) and far == to_hex(
        mpl.colormaps[DEPTH_CMAP](0.0)
    )
    assert COLORS["no_reading"] not in {near, far}
    assert np.ma.is_masked(
        image.get_array()[frame.depth_mm == 0].max() if False else image.get_array()
    )


@pytest.mark.parametrize(
    ("args", "code", "needle"),
    [
        (["--frame", "40", "OUT.png"], 1, "give --frame between 0 and 11"),
        (["--frame", "-1", "OUT.png"], 2, "--frame=-1"),
        (["OUT.gif"], 2, "accepted: .png, .svg"),
        (["--footprint-m", "0.4", "OUT.png"], 2, "LENGTH,WIDTH"),
        (["--set", "scan.range_max_m=-1", "OUT.png"], 2, "range_max_m"),
    ],
)
def test_snapshot_bad_input(tmp_path: Path, args: list[str], code: int, needle: str) -> None:
    args = [a.replace("OUT", str(tmp_path / "snap")) for a in args]
    p = depthnav("snapshot", "--device", f"replay:{FIXTURE}", *args)
    assert p.returncode == code, p.stderr
    errors = [line for line in p.stderr.splitlines() if "error:" in line]
    assert len(errors) == 1 and needle in p.stderr, p.stderr
    assert "Traceback" not in p.stderr and not any(tmp_path.iterdir())


def test_snapshot_of_a_missing_device(tmp_path: Path) -> None:
    p = depthnav("snapshot", "--device", "replay:/nonexistent/rec", str(tmp_path / "s.png"))
    assert p.returncode == 1 and "/nonexistent/rec" in p.stderr, p.stderr
    assert "Traceback" not in p.stderr and not os.listdir(tmp_path)


def test_without_matplotlib_the_text_still_prints_and_figures_say_what_to_install(
    tmp_path: Path,
) -> None:
    code = (
        "import sys\n"
        "sys.modules['matplotlib'] = None  # as if the plot extra were not installed\n"
        "from depthnav_daemon.cli import main\n"
        "args = ['mount', '--height-m', '0.5', '--tilt-deg', '15']\n"
        "print('rc', main(args))\n"
        f"print('rc', main([*args, '--plot', '{tmp_path / 'side.png'}']))\n"
    )
    p = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT, timeout=120
    )
    assert p.stdout.count("lower dead zone") == 1 and "rc 0" in p.stdout and "rc 1" in p.stdout
    assert "needs matplotlib" in p.stderr and "depthnav[plot]" in p.stderr
    assert "Traceback" not in p.stderr and not (tmp_path / "side.png").exists()


def test_side_view_and_sweep_fit_every_mount() -> None:
    """A level sensor's table points are on the plot; a mount tilted up is called so and on the
    sweep's axis; a steep mount shades what lies beyond where its view meets the floor."""
    level = mount_plan(0.3, 0.0, "realsense-d435", None, "0.5,1,1.5,2,3,4,5")
    ax = draw_side_view(level).axes[0]
    assert ax.get_ylim()[1] >= max(level.highest_m)
    up = mount_plan(0.5, -5.0, "kinect", None, "1,2,3")
    fig = draw_side_view(up)
    assert "tilted 5° up" in fig.axes[0].get_title()
    sweep = draw_sweep(up, "kinect")
    assert all(a.get_xlim()[0] <= -5.0 for a in sweep.axes[:2])
    steep = mount_plan(1.2, 60.0, "kinect", None, "0.5,1,2,3")
    assert steep.view_ends_m == pytest.approx(1.51, abs=0.01)
    labels = [h.get_label() for h in draw_side_view(steep).axes[0].patches]
    assert any("view ends on the floor at 1.51 m" in t for t in labels)
