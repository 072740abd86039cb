"""depthnav calibrate searches every plausible mount: no prior to guess (issue: a sensor 2.6 m
high pitched 35 deg down, or 1.27 m high pitched 73 deg down, was refused by the daemon's narrow
default prior)."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from depthnav_daemon.commands.calibration import WHOLE_RANGE, calibration_prior
from depthnav_daemon.pipeline.geometry import Mount
from depthnav_daemon.pipeline.pose import PoseParams
from depthnav_daemon.sim.synthetic import Scene, render
from drivers.base import Frame, Intrinsics, tilt_roll_to_accel
from drivers.formats.recording_writer import write_recording

ROOT = Path(__file__).resolve().parents[2]
CMU = ROOT.parent / "shared" / "data" / "real" / "cmu_panoptic_kinoptic_10view"
ASYM = Intrinsics(320, 240, 290.0, 280.0, 163.0, 117.0)
FRAMES = ("--frames", "3")


def calibrate(spec: str) -> dict:
    proc = subprocess.run(
        [sys.executable, "-m", "depthnav_daemon", "calibrate", "--device", spec, "--json", *FRAMES],
        capture_output=True,
        text=True,
        cwd=ROOT,
        timeout=300,
    )
    assert proc.returncode == 0, proc.stderr
    return json.loads(proc.stdout)


def record(tmp_path: Path, frames: list[Frame]) -> str:
    out = tmp_path / "rec"
    write_recording(out, frames)
    return f"replay:{out}?rate=max"


@pytest.mark.parametrize("mount", [Mount(2.6, 35.0, 4.0), Mount(1.27, 73.0, -2.0)])
def test_calibrate_finds_a_mount_far_outside_the_daemons_default_prior(
    tmp_path: Path, mount: Mount
) -> None:
    depth = render(Scene(), ASYM, mount).depth_mm
    got = calibrate(record(tmp_path, [Frame(i, i / 30, depth, ASYM) for i in range(3)]))
    assert got["height_m"] == pytest.approx(mount.height_m, abs=0.01)
    assert got["tilt_deg"] == pytest.approx(mount.tilt_deg, abs=0.5)
    assert got["roll_deg"] == pytest.approx(mount.roll_deg, abs=0.5)


def test_calibrate_on_a_real_kinect_v2_on_a_mast(tmp_path: Path) -> None:
    """CMU Panoptic view 5 (2.64 m, 38 deg down; non-commercial: read in place, a temporary
    recording only)."""
    if not CMU.is_dir():
        pytest.skip(f"{CMU} is absent")
    data = np.load(CMU / "views.npz")
    fx, fy, cx, cy = (float(v) for v in data["intrinsics_per_view"][5])
    depth = data["depth_mm"][5]
    intr = Intrinsics(depth.shape[1], depth.shape[0], fx, fy, cx, cy)
    got = calibrate(record(tmp_path, [Frame(i, i / 30, depth, intr) for i in range(3)]))
    assert got["height_m"] == pytest.approx(float(data["height_m"][5]), abs=0.02)
    assert got["tilt_deg"] == pytest.approx(float(data["pitch_down_deg"][5]), abs=1.0)


def test_a_prior_the_user_gave_wins_over_the_whole_range() -> None:
    wide = calibration_prior(PoseParams())
    assert {k: getattr(wide, k) for k in WHOLE_RANGE} == WHOLE_RANGE
    mine = PoseParams(height_min_m=0.4, height_max_m=0.7)
    assert calibration_prior(mine) == mine


def test_the_accelerometer_centres_the_search_even_beyond_80_deg(tmp_path: Path) -> None:
    # 85 deg down: outside the no-accelerometer range (a wall head-on looks like a floor from
    # above), found when the frames carry the accelerometer's reading
    mount = Mount(1.1, 85.0, 3.0)
    depth = render(Scene(), ASYM, mount).depth_mm
    accel = tilt_roll_to_accel(mount.tilt_deg, mount.roll_deg)
    frames = [Frame(i, i / 30, depth, ASYM, accel) for i in range(3)]
    got = calibrate(record(tmp_path, frames))
    assert got["tilt_deg"] == pytest.approx(85.0, abs=0.5)
    assert got["height_m"] == pytest.approx(1.1, abs=0.01)
    prior = calibration_prior(PoseParams(), accel)
    assert (prior.tilt_min_deg, prior.tilt_max_deg) == (75.0, 89.0)


def test_the_daemon_tracks_a_calibrated_mount_outside_its_default_prior(tmp_path: Path) -> None:
    # calibrate writes a mast mount (2.6 m, 35 deg); the daemon's live floor tracking must keep
    # finding the floor around it, not give up for its default 0.1-1.5 m window
    mount = Mount(2.6, 35.0, 4.0)
    depth = render(Scene(), ASYM, mount).depth_mm
    spec = record(tmp_path, [Frame(i, i / 30, depth, ASYM) for i in range(3)])
    cfg = tmp_path / "robot.toml"
    cfg.write_text("[mount]\nheight_m = 2.62\ntilt_deg = 34.0\nroll_deg = 3.0\n")
    proc = subprocess.run(
        [
            sys.executable,
            "-m",
            "depthnav_daemon",
            "run",
            "--device",
            spec,
            "--config",
            str(cfg),
            "--sink",
            "stdout",
            "--set",
            "daemon.pose_every_frames=1",
        ],
        capture_output=True,
        text=True,
        cwd=ROOT,
        timeout=300,
    )
    assert proc.returncode == 0, proc.stderr
    poses = [json.loads(line)["pose"] for line in proc.stdout.splitlines()]
    assert all(p["estimate"]["ok"] for p in poses), poses[0]["estimate"]
    assert poses[-1]["source"] == "floor"
    assert poses[-1]["height_m"] == pytest.approx(2.6, abs=0.01)
    assert poses[-1]["tilt_deg"] == pytest.approx(35.0, abs=0.5)
