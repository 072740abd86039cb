"""The compiled JSON writer of ranges and points: the same bytes as the reference encoder
(``jsonmsg.encode_ranges`` + orjson, ``np.round(points, 3).tolist()`` + orjson), one line per
frame shared by the sinks."""

from __future__ import annotations

import json
import math
from dataclasses import replace

import numpy as np
import orjson
import pytest

from depthnav_daemon.sinks.json import line as json_line
from depthnav_daemon.sinks.json import message as jsonmsg
from depthnav_daemon.sinks.json.numbers import (
    _TEXTS,
    CHARS_PER_VALUE,
    TABLE_K,
    _write_lists,
    lists_json,
    mm_json,
)
from tests.sinks.conftest import with_ranges


def reference(values: np.ndarray) -> bytes:
    return orjson.dumps(jsonmsg.encode_ranges(values))


def test_a_pinned_list() -> None:
    r = np.array([math.nan, math.inf, -math.inf, 1.23456, 0.0004, 2.5, 12.0, -0.0001, 0.1])
    want = b'[null,"Infinity","-Infinity",1.235,0.0,2.5,12.0,-0.0,0.1]'
    assert mm_json(r) == want == reference(r)
    assert mm_json(np.zeros(0)) == b"[]" == reference(np.zeros(0))


def pairs_reference(points: np.ndarray) -> bytes:
    return orjson.dumps(np.round(np.asarray(points, np.float64), 3).tolist())


def test_the_table_holds_the_text_of_every_millimetre_below_100_m() -> None:
    """Entry k of the table: the text of k / 1000 as Python (and orjson) write that float, a
    comma, and its length in the top byte."""
    assert TABLE_K == 100_000 and _TEXTS.dtype == np.uint64 and _TEXTS.shape == (TABLE_K,)
    rows = _TEXTS.astype("<u8").view(np.uint8).reshape(-1, 8)
    for k in range(TABLE_K):
        text = (repr(k / 1000) + ",").encode()
        assert rows[k, 7] == len(text) and rows[k, : len(text)].tobytes() == text, k


