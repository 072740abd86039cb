"""The robot's body in the daemon (issue 33 item 5): a [robot] footprint removes the robot's own
parts (synthetic parts 5-25 cm high, 2-15 cm from the sensor, as on the issue's robot) from every
output: the scan, the cliff, the memory, the base frame and the merged scan of several sensors;
through the real CLI too. Without it those bins read -inf ("too close"); with it they read what
the rest of the scene gives (NaN where nothing else is seen), exactly what a robot without those
parts gives."""

from __future__ import annotations

import json
import subprocess
import sys
import threading
from pathlib import Path

import numpy as np
import pytest

from depthnav_daemon.config.loader import build_config
from depthnav_daemon.daemon.frame_step import FrameStep
from depthnav_daemon.daemon.loop import run
from depthnav_daemon.pipeline import Result, StageParams
from depthnav_daemon.pipeline._jit import KERNELS
from depthnav_daemon.pipeline.geometry import Mount
from depthnav_daemon.sim.synthetic import LABEL_BOX0, Box, KinectNoise, Scene, render
from depthnav_daemon.sinks.json.message import decode_ranges
from drivers.base import Frame
from drivers.formats.recording_writer import write_recording
from tests.daemon.test_loop import CollectSink
from tests.daemon.test_multi_sensor import UntilSink
from tests.pipeline.test_footprint import INTR, MOUNT, PARTS, POLYGON

ROOT = Path(__file__).resolve().parents[2]
# beyond the bumper, in the same bearings: with the footprint those bins read it
AHEAD = Box(0.7, 0.0, 0.15, 0.5, 0.4)
# a second camera looking back over the robot's tail, with a part of the body in its view
BACK = Mount(1.27, 73.0, 0.0, x_m=-0.05, y_m=-0.02, yaw_deg=180.0)
TAIL = Box(-0.16, -0.02, 0.06, 0.30, 0.22, base_m=0.05)
BEHIND = Box(-0.75, 0.1, 0.15, 0.3, 0.4)
ROBOT = {"footprint_m": [list(p) for p in POLYGON], "height_m": 0.3}
FRAMES = 4


def _mount_table(m: Mount) -> dict[str, float]:
    return {k: getattr(m, k) for k in ("height_m", "tilt_deg", "roll_deg", "x_m", "y_m", "yaw_deg")}


def _record(path: Path, scene: Scene, mount: Mount, noisy: bool = False) -> Path:
    """A still robot (odometry in every frame, so the memory is on) watching ``scene``."""
    rng = np.random.default_rng(5)
    frames = []
    for i in range(FRAMES):
        depth = render(scene, INTR, mount, KinectNoise() if noisy else None, rng).depth_mm
        frames.append(Frame(i, i / 10.0, depth, INTR, odom=(0.0, 0.0, 0.0)))
    write_recording(path, frames)
    return path


@pytest.fixture(scope="module")
def recordings(tmp_path_factory) -> dict[str, Path]:
    tmp = tmp_path_factory.mktemp("body")
    return {
        "robot": _record(tmp / "robot", Scene(boxes=(*PARTS, TAIL, AHEAD, BEHIND)), MOUNT),
        "bare": _record(tmp / "bare", Scene(boxes=(AHEAD, BEHIND)), MOUNT),
        "back": _record(tmp / "back", Scene(boxes=(*PARTS, TAIL, AHEAD, BEHIND)), BACK),
        "back_bare": _record(tmp / "back_bare", Scene(boxes=(AHEAD, BEHIND)), BACK),
        "noisy": _record(tmp / "noisy", Scene(boxes=(*PARTS, TAIL, AHEAD)), MOUNT, noisy=True),
    }


def _results(overrides: dict, *sets: str) -> list[Result]:
    sink = CollectSink()
    # the mount pinned: the runs compared below use exactly the same mount
    cfg = build_config([], ["daemon.tilt_source=config", *sets], overrides)
    run(cfg, threading.Event(), sink_factory=lambda _s: sink)
    return sink.results


def _last(overrides: dict, *sets: str) -> Result:
    return _results(overrides, *sets)[-1]


