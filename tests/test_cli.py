"""The depthnav command line end to end, as a user runs it (subprocesses, real fixture, real
signals)."""

from __future__ import annotations

import json
import math
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from depthnav_daemon.pipeline.geometry import Mount
from depthnav_daemon.sim.synthetic import Scene, render, wall
from drivers.base import KINECT_V1, Frame
from drivers.formats.recording_writer import write_recording

ROOT = Path(__file__).resolve().parents[1]
FIXTURE = ROOT / "fixtures" / "corridor_step"


def depthnav(*args: str, timeout: float = 120, **kw: object) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "depthnav_daemon", *args],
        capture_output=True,
        text=True,
        timeout=timeout,
        cwd=ROOT,
        **kw,  # type: ignore[arg-type]
    )


def test_run_prints_one_valid_json_line_per_frame() -> None:
    p = depthnav(
        "run", "--device", f"replay:{FIXTURE}?rate=max", "--sink", "stdout", "--max-frames", "5"
    )
    assert p.returncode == 0, p.stderr
    lines = p.stdout.strip().splitlines()
    assert len(lines) == 5
    for i, line in enumerate(lines):
        msg = json.loads(
            line, parse_constant=lambda c: pytest.fail(f"non-strict JSON constant {c}")
        )
        assert msg["seq"] == i
        scan = msg["scan"]
        for key in (
            "angle_min",
            "angle_max",
            "angle_increment",
            "range_min",
            "range_max",
            "ranges",
        ):
            assert key in scan
        assert {"height_m", "tilt_deg", "roll_deg"} <= set(msg["pose"])
        assert "cliff" in msg
    # logs go to stderr, never into the JSON stream
    assert "depthnav:" in p.stderr


def test_replay_alias_equals_run_with_replay_device() -> None:
    a = depthnav("replay", str(FIXTURE), "--max-frames", "2", "-q")
    b = depthnav("run", "--device", f"replay:{FIXTURE}?rate=max", "--max-frames", "2", "-q")
    assert a.returncode == b.returncode == 0, a.stderr + b.stderr
    strip = lambda out: [  # noqa: E731 - wall clock and stage timings differ between any two runs
        {k: v for k, v in json.loads(x).items() if k not in ("wall_s", "timings_s")}
        for x in out.splitlines()
    ]
    assert strip(a.stdout) == strip(b.stdout)


def test_calibrate_recovers_the_fixture_mount(tmp_path: Path) -> None:
    out = tmp_path / "robot.toml"
    out.write_text('device = "kinect"\n[scan]\nrange_max_m = 4.0\n')
    p = depthnav(
        "calibrate",
        "--device",
        f"replay:{FIXTURE}?rate=max",
        "--frames",
        "8",
        "--json",
        "--write",
        str(out),
    )
    assert p.returncode == 0, p.stderr
    got = json.loads(p.stdout)
    # the fixture's truth (recording.toml [truth]): 0.55 m high, pitched 15 deg down, no roll
    assert got["height_m"] == pytest.approx(0.55, abs=0.01)
    assert got["tilt_deg"] == pytest.approx(15.0, abs=0.5)
    assert got["roll_deg"] == pytest.approx(0.0, abs=0.5)
    assert got["frames_used"] >= 6 and 0 < got["inlier_ratio"] <= 1
    text = out.read_text()
    assert "[mount]" in text and 'device = "kinect"' in text and "range_max_m = 4.0" in text


def test_calibrate_without_floor_fails_with_a_hint(tmp_path: Path) -> None:
    mount = Mount(0.6, 0.0, 0.0)
    view = render(Scene(boxes=(wall(1.2),), floor=False), KINECT_V1, mount)
    frames = [Frame(i, i / 30, view.depth_mm, KINECT_V1) for i in range(3)]
    write_recording(tmp_path / "wall", frames)
    p = depthnav("calibrate", "--device", f"replay:{tmp_path / 'wall'}?rate=max", "--frames", "3")
    assert p.returncode == 1
    assert "too little floor" in p.stderr and "point the sensor at open floor" in p.stderr
    assert "Traceback" not in p.stderr


