"""Round 3, part 2 (issue 35 item 10): ``calibrate --write`` changes the robot's config only on a
normal end or SIGTERM, and only from at least MIN_WRITE_FRAMES (3) frames with a floor estimate:
a hang-up (SIGHUP, a closing terminal) rewrote it from 31-69 frames, and under load from 1.
Through the CLI in a child process: the exit code, the file, a prompt stop."""

from __future__ import annotations

import signal
import time
from pathlib import Path

import numpy as np
import pytest

from depthnav_daemon.commands.calibrate import MIN_WRITE_FRAMES
from drivers.base import Frame
from drivers.formats.recording import read_recording
from drivers.formats.recording_writer import write_recording
from tests.faults.kit import (
    ENDLESS,
    FIXTURE,
    WAIT_S,
    depthnav_measured,
    finish,
    one_error_line,
    start,
    wait_until_ours,
)

ROBOT = 'device = "kinect"  # the sensor\n[scan]\nrange_max_m = 4.0\n'
ENOUGH = "frames gave a floor estimate: enough to write the config"


def _calibrate_until(tmp_path: Path, device: str, needle: str, sig: int) -> tuple[int, str, float]:
    """calibrate --write until ``needle`` is on stderr, then ``sig``: (exit code, stderr, seconds
    from the signal to the exit)."""
    robot = tmp_path / "robot.toml"
    robot.write_text(ROBOT)
    proc = start(
        "calibrate", "--device", device, "--frames", "100000", "--write", str(robot),
        stderr_path=tmp_path / "err.txt",
    )  # fmt: skip
    wait_until_ours(proc)
    deadline = time.monotonic() + WAIT_S
    while needle not in (tmp_path / "err.txt").read_text():
        assert proc.poll() is None and time.monotonic() < deadline, "never got there"
        time.sleep(0.02)
    t0 = time.monotonic()
    code, _, err = finish(proc, sig)
    return code, err, time.monotonic() - t0


def test_a_hang_up_writes_nothing(tmp_path: Path) -> None:
    code, err, took = _calibrate_until(tmp_path, ENDLESS, ENOUGH, signal.SIGHUP)
    assert code == 0 and took < 1.0, err
    assert "stopped by SIGHUP: nothing written" in err and "Traceback" not in err
    assert (tmp_path / "robot.toml").read_text() == ROBOT


def test_sigterm_writes_what_enough_frames_give(tmp_path: Path) -> None:
    code, err, took = _calibrate_until(tmp_path, ENDLESS, ENOUGH, signal.SIGTERM)
    assert code == 0 and took < 1.0, err
    text = (tmp_path / "robot.toml").read_text()
    assert text.startswith(ROBOT.splitlines()[0]) and "[mount]" in text and "height_m" in text


def _no_floor(tmp_path: Path, n: int, good: int = 0) -> str:
    """A recording of ``n`` frames: ``good`` fixture frames (floor found), then nothing."""
    frames = read_recording(FIXTURE).frames()
    out = [
        frames[i]
        if i < good
        else Frame(i, i / 30, np.zeros_like(frames[0].depth_mm), frames[0].intrinsics)
        for i in range(n)
    ]
    for i, f in enumerate(out):
        out[i] = Frame(i, i / 30, f.depth_mm, f.intrinsics)
    write_recording(tmp_path / "rec", out)
    return f"replay:{tmp_path / 'rec'}"


def test_sigterm_before_enough_frames_writes_nothing(tmp_path: Path) -> None:
    device = _no_floor(tmp_path, 30) + "?rate=realtime&loop=1"
    code, err, took = _calibrate_until(tmp_path, device, "calibrating replay:", signal.SIGTERM)
    assert code == 0 and took < 1.0, err
    assert f"a written calibration needs {MIN_WRITE_FRAMES}" in err or "too little floor" in err
    assert (tmp_path / "robot.toml").read_text() == ROBOT


def test_a_normal_end_below_the_minimum_writes_nothing(tmp_path: Path) -> None:
    """4 frames, 2 with floor: calibrate's own rule (a third of the frames) takes it, the write
    does not (2 < 3)."""
    robot = tmp_path / "robot.toml"
    robot.write_text(ROBOT)
    device = _no_floor(tmp_path, 4, good=2) + "?rate=max"
    done = depthnav_measured(
        "calibrate", "--device", device, "--frames", "4", "--write", str(robot)
    )
    assert done.returncode == 1, done.stderr
    line = one_error_line(done.stderr)
    assert "nothing written" in line and "2 of 4 frames gave a floor estimate" in line, line
    assert robot.read_text() == ROBOT


@pytest.mark.parametrize("frames", ["1", "2"])
def test_too_few_frames_to_write_is_a_usage_error(tmp_path: Path, frames: str) -> None:
    robot = tmp_path / "robot.toml"
    robot.write_text(ROBOT)
    done = depthnav_measured(
        "calibrate", "--device", ENDLESS, "--frames", frames, "--write", str(robot)
    )
    assert done.returncode == 2, done.stderr
    assert "too few to --write" in one_error_line(done.stderr)
    assert robot.read_text() == ROBOT
