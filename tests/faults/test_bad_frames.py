"""Frames with extreme content through the real frame loop: a defined result or one clear line.

Depth is uint16 millimetres by contract (drivers/base.py), so NaN, inf and negative values can
only come from a file: the readers reject them (below, and test_fuzz_inputs.py). What a uint16
frame can hold (all zeros, saturated 65535, noise, a resolution that changes mid-stream, an
accelerometer reading NaN or zero) must give a Result for every frame.
"""

from __future__ import annotations

import math
import threading
from pathlib import Path

import numpy as np
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from depthnav_daemon.config.loader import build_config
from depthnav_daemon.daemon.loop import run
from depthnav_daemon.pipeline import Result
from drivers.base import DeviceInfo, Frame, Intrinsics
from drivers.formats.recording_writer import write_recording

from .kit import depthnav, json_lines, one_error_line

A = Intrinsics(64, 48, 61.5, 57.25, 30.25, 22.75)
B = Intrinsics(80, 60, 70.0, 66.0, 41.0, 27.5)  # a second mode, for the mid-stream switch
NO_DEPTH = "no valid depth in this frame (all pixels 0)"
# a configured mount: with none, every range stays unknown until the floor is found (issue 33)
MOUNT = ("mount.height_m=0.55", "mount.tilt_deg=5.0")


class ListDriver:
    """A source that plays the given frames (the input under test), then ends."""

    def __init__(self, frames: list[Frame]) -> None:
        self.frames = list(frames)

    def open(self) -> DeviceInfo:
        return DeviceInfo("frames under test", None, "test", self.frames[0].intrinsics, True)

    def read_frame(self, timeout_s: float = 1.0) -> Frame | None:
        return self.frames.pop(0) if self.frames else None

    def close(self) -> None:
        pass


class Collect:
    name = "collect"

    def __init__(self) -> None:
        self.results: list[Result] = []

    def open(self, context: object) -> None:
        pass

    def write(self, frame: Frame, result: Result) -> None:
        self.results.append(result)

    def close(self) -> None:
        pass


def run_frames(frames: list[Frame], *sets: str) -> list[Result]:
    sink = Collect()
    cfg = build_config(
        [], ["daemon.pose_every_frames=1", *sets], {"device": "test", "sinks": ["c"]}
    )
    report = run(
        cfg,
        threading.Event(),
        driver_factory=lambda _s: ListDriver(frames),
        sink_factory=lambda _s: sink,
    )
    assert report.frames == len(frames) == len(sink.results)
    return sink.results


def defined(result: Result, frame: Frame) -> None:
    """What every Result must be, whatever the depth: the frame's intrinsics, finite mount,
    ranges that are numbers or the REP 117 specials."""
    assert result.intrinsics == frame.intrinsics
    assert all(
        math.isfinite(v)
        for v in (result.mount.height_m, result.mount.tilt_deg, result.mount.roll_deg)
    )
    r = np.asarray(result.scan.ranges, dtype=np.float64)
    finite = r[np.isfinite(r)]
    assert np.all(finite >= 0)


DEPTH = st.one_of(
    st.sampled_from(["zeros", "saturated", "ones", "noise", "half"]),
    st.integers(0, 65535),
)
ACCEL = st.one_of(
    st.none(),
    st.tuples(*[st.floats(allow_nan=True, allow_infinity=True, width=32)] * 3),
    st.just((0.0, 0.0, 0.0)),
    st.just((0.0, -9.81, -2.6)),
)


def depth_of(kind: str | int, intr: Intrinsics, seed: int) -> np.ndarray:
    shape = (intr.height, intr.width)
    rng = np.random.default_rng(seed)
    if isinstance(kind, int):
        return np.full(shape, kind, np.uint16)
    return {
        "zeros": lambda: np.zeros(shape, np.uint16),
        "saturated": lambda: np.full(shape, 65535, np.uint16),
        "ones": lambda: np.ones(shape, np.uint16),
        "noise": lambda: rng.integers(0, 65536, shape, dtype=np.uint16),
        "half": lambda: np.where(rng.random(shape) < 0.5, 0, rng.integers(300, 5000, shape)).astype(
            np.uint16
        ),
    }[kind]()


@settings(
    max_examples=150,
    deadline=None,
    derandomize=True,
    database=None,
    suppress_health_check=list(HealthCheck),
)
@given(
    kinds=st.lists(st.tuples(DEPTH, ACCEL, st.booleans()), min_size=1, max_size=4),
    seed=st.integers(0, 9),
)
def test_extreme_frames_give_defined_results(kinds, seed: int) -> None:
    """Zeros, saturation, noise, NaN/inf/zero accelerometer and a resolution switching
    mid-stream."""
    frames = [
        Frame(
            i,
            i / 30,
            depth_of(kind, B if switch else A, seed + i),
            B if switch else A,
            None if accel is None else tuple(map(float, accel)),
        )
        for i, (kind, accel, switch) in enumerate(kinds)
    ]
    for result, frame in zip(run_frames(frames), frames, strict=True):
        defined(result, frame)