def _start_endless_run() -> tuple[subprocess.Popen[str], list[str], threading.Thread]:
    """An endless real-time replay; a thread drains its stdout so a full pipe never blocks it."""
    proc = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "depthnav_daemon",
            "run",
            "--device",
            f"replay:{FIXTURE}?rate=realtime&loop=1",
            "--sink",
            "stdout",
        ],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        cwd=ROOT,
    )
    lines: list[str] = []
    first = threading.Event()

    def drain() -> None:
        assert proc.stdout is not None
        for line in proc.stdout:
            lines.append(line)
            first.set()
        first.set()

    reader = threading.Thread(target=drain, daemon=True)
    reader.start()
    assert first.wait(60), "no output within a minute"
    assert lines and lines[0].startswith("{"), proc.stderr.read() if proc.stderr else ""
    return proc, lines, reader


@pytest.mark.parametrize(("sig", "code"), [(signal.SIGTERM, 0), (signal.SIGINT, 130)])
def test_signals_stop_the_run_cleanly(sig: int, code: int) -> None:
    proc, lines, reader = _start_endless_run()
    proc.send_signal(sig)
    proc.wait(timeout=30)
    reader.join(timeout=30)
    err = proc.stderr.read() if proc.stderr else ""
    assert proc.returncode == code, err
    for line in lines:
        json.loads(line)  # nothing half-written
    assert "Traceback" not in err


@pytest.mark.parametrize(
    ("args", "code", "needle"),
    [
        (["run", "--device", "nosuch://x"], 2, "unknown device scheme 'nosuch'"),
        (["run", "--device", "replay:/nonexistent/rec"], 1, "/nonexistent/rec"),
        (["run", "--device", f"replay:{FIXTURE}", "--set", "mount.height_m=-3"], 2, "height_m=-3"),
        (
            ["run", "--device", f"replay:{FIXTURE}", "--sink", "carrier-pigeon://x"],
            2,
            "carrier-pigeon",
        ),
        (["run", "--device", f"replay:{FIXTURE}", "--max-frames", "0"], 2, "--max-frames=0"),
        (
            ["run", "--device", f"replay:{FIXTURE}", "--odometry", "odom+udp://127.0.0.1:0"],
            2,
            "needs a port 1..65535",
        ),
        (["run"], 2, "no device given"),
        (["frobnicate"], 2, "invalid choice"),
        (["mount", "--height-m", "0.5", "--tilt-deg", "200"], 2, "tilt_deg=200"),
    ],
)
def test_bad_input_is_one_clear_line(args: list[str], code: int, needle: str) -> None:
    p = depthnav(*args)
    assert p.returncode == code, p.stderr
    assert needle in p.stderr
    assert "Traceback" not in p.stderr
    errors = [line for line in p.stderr.splitlines() if "error:" in line]
    assert len(errors) == 1, p.stderr


def test_mount_prints_eq_15_16_table_and_plot(tmp_path: Path) -> None:
    png = tmp_path / "side.png"
    p = depthnav(
        "mount", "--height-m", "0.5", "--tilt-deg", "15", "--vfov-deg", "43", "--plot", str(png)
    )
    assert p.returncode == 0, p.stderr
    # eq. 15 with h1 = 0: 0.5 * tan(90 - 21.5 - 15 deg) = 0.5 * tan(53.5 deg) = 0.6757 m
    assert f"{0.5 * math.tan(math.radians(53.5)):.2f} m" in p.stdout
    assert png.stat().st_size > 1000


def test_info_and_devices_run_without_hardware() -> None:
    info = depthnav("info")
    assert info.returncode == 0, info.stderr
    assert "depthnav 0.1.0" in info.stdout and "numpy" in info.stdout
    dev = depthnav("devices")
    assert dev.returncode == 0, dev.stderr


