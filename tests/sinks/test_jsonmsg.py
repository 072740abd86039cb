"""The JSON message: strict JSON, REP 117 values kept apart, fields as documented."""

from __future__ import annotations

import json
import math
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from depthnav_daemon.pipeline import MountTrust
from depthnav_daemon.pipeline.pose import PoseEstimate
from depthnav_daemon.sinks.json import line as json_line
from depthnav_daemon.sinks.json import message as jsonmsg
from tests.sinks.conftest import make_pair, with_memory, with_ranges


def test_special_ranges_round_trip_distinct(pairs):
    frame, result = pairs[0]
    ranges = result.scan.ranges.copy()
    ranges[:4] = [np.nan, np.inf, -np.inf, 1.23456]
    result = with_ranges(result, ranges)
    line = jsonmsg.dumps(jsonmsg.frame_message(frame, result, "9.9", 1.0))
    assert "NaN" not in line and "Infinity," not in line.replace('"Infinity"', "")
    msg = json.loads(line)  # strict parsers (JS JSON.parse) accept it: no bare NaN/Infinity tokens
    assert msg["scan"]["ranges"][:4] == [None, "Infinity", "-Infinity", 1.235]
    back = jsonmsg.decode_ranges(msg["scan"]["ranges"])
    want = ranges.astype(np.float64)
    assert np.array_equal(np.isnan(back), np.isnan(want))
    assert np.array_equal(np.isposinf(back), np.isposinf(want))
    assert np.array_equal(np.isneginf(back), np.isneginf(want))
    fin = np.isfinite(want)
    assert np.max(np.abs(back[fin] - want[fin])) <= 0.0005 + 1e-9  # rounded to 1 mm


def test_python_float_reads_the_inf_strings():
    # the documented consumer recipe: float(v) for numbers and the two strings, None -> NaN
    assert float(jsonmsg.POS_INF) == math.inf and float(jsonmsg.NEG_INF) == -math.inf


@settings(max_examples=60, deadline=None)
@given(
    st.lists(
        st.one_of(
            st.floats(0.0, 100.0, width=32),
            st.just(math.nan),
            st.just(math.inf),
            st.just(-math.inf),
        ),
        max_size=200,
    )
)
def test_encode_decode_property(values):
    r = np.asarray(values, dtype=np.float32)
    enc = jsonmsg.encode_ranges(r)
    back = jsonmsg.decode_ranges(json.loads(json.dumps(enc, allow_nan=False)))
    want = r.astype(np.float64)
    assert back.shape == want.shape
    same_special = np.isnan(back) == np.isnan(want)
    assert same_special.all() and (np.isinf(back) == np.isinf(want)).all()
    fin = np.isfinite(want)
    assert np.all(np.abs(back[fin] - want[fin]) <= 0.0005 + 1e-6)
    assert np.all(np.sign(back[np.isinf(want)]) == np.sign(want[np.isinf(want)]))


def test_decode_rejects_unknown_tokens():
    with pytest.raises(ValueError, match="ranges\\[1\\]"):
        jsonmsg.decode_ranges([1.0, "inf"])


def test_fields_and_values(pairs):
    frame, result = pairs[2]  # this frame carries a floor estimate
    msg = json.loads(jsonmsg.dumps(jsonmsg.frame_message(frame, result, "0.1.0", 1795345761.5)))
    assert msg["v"] == 1 and msg["version"] == "0.1.0"
    assert msg["seq"] == 2 and msg["t_s"] == pytest.approx(frame.timestamp_s, abs=1e-6)
    assert msg["wall_s"] == 1795345761.5
    scan = msg["scan"]
    assert set(scan) == {
        "angle_min",
        "angle_max",
        "angle_increment",
        "range_min",
        "range_max",
        "ranges",
        "trusted",
    }
    assert scan["trusted"] is True  # nobody assessed this mount (no trust): nothing to doubt
    assert scan["angle_min"] == pytest.approx(result.scan.angle_min, abs=1e-6)
    assert scan["angle_increment"] == pytest.approx(result.scan.angle_increment, rel=1e-6)
    assert len(scan["ranges"]) == result.scan.ranges.size
    assert scan["range_min"] == 0.4 and scan["range_max"] == 5.0
    pose = msg["pose"]
    assert (
        pose["height_m"] == pytest.approx(0.52)
        and pose["tilt_deg"] == 12.0
        and pose["roll_deg"] == 1.5
    )
    assert pose["source"] == "config"
    assert pose["estimate"] == {
        "ok": True,
        "height_m": 0.52,
        "tilt_deg": 12.0,
        "roll_deg": 1.5,
        "inliers": 900,
        "inlier_ratio": 0.9,
        "residual_m": 0.004,
        "candidates": 1000,
        "reason": "",
    }
    cliff = msg["cliff"]
    assert cliff["points_total"] == len(result.cliff.points_m) > 0 and cliff["points_dropped"] == 0
    assert np.allclose(cliff["points_m"], result.cliff.points_m, atol=0.0006)
    assert len(cliff["scan"]["ranges"]) == result.cliff.scan.ranges.size
    assert msg["timings_s"] == {"cliff": 0.002, "scan": pytest.approx(0.0042)}
    assert msg["warning"] is None and msg["message"] is None


