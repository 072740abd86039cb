"""Folders as datasets ship them: depth beside colour (TUM, slambook, flat), 16-bit PGM, ?glob=."""

from __future__ import annotations

import logging
import os
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

import drivers
from drivers.errors import RecordingError
from drivers.formats.depth_images import kind_of, read_depth_image
from tests.drivers.driverkit import SMALL, ramp_frames

INTR = "fx=61.5&fy=57.25&cx=30.25&cy=22.75"


def read_all(spec: str) -> list[drivers.Frame]:
    with drivers.opened(drivers.create_driver(spec)) as driver:
        return list(drivers.iter_frames(driver))


def depths(n: int = 3) -> list[np.ndarray]:
    return [f.depth_mm for f in ramp_frames(n, accel=False)]


def write_pgm(path: Path, depth: np.ndarray, maxval: int = 65535, header: bytes = b"") -> Path:
    """A netpbm binary PGM: big-endian samples (``header`` replaces the standard one)."""
    height, width = depth.shape
    head = header or f"P5\n# depthnav test\n{width} {height}\n{maxval}\n".encode()
    sample = ">u2" if maxval > 255 else "u1"
    path.write_bytes(head + depth.astype(sample).tobytes())
    return path


def write_colour(path: Path, seed: int = 0) -> Path:
    rgb = np.random.default_rng(seed).integers(0, 255, (SMALL.height, SMALL.width, 3), np.uint8)
    Image.fromarray(rgb).save(path)
    return path


def write_depth_png(path: Path, depth: np.ndarray) -> Path:
    Image.fromarray(depth.astype(np.uint16)).save(path)
    return path


# --- PGM -----------------------------------------------------------------------------------------
@pytest.mark.parametrize("maxval", [65535, 4095, 1000])
def test_pgm_values_are_read_as_stored_big_endian(tmp_path, maxval):
    # Pillow rescales samples to 0..65535 when maxval is not 65535: depth must not be rescaled
    depth = np.minimum(depths(1)[0], maxval)
    path = write_pgm(tmp_path / "d.pgm", depth, maxval)
    np.testing.assert_array_equal(read_depth_image(path, 1000.0), depth)
    np.testing.assert_array_equal(
        read_depth_image(path, 5000.0), np.rint(depth / 5.0).astype(np.uint16)
    )
    assert kind_of(path) == "depth"


@pytest.mark.parametrize(
    ("content", "says"),
    [
        (b"P5 64 48 255\n" + bytes(64 * 48), "8-bit PGM"),
        (b"P5 64 48 65535\n" + bytes(100), "bytes of pixels"),
        (b"P5 64 x 65535\n" + bytes(6144), "malformed"),
        (b"P5 64 48 65535" + bytes(6144), "whitespace"),
        (b"P5 100000 100000 65535\n" + bytes(64), "100000"),
        (b"P5 64 48 70000\n" + bytes(6144), "maxval 70000"),
        (b"P5 2 1 1000\n\xff\xff\x00\x00", "above the PGM's maxval"),
    ],
)
def test_bad_pgms_are_one_line_errors(tmp_path, content, says):
    path = tmp_path / "bad.pgm"
    path.write_bytes(content)
    with pytest.raises(RecordingError, match=says) as info:
        read_depth_image(path, 1000.0)
    assert "\n" not in str(info.value) and str(path) in str(info.value)


def test_a_fifo_named_pgm_is_refused_not_waited_on(tmp_path):
    fifo = tmp_path / "d.pgm"
    os.mkfifo(fifo)
    assert kind_of(fifo) == "unknown"  # kept, so that reading it says what it is
    with pytest.raises(RecordingError, match="not a regular file"):
        read_depth_image(fifo, 1000.0)


def test_slambook_layout_color_and_pgm_depth_folders(tmp_path):
    want = depths(3)
    for i, depth in enumerate(want, 1):
        (tmp_path / "color").mkdir(exist_ok=True)
        (tmp_path / "depth").mkdir(exist_ok=True)
        write_colour(tmp_path / "color" / f"{i}.png", i)
        write_pgm(tmp_path / "depth" / f"{i}.pgm", depth)
    (tmp_path / "pose.txt").write_text("0 0 0 0 0 0 1\n")
    got = read_all(f"replay:{tmp_path}?rate=max&scale=1000&{INTR}")
    assert len(got) == 3
    for frame, depth in zip(got, want, strict=True):
        np.testing.assert_array_equal(frame.depth_mm, depth)
        assert frame.intrinsics == SMALL