def test_all_zero_frame_is_a_warning_not_an_error() -> None:
    frame = Frame(0, 0.0, np.zeros((48, 64), np.uint16), A)
    (result,) = run_frames([frame], *MOUNT)
    assert result.warning == NO_DEPTH
    assert np.isnan(np.asarray(result.scan.ranges, dtype=np.float64)).all()


def test_no_depth_warning_only_when_every_bin_is_nan() -> None:
    """The first bin is looked at first (process() skips the pass over the scan when it has a
    reading): a frame whose first bins see nothing but others do is no warning."""
    depth = np.full((48, 64), 1500, np.uint16)
    depth[:, :40] = 0  # the left part of the image: the last bins (bearings run right to left)
    (left_blind,) = run_frames([Frame(0, 0.0, depth, A)], *MOUNT)
    ranges = np.asarray(left_blind.scan.ranges, dtype=np.float64)
    assert np.isnan(ranges[-1]) and not np.isnan(ranges).all()
    assert left_blind.warning != NO_DEPTH
    depth = np.full((48, 64), 1500, np.uint16)
    depth[:, 24:] = 0  # the right part: the first bins
    (right_blind,) = run_frames([Frame(1, 1 / 30, depth, A)], *MOUNT)
    ranges = np.asarray(right_blind.scan.ranges, dtype=np.float64)
    assert np.isnan(ranges[0]) and not np.isnan(ranges).all()
    assert right_blind.warning != NO_DEPTH


def test_nan_inf_negative_depth_in_a_file_is_one_line(tmp_path: Path) -> None:
    depth = np.full((2, 48, 64), 1500.0, np.float32)
    depth[0, 0, :3] = [np.nan, np.inf, -1.0]
    np.savez(tmp_path / "bad.npz", depth_mm=depth, intrinsics=np.array([61.5, 57.25, 30.25, 22.75]))
    p = depthnav(
        "run", "--device", f"replay:{tmp_path / 'bad.npz'}?rate=max", "--sink", "stdout", timeout=60
    )
    assert p.returncode == 1, p.stderr
    line = one_error_line(p.stderr)
    assert "bad.npz" in line and "'depth_mm' must be uint16" in line
    assert p.stdout == ""


def test_intrinsics_that_do_not_match_the_image(tmp_path: Path) -> None:
    frames = [Frame(i, i / 30, np.full((48, 64), 1500, np.uint16), A) for i in range(2)]
    write_recording(tmp_path / "rec", frames)
    meta = tmp_path / "rec" / "recording.toml"
    meta.write_text(
        meta.read_text().replace("width = 64", "width = 640").replace("height = 48", "height = 480")
    )
    p = depthnav("run", "--device", f"replay:{tmp_path / 'rec'}?rate=max", timeout=60)
    assert p.returncode == 1, p.stderr
    assert "[intrinsics] says 640x480 but frames are 64x48" in one_error_line(p.stderr)
    # a principal point outside the image, given on the command line: a usage error
    write_recording(tmp_path / "ok", frames)
    p = depthnav("run", "--device", f"replay:{tmp_path / 'ok'}?rate=max&cx=900", timeout=60)
    assert p.returncode == 2, p.stderr
    assert "cx=900" in one_error_line(p.stderr)


def test_an_image_too_small_for_the_cliff_blocks_is_a_config_error(tmp_path: Path) -> None:
    """A defined result for a tiny image: the configuration does not fit it (exit 2), and the
    message says which key; not a traceback from inside the stages."""
    tiny = Intrinsics(8, 6, 8.0, 8.0, 3.5, 2.5)
    write_recording(tmp_path / "tiny", [Frame(0, 0.0, np.full((6, 8), 1200, np.uint16), tiny)])
    p = depthnav("run", "--device", f"replay:{tmp_path / 'tiny'}?rate=max", timeout=60)
    assert p.returncode == 2, p.stderr
    assert "cliff.block_size=16 does not fit" in one_error_line(p.stderr)
    p = depthnav(
        "run",
        "--device",
        f"replay:{tmp_path / 'tiny'}?rate=max",
        "--set",
        "daemon.cliff=false",
        "--sink",
        "stdout",
        timeout=60,
    )
    assert p.returncode == 0, p.stderr
    assert len(json_lines(p.stdout)) == 1