def test_an_unconfirmed_mount_flags_the_scan_and_the_mount(pairs):
    frame, result = pairs[0]
    note = "the mount is not configured (...): mount unconfirmed, every range unknown"
    unknown = MountTrust(source="default", dropoffs_trusted=False, trusted=False, note=note)
    nan = np.full_like(result.scan.ranges, np.nan)
    doubtful = replace(
        result,
        scan=replace(result.scan, ranges=nan),
        mount_state=replace(result.mount_state, trust=unknown),
        warning=note,
    )
    msg = json.loads(jsonmsg.dumps(jsonmsg.frame_message(frame, doubtful, "0.1.0", 1.0)))
    assert msg["scan"]["trusted"] is False and set(msg["scan"]["ranges"]) == {None}
    mount = msg["mount"]
    assert (mount["trusted"], mount["dropoffs_trusted"], mount["source"]) == (
        False,
        False,
        "default",
    )
    assert "unconfirmed" in mount["note"] and "unconfirmed" in msg["warning"]
    assert msg["cliff"]["trusted"] is False
    # a known mount whose drop-offs are doubted: the scan stands, the drop-offs are flagged
    contradicted = MountTrust(source="config", floor="contradicted", dropoffs_trusted=False)
    known = replace(result, mount_state=replace(result.mount_state, trust=contradicted))
    msg = json.loads(jsonmsg.dumps(jsonmsg.frame_message(frame, known, "0.1.0", 1.0)))
    assert msg["scan"]["trusted"] is True and msg["mount"]["trusted"] is True
    assert msg["cliff"]["trusted"] is False


def test_no_cliff_and_failed_estimate_are_null_not_nan(pairs):
    frame, result = pairs[0]
    bad = PoseEstimate(
        False, math.nan, math.nan, math.nan, 3, 0.01, math.nan, 300, "too few floor points"
    )
    result = replace(result, cliff=None, mount_state=replace(result.mount_state, pose=bad))
    msg = json.loads(jsonmsg.dumps(jsonmsg.frame_message(frame, result, "0.1.0", 1.0)))
    assert msg["cliff"] is None
    est = msg["pose"]["estimate"]
    assert est["ok"] is False and est["height_m"] is None and est["residual_m"] is None
    assert est["reason"] == "too few floor points"


def test_fit_message_caps_cliff_points_nearest_first(pairs):
    frame, result = pairs[0]
    rng = np.random.default_rng(1)
    pts = rng.uniform([0.5, -3.0], [5.0, 3.0], size=(6000, 2)).astype(np.float32)
    pts[17] = [0.6, 0.0]  # the nearest drop-off must survive the cap
    cliff = replace(result.cliff, points_m=pts, blocks=np.zeros((6000, 2), np.int64))
    result = replace(result, cliff=cliff)
    full = jsonmsg.dumps(jsonmsg.frame_message(frame, result, "0.1.0", 1.0)).encode()
    assert len(full) > 20000
    data = json_line.fit_message(frame, result, "0.1.0", 1.0, 20000)
    assert data is not None and len(data) <= 20000
    msg = json.loads(data)
    kept = np.asarray(msg["cliff"]["points_m"])
    assert 0 < len(kept) < 6000
    assert msg["cliff"]["points_total"] == 6000
    assert msg["cliff"]["points_dropped"] == 6000 - len(kept)
    assert "capped" in msg["message"]
    dist_kept = np.hypot(kept[:, 0], kept[:, 1])
    assert [0.6, 0.0] in kept.tolist()
    dropped_min = np.sort(np.hypot(pts[:, 0], pts[:, 1]))[len(kept)]
    assert (
        dist_kept.max() <= dropped_min + 0.001
    )  # every kept point is nearer than every dropped one
    # a message that cannot fit even without cliff points is refused
    assert json_line.fit_message(frame, result, "0.1.0", 1.0, 600) is None