def test_pgm_folder_needs_a_stated_scale_like_png(tmp_path):
    write_pgm(tmp_path / "1.pgm", depths(1)[0])
    with pytest.raises(RecordingError, match="not stated"):
        read_all(f"replay:{tmp_path}?rate=max&{INTR}")


# --- picking depth among colour ------------------------------------------------------------------
def test_flat_folder_of_colour_and_depth_reads_the_depth_and_says_what_it_skipped(tmp_path, caplog):
    want = depths(3)
    for i, depth in enumerate(want, 1):  # slambook ch7 / TUM pairs: 1.png beside 1_depth.png
        write_colour(tmp_path / f"{i}.png", i)
        write_depth_png(tmp_path / f"{i}_depth.png", depth)
    with caplog.at_level(logging.INFO, logger="drivers"):
        got = read_all(f"replay:{tmp_path}?rate=max&scale=1000&{INTR}")
    assert [f.seq for f in got] == [0, 1, 2]
    for frame, depth in zip(got, want, strict=True):
        np.testing.assert_array_equal(frame.depth_mm, depth)
    said = [r.getMessage() for r in caplog.records if "skipped" in r.getMessage()]
    assert len(said) == 1 and "3 colour" in said[0] and "glob" in said[0]


def test_tum_layout_without_depth_txt_reads_depth_subfolder(tmp_path):
    want = depths(2)
    (tmp_path / "rgb").mkdir()
    (tmp_path / "depth").mkdir()
    for i, depth in enumerate(want):
        write_colour(tmp_path / "rgb" / f"{i}.png", i)
        write_depth_png(tmp_path / "depth" / f"{i}.png", depth * 5)
    (tmp_path / "rgb.txt").write_text("# colour\n")
    got = read_all(f"replay:{tmp_path}?rate=max&scale=5000&{INTR}")
    for frame, depth in zip(got, want, strict=True):
        np.testing.assert_array_equal(frame.depth_mm, depth)


def test_natural_order_puts_2_before_10(tmp_path):
    want = depths(11)
    for i, depth in enumerate(want, 1):
        write_depth_png(tmp_path / f"{i}.png", depth)
    got = read_all(f"replay:{tmp_path}?rate=max&scale=1000&{INTR}")
    for frame, depth in zip(got, want, strict=True):
        np.testing.assert_array_equal(frame.depth_mm, depth)


def test_colour_only_folder_is_one_line_with_a_hint(tmp_path):
    for i in range(3):
        write_colour(tmp_path / f"{i}.png", i)
    Image.fromarray(np.zeros((4, 4), np.uint8)).save(tmp_path / "grey8.png")
    with pytest.raises(RecordingError, match="no 16-bit depth images") as info:
        read_all(f"replay:{tmp_path}?rate=max&scale=1000&{INTR}")
    assert "3 colour and 1 8-bit" in str(info.value) and "glob=" in info.value.hint


def test_glob_picks_the_depth_images(tmp_path):
    want = depths(2)
    for i, depth in enumerate(want):
        write_depth_png(tmp_path / f"{i}_depth.png", depth)
        write_depth_png(tmp_path / f"{i}_ir.png", depth + 7)  # 16-bit too: only a name tells
    got = read_all(f"replay:{tmp_path}?rate=max&scale=1000&glob=*_depth.png&{INTR}")
    for frame, depth in zip(got, want, strict=True):
        np.testing.assert_array_equal(frame.depth_mm, depth)


@pytest.mark.parametrize(
    ("pattern", "says"),
    [("*.tiff", "matches no file"), ("../*.png", "inside the folder"), ("/x/*.png", "inside")],
)
def test_bad_globs_are_one_line_errors(tmp_path, pattern, says):
    write_depth_png(tmp_path / "0.png", depths(1)[0])
    with pytest.raises(RecordingError, match=says):
        read_all(f"replay:{tmp_path}?rate=max&scale=1000&glob={pattern}&{INTR}")


def test_glob_on_a_file_is_refused(tmp_path):
    path = write_depth_png(tmp_path / "0.png", depths(1)[0])
    with pytest.raises(RecordingError, match="not a folder"):
        read_all(f"replay:{path}?glob=*.png")