def _one(recordings, name: str, robot: bool) -> Result:
    over = {"device": f"replay:{recordings[name]}?rate=max", "mount": _mount_table(MOUNT)}
    result = _last({**over, "robot": ROBOT} if robot else over)
    assert result.seq == FRAMES - 1
    return result


def _same(a: np.ndarray, b: np.ndarray) -> bool:
    return np.array_equal(a, b, equal_nan=True)


def test_the_footprint_removes_the_robot_from_the_scan_the_cliff_and_the_memory(
    recordings,
) -> None:
    without = _one(recordings, "robot", robot=False)
    body = _one(recordings, "robot", robot=True)
    bare = _one(recordings, "bare", robot=False)
    # without the footprint the robot's parts are obstacles "too close" on every frame
    too_close = np.isneginf(without.scan.ranges)
    assert too_close.sum() > 100 and np.isneginf(without.level_scan.ranges).sum() > 100
    # with it: what a robot without those parts sees, bin for bin (base and sensor frames)
    assert _same(body.scan.ranges, bare.scan.ranges)
    assert _same(body.level_scan.ranges, bare.level_scan.ranges)
    assert not np.isneginf(body.scan.ranges).any()
    # the body's bins read the box beyond the bumper, or unknown: never clear
    ahead = too_close & np.isfinite(body.scan.ranges)
    assert ahead.sum() > 20 and np.all(np.abs(body.scan.ranges[ahead] - 0.66) < 0.05)
    assert np.isnan(body.scan.ranges[too_close & ~ahead]).all()
    assert not np.isposinf(body.scan.ranges[too_close]).any()
    # the cliff: no drop-off from the body, every bin as without the parts
    for got, want in ((body.cliff, bare.cliff), (body.level_cliff, bare.level_cliff)):
        assert _same(got.scan.ranges, want.scan.ranges)
        assert np.array_equal(got.points_m, want.points_m)
    # the memory: the body was remembered around the robot; with the footprint it is not
    assert without.memory.obstacle_cells > body.memory.obstacle_cells
    assert body.memory.obstacle_cells == bare.memory.obstacle_cells
    assert _same(body.memory.scan.ranges, bare.memory.scan.ranges)
    assert np.nanmin(without.memory.scan.ranges) < 0.4 < np.nanmin(body.memory.scan.ranges)
    assert body.timings_s["body"] >= 0.0 and "body" not in without.timings_s


def test_the_floor_search_and_a_noisy_sensor_keep_the_body_out(recordings, caplog) -> None:
    """The mount not pinned: the floor estimate runs on the frames without the body, and the
    noisy depth of a Kinect-like sensor (the body's edges drop out or wander) leaves nothing too
    close either."""
    caplog.set_level("INFO", "depthnav_daemon.daemon.frame_step")
    sink = CollectSink()
    over = {"device": f"replay:{recordings['noisy']}?rate=max", "mount": _mount_table(MOUNT)}
    run(
        build_config([], [], {**over, "robot": ROBOT}),
        threading.Event(),
        sink_factory=lambda _s: sink,
    )
    for r in sink.results:
        assert not np.isneginf(r.scan.ranges).any() and np.nanmin(r.scan.ranges) > 0.6
    assert sink.results[0].pose is not None and sink.results[0].pose.ok
    assert abs(sink.results[-1].mount.tilt_deg - 73.0) < 0.5
    assert "readings of it removed" in caplog.text


def test_the_stages_see_the_frame_without_the_body_and_the_drivers_frame_is_kept() -> None:
    view = render(Scene(boxes=(*PARTS, AHEAD)), INTR, MOUNT)
    frame = Frame(0, 0.0, view.depth_mm.copy(), INTR)
    cfg = build_config(
        [], ["daemon.tilt_source=config"], {"mount": _mount_table(MOUNT), "robot": ROBOT}
    )
    step = FrameStep(cfg, StageParams(scan=cfg.scan, cliff=cfg.cliff), None)
    try:
        result = step.run(frame)
    finally:
        step.close()
    assert np.array_equal(frame.depth_mm, view.depth_mm)  # the driver's frame as it came
    seen = step.stage_frame
    assert seen is not None and seen is not frame and seen.seq == frame.seq
    parts = (view.label >= LABEL_BOX0) & (view.label < LABEL_BOX0 + len(PARTS))
    assert parts.sum() > 500 and not seen.depth_mm[parts].any()
    assert not np.isneginf(result.scan.ranges).any()