def test_ros_parameter_file_is_accepted_as_a_config() -> None:
    ros = (
        ROOT.parent
        / "shared"
        / "reference"
        / "original_params"
        / "ros1_noetic"
        / "cliff_detector.yaml"
    )
    if not ros.exists():
        pytest.skip("../shared is not beside the project")
    p = depthnav(
        "run", "--device", f"replay:{FIXTURE}?rate=max", "--config", str(ros), "--max-frames", "1"
    )
    assert p.returncode == 0, p.stderr
    assert json.loads(p.stdout)["seq"] == 0


def test_run_quick_enough_to_start() -> None:
    """Not a timing assertion: a sanity bound of a minute so a hang fails instead of stalling CI."""
    t0 = time.monotonic()
    p = depthnav(
        "run",
        "--device",
        f"replay:{FIXTURE}?rate=max",
        "--sink",
        "null",
        "--max-frames",
        "12",
        timeout=60,
    )
    assert p.returncode == 0, p.stderr
    assert time.monotonic() - t0 < 60
    assert np.isfinite(0.0)
    assert os.environ.get("DEPTHNAV_NEVER_SET") is None


def test_a_mount_typed_on_the_command_line_wins_over_the_accelerometer_and_floor() -> None:
    # the fixture's accelerometer and floor both say 0.55 m / 15 deg; the user typed 30 and 5
    p = depthnav(
        "run",
        "--device",
        f"replay:{FIXTURE}?rate=max",
        "--sink",
        "stdout",
        "--max-frames",
        "3",
        "--tilt-deg",
        "30",
        "--roll-deg",
        "5",
    )
    assert p.returncode == 0, p.stderr
    poses = [json.loads(line)["pose"] for line in p.stdout.splitlines()]
    assert all(q["tilt_deg"] == 30.0 and q["roll_deg"] == 5.0 for q in poses), poses
    assert all(q["source"] == "config" for q in poses)
    assert "as given: the accelerometer and the floor estimates do not replace it" in p.stderr
    # asking for the sensors back on the command line lets them in again
    p = depthnav(
        "run",
        "--device",
        f"replay:{FIXTURE}?rate=max",
        "--sink",
        "stdout",
        "--max-frames",
        "3",
        "--tilt-deg",
        "30",
        "--set",
        "daemon.tilt_source=auto",
    )
    assert p.returncode == 0, p.stderr
    last = json.loads(p.stdout.splitlines()[-1])["pose"]
    assert last["tilt_deg"] == pytest.approx(15.0, abs=0.5)


def test_record_from_a_source_shorter_than_asked_says_so(tmp_path: Path) -> None:
    out = tmp_path / "rec"
    p = depthnav("record", "--device", f"replay:{FIXTURE}?rate=max", "--frames", "50", str(out))
    assert p.returncode == 0, p.stderr
    assert "ended after 12 of the 50 frames asked for; recorded 12" in p.stderr


def test_calibrate_interrupted_reports_what_it_has_marked_partial(tmp_path: Path) -> None:
    cfg = tmp_path / "robot.toml"
    cfg.write_text('device = "kinect"\n')
    proc = subprocess.Popen(
        [
            *(sys.executable, "-m", "depthnav_daemon", "calibrate", "--json"),
            *("--device", f"replay:{FIXTURE}?rate=realtime&loop=1", "--frames", "100000"),
            *("--write", str(cfg)),
        ],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        cwd=ROOT,
    )
    assert proc.stderr is not None
    # wait for the first frame (a line on stderr), then Ctrl-C
    deadline = time.monotonic() + 60
    for line in proc.stderr:
        if "calibrating replay:" in line:
            break
        assert time.monotonic() < deadline
    proc.send_signal(signal.SIGINT)
    out, err = proc.communicate(timeout=60)
    assert proc.returncode == 130, err
    got = json.loads(out)
    assert got["partial"] is True and got["frames_read"] >= 1
    assert "partial calibration: stopped after" in err and "nothing written" in err
    assert cfg.read_text() == 'device = "kinect"\n'
