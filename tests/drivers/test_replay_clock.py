"""The replay's clock: a looped recording goes on from its own first stamp (any epoch), and the
times handed out always increase."""

from __future__ import annotations

import dataclasses
import itertools
import logging
from pathlib import Path

import numpy as np
import pytest

import drivers
from drivers.base import Frame
from drivers.formats.png_folder import write_png_folder
from drivers.formats.recording_writer import write_recording
from drivers.replay_clock import ReplayClock
from tests.drivers.driverkit import ramp_frames

T0_S = 1_355_494_975.25  # a UNIX time, as robots stamp their recordings
PERIOD_S = 1.0 / 30.0


def epoch_frames(stamps: list[float]) -> list[Frame]:
    """ramp_frames stamped at ``stamps`` (s)."""
    frames = ramp_frames(len(stamps))
    return [dataclasses.replace(f, timestamp_s=t) for f, t in zip(frames, stamps, strict=True)]


def replay_stamps(spec: str, count: int) -> list[float]:
    with drivers.opened(drivers.create_driver(spec)) as driver:
        got = [driver.read_frame() for _ in range(count)]
    assert all(f is not None for f in got)
    return [f.timestamp_s for f in got]  # type: ignore[union-attr]


def write_as(kind: str, path: Path, frames: list[Frame]) -> str:
    """``frames`` as a depthnav recording, a bare .npz or an image folder; returns the spec path."""
    if kind == "images":
        write_png_folder(path, frames, scale=1000.0)
        return str(path)
    write_recording(path, frames)
    if kind == "recording":
        return str(path)
    i = frames[0].intrinsics  # a bare .npz: its stamps, the intrinsics given
    return f"{path / 'frames.npz'}?fx={i.fx}&fy={i.fy}&cx={i.cx}&cy={i.cy}"


@pytest.mark.parametrize("kind", ["recording", "npz", "images"])
def test_loop_goes_on_from_the_recordings_first_stamp(tmp_path: Path, kind: str) -> None:
    """3 frames at 10 Hz from T0: the 8 looped frames are T0 + k/10, not 2*T0 after the first
    pass (the loop offset assumed recordings start at 0) and not a 1/fps gap between passes.
    (Image folders are stamped from their first image, so only the gap shows there.)"""
    period = 0.1
    path = write_as(kind, tmp_path / kind, epoch_frames([T0_S + i * period for i in range(3)]))
    stamps = replay_stamps(f"replay:{path}{'&' if '?' in path else '?'}rate=max&loop=1", 8)
    first = stamps[0]
    assert first == pytest.approx(0.0 if kind == "images" else T0_S, abs=1e-6)
    want = [first + k * period for k in range(8)]
    np.testing.assert_allclose(stamps, want, rtol=0, atol=2e-6)  # PNG folders keep 6 decimals


def test_loop_with_start_counts_the_pass_from_frame_0(tmp_path: Path) -> None:
    rec = tmp_path / "r"
    write_recording(rec, epoch_frames([T0_S + i * PERIOD_S for i in range(4)]))
    stamps = replay_stamps(f"replay:{rec}?rate=max&loop=1&start=2", 5)
    want = [T0_S + k * PERIOD_S for k in (2, 3, 4, 5, 6)]
    np.testing.assert_allclose(stamps, want, rtol=0, atol=1e-6)


def test_a_single_frame_loops_one_fps_period_apart(tmp_path: Path) -> None:
    write_recording(tmp_path / "one", epoch_frames([T0_S]))
    stamps = replay_stamps(f"replay:{tmp_path / 'one'}?rate=max&loop=1&fps=10", 3)
    np.testing.assert_allclose(stamps, [T0_S, T0_S + 0.1, T0_S + 0.2], rtol=0, atol=1e-6)


def test_duplicate_stamps_are_moved_past_the_last(tmp_path: Path, caplog) -> None:
    """Duplicates in a recording: kept, stamped 1 ms after the frame before; one warning and the
    count at the end; the loop still goes on after the pass's latest stamp."""
    raw = [T0_S, T0_S + 0.1, T0_S + 0.1, T0_S + 0.1, T0_S + 0.2]
    write_recording(tmp_path / "r", epoch_frames(raw))
    with caplog.at_level(logging.WARNING, logger="drivers.replay_clock"):
        stamps = replay_stamps(f"replay:{tmp_path / 'r'}?rate=max&loop=1", 7)
    want = [T0_S, T0_S + 0.1, T0_S + 0.101, T0_S + 0.102, T0_S + 0.2]
    np.testing.assert_allclose(stamps[:5], want, rtol=0, atol=1e-6)
    assert all(b > a for a, b in itertools.pairwise(stamps))
    # pass 2 from T0 + (0.2 + 0.05): the span plus the mean spacing
    np.testing.assert_allclose(stamps[5:], [T0_S + 0.25, T0_S + 0.35], rtol=0, atol=1e-6)
    # the clock's own records: other loggers' records reach caplog too when an earlier test of
    # the worker lowered the root level (the writer's "wrote 5 frames")
    said = [r.getMessage() for r in caplog.records if r.name == "drivers.replay_clock"]
    assert len(said) == 2, said
    assert "not after the frame before" in said[0] and "2 frames' stamps moved" in said[1]


def test_a_step_back_is_moved_past_the_last() -> None:
    """A stamp going back (a bag's header stamps need not follow its log order)."""
    clock = ReplayClock("bag", 30.0)
    got = [clock.time(t, i) for i, t in enumerate([10.0, 10.5, 10.2, 10.4, 11.0])]
    assert got == pytest.approx([10.0, 10.5, 10.501, 10.502, 11.0])
    assert clock.nudged == 2