BOUNDARIES = [
    0.0, -0.0, 0.0004, 0.0005, 0.0015, -0.0004, -0.0005, 0.001, 0.999, 0.9995, 1.0,
    9.999, 9.9994, 9.9995, 10.0, 10.001, 99.0, 99.999, 99.9994, 99.99949, 99.9995, 99.9996,
    100.0, 100.0004, 100.0005, 100.001, 100.999, 101.0, 999.9995, 1000.0, 12345.678,
    999_999_999_999.999, 0.1, 1e-300, 5e-324,
]  # fmt: skip


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_values_at_the_bounds_of_the_table_and_of_rounding(dtype: type) -> None:
    """0.0005 rounds as np.round does, -0.0004 is "-0.0", 99.9995 leaves the table (100.0 m and
    beyond are written digit by digit), and each with either sign, flat and as pairs."""
    v = np.array(BOUNDARIES + [-b for b in BOUNDARIES], dtype)
    assert mm_json(v) == reference(v)
    assert mm_json(v[::-1]) == reference(v[::-1])
    pts = v.reshape(-1, 2)
    assert mm_json(pts, pairs=True) == pairs_reference(pts)
    assert lists_json(v, pts, v[::-1]) == (reference(v), pairs_reference(pts), reference(v[::-1]))
    for x in v:  # one at a time: each a list of its own
        assert mm_json(np.array([x], dtype)) == reference(np.array([x], dtype)), x
    # as np.round rounds: half to even for the float64 0.0005 (0.5 mm), while the float32 nearest
    # 0.0005 lies above it and the one nearest 99.9995 below
    pinned = mm_json(np.array([0.0005, -0.0004, 9.9995, 99.9995, -99.999, 100.0], dtype))
    if dtype == np.float64:
        assert pinned == b"[0.0,-0.0,10.0,100.0,-99.999,100.0]"
    else:
        assert pinned == b"[0.001,-0.0,10.0,99.999,-99.999,100.0]"


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_every_entry_of_the_table_and_the_values_rounded_into_it(dtype: type) -> None:
    """Every millimetre below the table's end (and a little beyond), and values up to 0.4 mm
    either side of it, of either sign: flat, as pairs, and all three lists of one call."""
    k = np.arange(TABLE_K + 1001)
    for offset in (0.0, 0.0004, -0.0004):
        v = (k / 1000 + offset).astype(dtype)
        for sign in (1, -1):
            flat = sign * v
            assert mm_json(flat) == reference(flat), (offset, sign)
            pts = flat[: flat.size // 2 * 2].reshape(-1, 2)
            texts = lists_json(flat[:5000], pts, flat[-5000:])
            assert texts == (
                reference(flat[:5000]),
                pairs_reference(pts),
                reference(flat[-5000:]),
            ), (offset, sign)


@pytest.mark.parametrize("size", [0, 1, 2, 3, 2000])
def test_the_longest_texts_stay_within_the_buffer(size: int) -> None:
    """Lists of nothing but the longest texts (-999999999999.999, "-Infinity"), flat and as
    pairs: the kernel's fixed 8-byte stores stay within the buffer lists_json gives it (a guard
    after it stays untouched), and the text is the reference's."""
    empty = np.zeros(0)
    longest = np.full(size, -999_999_999_999.999)
    cases = [
        (longest, empty, empty),
        (empty, longest, empty),
        (empty, empty, np.full(size, -math.inf)),
        (longest, longest, longest),
    ]
    for lists in cases:
        room = CHARS_PER_VALUE * sum(a.size for a in lists) + 12  # as lists_json allocates
        buffer = np.full(2 * room + 64, 0xAB, np.uint8)  # a guard as long: a clean failure
        n, a, b = _write_lists(*lists, _TEXTS, buffer[:room])
        assert 0 < n <= room and (buffer[room:] == 0xAB).all(), size
        text = buffer[:n].tobytes()
        pairs = lists[1][: size // 2 * 2].reshape(-1, 2)
        if size % 2 == 0:
            assert text[a:b] == pairs_reference(pairs)
        assert text[:a] == reference(lists[0]) and text[b:] == reference(lists[2])
    assert mm_json(np.array([1e12])) is None  # k = 1e15: the reference path's
    assert mm_json(np.array([-999_999_999_999.9994])) == b"[-999999999999.999]"


def test_an_odd_count_of_pair_values_and_lists_not_given() -> None:
    """The kernel's pairs list holds a last pair of one value for an odd count, and the lists
    not given are "[]" (as the writer wrote them before the table)."""
    assert lists_json(np.zeros(0), np.array([1.0, 2.0, 3.0])) == (
        b"[]",
        b"[[1.0,2.0],[3.0]]",
        b"[]",
    )
    assert lists_json(np.array([1.5])) == (b"[1.5]", b"[]", b"[]")
    assert lists_json(np.array([1.5], np.float32), None, [2.25]) == (b"[1.5]", b"[]", b"[2.25]")
    assert mm_json(np.array([np.copysign(math.nan, -1.0), -math.inf])) == b'[null,"-Infinity"]'
    assert lists_json(np.zeros(0), np.array([[1.0, math.inf]])) is None


def test_every_millimetre_up_to_2_km_is_written_as_orjson_writes_it() -> None:
    v = np.arange(0, 2_000_001) / 1000.0
    assert mm_json(v) == reference(v)
    assert mm_json(-v) == reference(-v)


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_random_arrays_with_every_special_value(dtype: type) -> None:
    rng = np.random.default_rng(7)
    fallbacks = 0
    for trial in range(300):
        n = int(rng.integers(0, 700))
        top = 13.0 if trial % 4 == 0 else 11.5  # 1e13 m: beyond what the kernel writes
        v = 10.0 ** rng.uniform(-6, top, n) * rng.choice([-1.0, 1.0], n)
        kind = rng.random(n)
        v[kind < 0.1] = math.nan
        v[(kind >= 0.1) & (kind < 0.2)] = math.inf
        v[(kind >= 0.2) & (kind < 0.25)] = -math.inf
        v[(kind >= 0.25) & (kind < 0.28)] = -0.0
        v[(kind >= 0.28) & (kind < 0.3)] = 0.0
        v = v.astype(dtype)
        got = mm_json(v)
        if got is None:  # a value too large to write exactly: the reference path takes it
            fallbacks += 1
            assert np.nanmax(np.abs(np.where(np.isinf(v), 0, v))) * 1000 >= 1e15 * 0.999
        else:
            assert got == reference(v), trial
        # what the message holds either way
        assert orjson.dumps(jsonmsg.ranges_json(v)) == reference(v)
    assert 0 < fallbacks < 300


def test_points_as_pairs() -> None:
    rng = np.random.default_rng(3)
    for n in (0, 1, 2, 111, 500):
        pts = rng.uniform(-6.0, 6.0, (n, 2))
        want = orjson.dumps(np.round(pts, 3).tolist())
        assert mm_json(pts, pairs=True) == want
        assert orjson.dumps(jsonmsg.points_json(pts)) == want


def test_the_line_is_strict_json_and_decodes(pairs) -> None:
    frame, result = pairs[1]
    ranges = result.scan.ranges.copy()
    ranges[:5] = [np.nan, np.inf, -np.inf, 1.23456, 0.0]
    result = with_ranges(result, ranges)
    line = json_line.frame_json(frame, result, "9.9", 1.0)
    msg = json.loads(line)  # strict: no NaN / Infinity literals
    assert msg["scan"]["ranges"][:5] == [None, "Infinity", "-Infinity", 1.235, 0.0]
    assert line == orjson.dumps(jsonmsg.frame_message(frame, result, "9.9", 1.0))


def test_one_line_per_result_shared_by_the_sinks(pairs) -> None:
    (f0, r0), (f1, r1) = pairs[0], pairs[1]
    first = json_line.frame_line(f0, r0, "1", 1.0)
    assert json_line.frame_line(f0, r0, "1", 2.0) is first  # same frame: the same line (wall_s 1.0)
    assert json.loads(first)["wall_s"] == 1.0 and first.endswith(b"}\n")
    assert json_line.frame_json(f0, r0, "1", 2.0) == first[:-1]
    assert json_line.frame_line(f1, r1, "1", 2.0) != first  # the next frame: a new line
    assert json.loads(json_line.frame_line(f0, r0, "2", 3.0))["version"] == "2"
    # a datagram of the whole object is that line; a reshaped one is built anew
    line = json_line.frame_line(f1, r1, "1", 9.0)
    assert json_line.fit_message(f1, r1, "1", 9.0, 60000) == line[:-1]


def test_udp_mm_ranges_from_the_written_text(pairs) -> None:
    from depthnav_daemon.sinks.json.udp import Content

    frame, result = pairs[0]
    data = json_line.fit_message(frame, result, "1", 1.0, 60000, Content(ranges_mm=True).shape)
    assert data is not None
    got = json.loads(data)["scan"]["ranges"]
    want = jsonmsg.encode_ranges(result.scan.ranges)
    assert got == [round(v * 1000) if isinstance(v, float) else v for v in want]


def test_the_line_written_in_one_kernel_call_is_the_reference_encoders_line(pairs) -> None:
    """Both scans and the cliff points come from one kernel call: the line is the one the
    reference encoders make, with special ranges, non-finite or no cliff points, and no cliff."""
    frame, result = pairs[2]
    assert result.cliff is not None and len(result.cliff.points_m) > 3
    ranges = result.scan.ranges.copy()
    ranges[:4] = [np.nan, np.inf, -np.inf, -0.0]
    special = with_ranges(result, ranges)
    cliff = result.cliff
    bad_pts = np.array(cliff.points_m, dtype=np.float32)
    bad_pts[1] = [np.nan, 1.0]
    cliff_ranges = np.array(cliff.scan.ranges, dtype=np.float32)
    cliff_ranges[-3:] = [np.nan, -np.inf, 123.4567]
    cases = [
        result,
        special,
        replace(result, cliff=replace(cliff, points_m=bad_pts)),
        replace(result, cliff=replace(cliff, points_m=np.zeros((0, 2), np.float32))),
        replace(result, cliff=replace(cliff, scan=replace(cliff.scan, ranges=cliff_ranges))),
        replace(result, cliff=None),
    ]
    for i, res in enumerate(cases):
        want = jsonmsg.frame_message(frame, res, "1", 5.0)
        want["scan"]["ranges"] = jsonmsg.encode_ranges(res.scan.ranges)
        if res.cliff is not None:
            pts = np.asarray(res.cliff.points_m, dtype=np.float64).reshape(-1, 2)
            finite = pts[np.isfinite(pts).all(axis=1)]
            want["cliff"]["points_m"] = np.round(finite, 3).tolist()
            want["cliff"]["points_total"] = len(pts)
            want["cliff"]["points_dropped"] = len(pts) - len(finite)
            want["cliff"]["scan"]["ranges"] = jsonmsg.encode_ranges(res.cliff.scan.ranges)
        assert json_line.frame_json(frame, res, "1", 5.0) == orjson.dumps(want), i


WARM_THEN_WRITE = """
from dataclasses import replace
from depthnav_daemon.sinks.json import line as json_line
from depthnav_daemon.sinks.json.numbers import _write_lists
from depthnav_daemon.sinks.json.template import _write_template
from depthnav_daemon.tools import warmup
from tests.sinks.conftest import make_pair
warmup.warm_up()
before = len(_write_lists.signatures) + len(_write_template.signatures)
frame, result = make_pair(0)
json_line.frame_json(frame, result, "1", 1.0)
json_line.frame_json(frame, replace(result, cliff=None), "1", 1.0)
print(before, len(_write_lists.signatures) + len(_write_template.signatures))
"""


def test_warm_up_compiles_the_writer_for_every_line_the_sinks_write() -> None:
    """In a fresh process: after the warm-up, a frame's line (float32 lists from the stages)
    compiles nothing more (a compile at the first frame stalls it for seconds)."""
    import subprocess
    import sys
    from pathlib import Path

    root = Path(__file__).resolve().parents[2]
    out = subprocess.run(
        [sys.executable, "-c", WARM_THEN_WRITE],
        cwd=root, capture_output=True, text=True, timeout=600, check=True,
    ).stdout.split()  # fmt: skip
    assert len(out) == 2 and int(out[0]) >= 4 and out[0] == out[1], out