def test_an_unconfigured_mount_found_by_the_floor_leaves_the_body_out(recordings) -> None:
    """No [mount] (issue 33 item 4): the floor search finds the 1.27 m / 73 deg camera, and
    from the frame its mount serves on, the body is removed as seen from that mount. The
    placement (x_m, y_m) is configured: the floor gives only height, tilt and roll."""
    sink = CollectSink()
    over = {
        "device": f"replay:{recordings['robot']}?rate=max",
        "mount": {"x_m": MOUNT.x_m, "y_m": MOUNT.y_m},
        "robot": ROBOT,
    }
    run(build_config([], [], over), threading.Event(), sink_factory=lambda _s: sink)
    known = [r for r in sink.results if r.mount_trust is not None and r.mount_trust.trusted]
    assert known and abs(known[-1].mount.tilt_deg - 73.0) < 0.5
    for r in known:
        assert not np.isneginf(r.scan.ranges).any() and np.isfinite(r.scan.ranges).sum() > 20


def test_several_sensors_merge_without_the_body(recordings) -> None:
    def merged(front: str, back: str, robot: bool) -> Result:
        sensors = [
            {
                "name": n,
                "device": f"replay:{recordings[r]}?rate=max&loop=1",
                "mount": _mount_table(m),
            }
            for n, r, m in (("front", front, MOUNT), ("back", back, BACK))
        ]
        extra = {"robot": ROBOT} if robot else {}
        cfg = build_config(
            [],
            ["daemon.tilt_source=config", "daemon.sensor_max_age_s=3600"],
            {"sensor": sensors, **extra},
        )
        # the sensors run on threads of their own: until both merged 3 times (no timing)
        sink = UntilSink(lambda r: all(s.status == "ok" for s in r.sensors), 3)
        run(cfg, sink.stop, sink_factory=lambda _s: sink)
        both = [r for r in sink.results if all(s.status == "ok" for s in r.sensors)]
        assert len(both) >= 3 and len(both[-1].sensors) == 2
        return both[-1]

    without = merged("robot", "back", robot=False)
    body = merged("robot", "back", robot=True)
    bare = merged("bare", "back_bare", robot=False)
    assert np.isneginf(without.scan.ranges).sum() > 100
    assert not np.isneginf(body.scan.ranges).any()
    assert _same(body.scan.ranges, bare.scan.ranges)
    # both sides: the box ahead and the one behind, each where a part of the body read -inf
    back = np.abs(body.scan.angles) > np.pi / 2
    assert (np.isneginf(without.scan.ranges) & back).sum() > 20
    assert np.isfinite(body.scan.ranges[back]).sum() > 10


def _cli(*args: str) -> subprocess.CompletedProcess[str]:
    argv = [sys.executable, "-m", "depthnav_daemon", "run", "--sink", "stdout", *args]
    return subprocess.run(argv, capture_output=True, text=True, cwd=ROOT, timeout=600)


def test_through_the_cli_the_body_is_gone_from_the_json(recordings, tmp_path) -> None:
    lines = ["[mount]"] + [f"{k} = {v}" for k, v in _mount_table(MOUNT).items()]
    config = tmp_path / "robot.toml"
    config.write_text("\n".join(lines) + "\n")
    body = tmp_path / "body.toml"
    body.write_text(
        config.read_text()
        + "[robot]\nfootprint_m = "
        + json.dumps([list(p) for p in POLYGON])
        + "\nheight_m = 0.3\n"
    )
    device = f"replay:{recordings['robot']}?rate=max"
    out = {}
    for name, path in (("without", config), ("with", body)):
        done = _cli("--config", str(path), "--device", device)
        assert done.returncode == 0, done.stderr
        msgs = [json.loads(line) for line in done.stdout.splitlines()]
        assert len(msgs) == FRAMES
        out[name] = msgs[-1]
    scan = {k: decode_ranges(m["scan"]["ranges"]) for k, m in out.items()}
    memory = {k: decode_ranges(m["memory"]["scan"]["ranges"]) for k, m in out.items()}
    assert np.isneginf(scan["without"]).sum() > 100 and not np.isneginf(scan["with"]).any()
    assert not np.isposinf(scan["with"][np.isneginf(scan["without"])]).any()
    assert np.nanmin(memory["without"]) < 0.4 < np.nanmin(memory["with"])
    assert (
        out["with"]["memory"]["cells"]["obstacle"] < out["without"]["memory"]["cells"]["obstacle"]
    )
    assert "body" in out["with"]["timings_s"]


