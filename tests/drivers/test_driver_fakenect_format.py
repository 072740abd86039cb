"""Disparity <-> millimetres (libfreenect's formula) and the fakenect file layout."""

from __future__ import annotations

import struct

import numpy as np
import pytest

from drivers.base import Frame
from drivers.errors import RecordingError
from drivers.formats.fakenect import (
    PGM_HEADER,
    disparity_to_mm,
    disparity_to_mm_table,
    iter_fakenect,
    mm_to_disparity,
    write_fakenect,
)
from tests.drivers.driverkit import VGA, kinect_exact_frames


def test_table_matches_libfreenect_formula_at_a_hand_computed_point():
    # raw 800 = 4 * const_shift: fixed_ref_x = -0.375, metric = -0.375 * 0.1042 = -0.039075 mm,
    # depth = 10 * (metric * 120 / (7.5 - metric) + 120) = 1193.78 -> truncated to 1193 mm.
    assert int(disparity_to_mm_table()[800]) == 1193


def test_no_reading_both_ways():
    table = disparity_to_mm_table()
    assert table[2047] == 0
    assert mm_to_disparity(np.array([0], np.uint16))[0] == 2047


def test_depth_grows_with_disparity_over_the_valid_range():
    valid = disparity_to_mm_table()[disparity_to_mm_table() > 0].astype(int)
    assert np.all(np.diff(valid) >= 0) and valid[0] < 500 and valid[-1] > 9000


def test_round_trip_is_within_the_quantisation_step():
    table = disparity_to_mm_table().astype(np.int64)
    mm = np.arange(400, 9500, 7, dtype=np.uint16)
    back = disparity_to_mm(mm_to_disparity(mm)).astype(np.int64)
    raw = mm_to_disparity(mm).astype(np.int64)
    step = np.maximum(table[np.minimum(raw + 1, 2046)] - table[np.maximum(raw - 1, 0)], 1)
    assert np.all(np.abs(back - mm.astype(np.int64)) <= step)
    assert np.all(
        np.abs(back - mm.astype(np.int64)) <= np.maximum(0.02 * mm, 2)
    )  # < 2 % out to 9.5 m


def test_written_files_follow_the_fakenect_layout(tmp_path):
    frames = kinect_exact_frames(2)
    write_fakenect(tmp_path / "rec", frames)
    names = (tmp_path / "rec" / "INDEX.txt").read_text().split()
    assert [n[0] for n in names] == ["d", "a", "d", "a"]
    data = (tmp_path / "rec" / names[0]).read_bytes()
    assert data.startswith(PGM_HEADER) and len(data) == len(PGM_HEADER) + 640 * 480 * 2
    raw = np.frombuffer(data, "<u2", offset=len(PGM_HEADER)).reshape(480, 640)
    np.testing.assert_array_equal(disparity_to_mm(raw), frames[0].depth_mm)
    assert len((tmp_path / "rec" / names[1]).read_bytes()) == 12
    x, y, z, _tilt, _status = struct.unpack("<hhhbxi", (tmp_path / "rec" / names[1]).read_bytes())
    assert (x, y) == (0, 810) and z == -117  # (0, -9.7, -1.4) m/s^2 in camera axes


def test_only_vga_can_be_written(tmp_path):
    small = Frame(0, 0.0, np.zeros((48, 64), np.uint16), type(VGA)(64, 48, 60.0, 60.0, 31.5, 23.5))
    with pytest.raises(RecordingError, match="640x480"):
        write_fakenect(tmp_path / "rec", [small])


def test_bad_index_line_names_the_line(tmp_path):
    write_fakenect(tmp_path / "rec", kinect_exact_frames(1))
    (tmp_path / "rec" / "INDEX.txt").write_text("../../etc/passwd\n")
    with pytest.raises(RecordingError, match=r"INDEX.txt:1"):
        list(iter_fakenect(tmp_path / "rec"))