def test_each_frame_is_one_line(pairs):
    frame, result = make_pair(7, warning="two\nlines")
    line = jsonmsg.dumps(jsonmsg.frame_message(frame, result, "0.1.0", 1.0))
    assert "\n" not in line and json.loads(line)["warning"] == "two\nlines"


def _keys(obj, prefix=""):
    """Every dotted key path in a JSON object (lists: their first element)."""
    out = set()
    if isinstance(obj, dict):
        for k, v in obj.items():
            out.add(prefix + k)
            out |= _keys(v, prefix + k + ".")
    elif isinstance(obj, list) and obj and isinstance(obj[0], (dict, list)):
        out |= _keys(obj[0], prefix)
    return out


def test_documented_example_has_exactly_the_real_fields(pairs):
    doc = (Path(__file__).resolve().parents[2] / "docs" / "json_schema.md").read_text()
    block = doc.split("```json", 1)[1].split("```", 1)[0]
    example = json.loads(block.replace("\n", ""))
    frame, result = pairs[2]  # a frame with cliff and a floor estimate
    result = with_memory(result)  # and the obstacle memory on
    confirmed = MountTrust(source="config", floor="confirmed")
    result = replace(result, mount_state=replace(result.mount_state, trust=confirmed))
    real = json.loads(jsonmsg.dumps(jsonmsg.frame_message(frame, result, "0.1.0", 1.0)))

    def fixed(keys: set[str]) -> set[str]:
        return {k for k in keys if not k.startswith("timings_s.")}  # one key per stage that ran

    assert fixed(_keys(example)) == fixed(_keys(real))
    assert jsonmsg.decode_ranges(example["scan"]["ranges"]).tolist()[:3] == [
        pytest.approx(math.nan, nan_ok=True),
        math.inf,
        2.346,
    ]


def test_the_mount_parts_made_once_follow_every_change_and_are_not_shared(pairs):
    frame, result = pairs[0]
    trusted = MountTrust(source="config", floor="confirmed")
    first = replace(result, mount_state=replace(result.mount_state, trust=trusted))
    jsonmsg.frame_message(frame, first, "0.1.0", 1.0)  # makes the parts
    msg = jsonmsg.frame_message(frame, first, "0.1.0", 1.0)  # reuses them
    # a caller changing its message changes no later frame's (the parts are made once)
    msg["mount"]["source"] = "changed"
    msg["pose"]["height_m"] = -1.0
    again = jsonmsg.frame_message(frame, first, "0.1.0", 1.0)
    assert again["mount"]["source"] == "config" and again["pose"]["height_m"] == 0.5
    # a new verdict (another object) and a new mount are written anew
    doubt = MountTrust(
        source="config", floor="contradicted", floor_height_m=0.9, dropoffs_trusted=False
    )
    moved_mount = replace(first.mount, height_m=0.61)
    moved = replace(first, mount_state=replace(first.mount_state, trust=doubt, mount=moved_mount))
    later = jsonmsg.frame_message(frame, moved, "0.1.0", 1.0)
    assert later["mount"]["floor"] == "contradicted" and later["mount"]["floor_height_m"] == 0.9
    assert later["pose"]["height_m"] == 0.61
    # another source with the same mount object as the last frame's
    jsonmsg.frame_message(frame, first, "0.1.0", 1.0)
    other = replace(first, mount_state=replace(first.mount_state, source="floor"))
    assert jsonmsg.frame_message(frame, other, "0.1.0", 1.0)["pose"]["source"] == "floor"