def test_a_bad_footprint_on_the_command_line_is_one_line(recordings) -> None:
    done = _cli(
        "--device",
        f"replay:{recordings['robot']}?rate=max",
        "--set",
        "robot.footprint_m=[[0,0],[1,1],[1,0],[0,1]]",
        "--set",
        "robot.height_m=0.3",
    )
    assert done.returncode == 2 and not done.stdout
    assert "not a convex polygon" in done.stderr and "hint:" in done.stderr
    assert "Traceback" not in done.stderr and len(done.stderr.strip().splitlines()) <= 2


def test_after_the_warm_up_a_footprint_compiles_nothing(recordings) -> None:
    """The warm-up (tools/warmup.py) runs the daemon with a footprint: a service with one
    compiles nothing at its first frame (real replayed frames, read-only as every driver's)."""
    from depthnav_daemon.tools.warmup import warm_up

    warm_up()
    ours = [k for k in KERNELS if k.py_func.__module__.endswith(".footprint")]
    assert len(ours) == 3 and all(k.signatures for k in ours)
    before = {k.py_func.__name__: len(k.signatures) for k in ours}
    _one(recordings, "robot", robot=True)
    placed = Mount(0.55, 15.0, 0.0, x_m=0.2, y_m=-0.1, yaw_deg=20.0)
    over = {"device": f"replay:{ROOT / 'fixtures' / 'corridor_step'}?rate=max"}
    _last({**over, "mount": _mount_table(placed), "robot": ROBOT})
    assert {k.py_func.__name__: len(k.signatures) for k in ours} == before


def test_the_snapshot_draws_the_body_and_the_scan_without_it(recordings, tmp_path) -> None:
    """``depthnav snapshot`` with a [robot] draws the configured outline (hatched, "ignored") in
    the top-down view, and what it draws is the frame the stages saw (no -inf from the body)."""
    pytest.importorskip("matplotlib")
    from depthnav_daemon.plots.snapshot import draw_snapshot

    body = tmp_path / "body.toml"
    lines = ["[mount]"] + [f"{k} = {v}" for k, v in _mount_table(MOUNT).items()]
    lines += ["[robot]", f"footprint_m = {json.dumps([list(p) for p in POLYGON])}"]
    body.write_text("\n".join([*lines, "height_m = 0.3", ""]))
    out = tmp_path / "snap.png"
    device = f"replay:{recordings['robot']}?rate=max"
    argv = ["snapshot", "--config", str(body), "--device", device, "--frame", "2", str(out)]
    done = subprocess.run(
        [sys.executable, "-m", "depthnav_daemon", *argv],
        capture_output=True, text=True, cwd=ROOT, timeout=300,
    )  # fmt: skip
    assert done.returncode == 0, done.stderr
    assert out.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    result = _one(recordings, "robot", robot=True)
    fig = draw_snapshot(
        Frame(0, 0.0, np.zeros((INTR.height, INTR.width), np.uint16), INTR), result, 5.0,
        body_m=tuple(POLYGON),
    )  # fmt: skip
    labels = [t.get_text() for legend in fig.legends for t in legend.get_texts()]
    assert "robot body (ignored), sensor ▲" in labels
    top = fig.axes[1]
    drawn = [p.get_xy() for p in top.patches if p.get_hatch() == "//"]
    want = np.c_[[-y for _, y in POLYGON], [x for x, _ in POLYGON]]
    assert len(drawn) == 1 and np.allclose(drawn[0][: len(POLYGON)], want)
    assert not np.isneginf(result.scan.ranges).any()
