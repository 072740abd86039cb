"""The JSON line written from a template (json_line._line) is the message's line, byte for byte:
``orjson.dumps(jsonmsg.frame_message(...))`` and a newline, for every kind of frame the daemon
sends."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import orjson
import pytest

from depthnav_daemon.pipeline import MountTrust
from depthnav_daemon.pipeline.merge import SensorState
from depthnav_daemon.sinks.json import line as json_line
from depthnav_daemon.sinks.json import message as jsonmsg
from tests.sinks.conftest import with_memory

DOUBT = MountTrust(
    source="default",
    floor="contradicted",
    floor_height_m=0.61234,
    floor_tilt_deg=14.56789,
    floor_roll_deg=-0.5,
    dropoffs_trusted=False,
    note="the floor says 0.612 m, 14.6 deg",
)


def _variants(pairs):
    """(name, frame, result): the kinds of frames a daemon sends."""
    frame, result = pairs[1]
    _, with_pose = pairs[2]  # this frame's floor estimate
    _, warned = pairs[3]
    cliff = result.cliff
    assert cliff is not None and with_pose.pose is not None and warned.warning
    special = result.scan.ranges.copy()
    special[:4] = [np.nan, np.inf, -np.inf, -0.0]
    yield "plain", frame, result
    yield "floor estimate", frame, with_pose
    yield "warning", frame, warned
    yield "no cliff stage", frame, replace(result, cliff=None)
    yield "special ranges", frame, replace(result, scan=replace(result.scan, ranges=special))
    yield (
        "no cliff points",
        frame,
        replace(result, cliff=replace(cliff, points_m=np.zeros((0, 2), np.float32))),
    )
    trusted = replace(result.mount_state, trust=MountTrust(floor="confirmed"))
    yield "trusted", frame, replace(result, mount_state=trusted)
    doubtful = replace(result.mount_state, trust=DOUBT)
    yield "not trusted", frame, replace(result, mount_state=doubtful, warning=DOUBT.note)
    yield "memory", frame, with_memory(result)
    yield (
        "more timings",
        frame,
        replace(
            result, timings_s={"scan": 0.0012345, "pose": 0.0009, "cliff": 5.5e-05, "memory": 1e-9}
        ),
    )
    yield "control characters", frame, replace(warned, warning="a\x01b\x02c\x03d\x04\n")
    yield "one timing", frame, replace(result, timings_s={"scan": 0.5})
    yield "no timings", frame, replace(result, timings_s={})
    yield (
        "float64 ranges",
        frame,
        replace(result, scan=replace(result.scan, ranges=result.scan.ranges.astype(np.float64))),
    )


def test_the_line_from_text_is_the_messages_line(pairs) -> None:
    for name, frame, result in _variants(pairs):
        line = json_line._line(result, "1.2.3", 1796194456.0331335)
        assert line is not None, name  # every one of these takes the text path
        want = orjson.dumps(jsonmsg.frame_message(frame, result, "1.2.3", 1796194456.0331335))
        assert line == want + b"\n", name


def test_the_cached_pieces_follow_the_mount_and_the_trust(pairs) -> None:
    """The pose and trust texts are kept per object: a new mount or verdict is a new text."""
    (f0, r0), (f1, r1) = pairs[0], pairs[1]
    assert r0.mount != r1.mount  # the pairs' mount height changes frame to frame
    for trust in (MountTrust(floor="confirmed"), DOUBT, MountTrust(floor="confirmed")):
        for frame, result in ((f0, r0), (f1, r1), (f0, r0)):
            res = replace(result, mount_state=replace(result.mount_state, trust=trust))
            want = orjson.dumps(jsonmsg.frame_message(frame, res, "1", 2.0))
            assert json_line._line(res, "1", 2.0) == want + b"\n"


def test_what_text_cannot_make_goes_through_the_message(pairs) -> None:
    """Several sensors, cliff points the kernel cannot write (not finite), a timing that is not a
    number or a time too large to round exactly: the message's own dicts make the line, which is
    still the message's line."""
    frame, result = pairs[1]
    assert result.cliff is not None
    bad = np.array(result.cliff.points_m, dtype=np.float32)
    bad[0] = [np.nan, 1.0]
    sensors = (SensorState("left", "ok", 0.01, result), SensorState("right", "stale", 0.9, None))
    for res in (
        replace(result, cliff=replace(result.cliff, points_m=bad)),
        replace(result, sensors=sensors),
        replace(result, timings_s={"scan": None, "cliff": 0.001}),
        replace(result, timestamp_s=2.0**33),
    ):
        assert json_line._line(res, "1", 2.0) is None
        line = json_line.frame_line(frame, res, "1", 2.0)
        assert line == orjson.dumps(jsonmsg.frame_message(frame, res, "1", 2.0)) + b"\n"
        assert json_line.frame_json(frame, res, "1", 2.0) == line[:-1]


@pytest.mark.parametrize("n_bins", [1, 640, 4000])
def test_the_kept_buffer_grows_and_the_texts_stay_apart(pairs, n_bins: int) -> None:
    """The buffer the lists are written into is kept between calls: a longer scan after a short
    one grows it, and a line made earlier is not changed by a later one."""
    frame, result = pairs[1]
    rng = np.random.default_rng(n_bins)
    ranges = rng.uniform(0.4, 5.0, n_bins).astype(np.float32)
    res = replace(result, scan=replace(result.scan, ranges=ranges))
    first = json_line._line(res, "1", 2.0)
    again = json_line._line(replace(result, cliff=None), "1", 2.0)  # reuses the buffer
    assert first == orjson.dumps(jsonmsg.frame_message(frame, res, "1", 2.0)) + b"\n"
    assert again != first and len(orjson.loads(first)["scan"]["ranges"]) == n_bins


def test_a_plain_frame_reuses_the_last_template(pairs, monkeypatch: pytest.MonkeyPatch) -> None:
    """Frames that differ only in their numbers (the daemon's usual frame) make their template
    once; each line is still the message's."""
    frame, result = pairs[1]
    built = []
    new_shape = json_line._new_shape
    monkeypatch.setattr(json_line, "_last_shape", None)
    monkeypatch.setattr(
        json_line, "_new_shape", lambda *args: built.append(args[0]) or new_shape(*args)
    )
    rng = np.random.default_rng(5)
    for seq in range(6):
        res = replace(
            result,
            seq=seq,
            timestamp_s=1000.0 + seq / 30,
            scan=replace(result.scan, ranges=rng.uniform(0.5, 4.0, 640).astype(np.float32)),
            timings_s={"scan": 0.001 * seq, "cliff": 5e-5},
        )
        want = orjson.dumps(jsonmsg.frame_message(frame, res, "1", 2.0 + seq)) + b"\n"
        assert json_line._line(res, "1", 2.0 + seq) == want
    assert len(built) == 1


def test_the_kept_template_follows_what_it_is_made_of(pairs) -> None:
    """Each thing the template is made of, changed alone, makes a new one, and the next plain
    frame its own again."""
    frame, flat = pairs[1]
    assert flat.cliff is not None and flat.pose is None and flat.warning is None
    assert flat.mount_source != "serial" and flat.mount_trust != DOUBT
    cliff = flat.cliff
    variants = []
    for field in ("angle_min", "angle_max", "angle_increment", "range_min", "range_max"):
        for name, scan in (("scan", flat.scan), ("cliff scan", cliff.scan)):
            moved = replace(scan, **{field: getattr(scan, field) + 0.0123})
            res = (
                replace(flat, scan=moved)
                if name == "scan"
                else replace(flat, cliff=replace(cliff, scan=moved))
            )
            variants.append((f"{name} {field}", "1", res))
    variants += [
        (
            "mount",
            "1",
            replace(
                flat,
                mount_state=replace(flat.mount_state, mount=replace(flat.mount, height_m=0.734)),
            ),
        ),
        ("source", "1", replace(flat, mount_state=replace(flat.mount_state, source="serial"))),
        ("verdict", "1", replace(flat, mount_state=replace(flat.mount_state, trust=DOUBT))),
        ("timing order", "1", replace(flat, timings_s={"cliff": 2e-4, "scan": 0.002})),
        ("timing keys", "1", replace(flat, timings_s={"scan": 0.002})),
        ("version", "2.0", flat),
    ]
    for name, version, res in variants:
        for v, r in ((version, res), ("1", flat)):
            want = orjson.dumps(jsonmsg.frame_message(frame, r, v, 3.5)) + b"\n"
            assert json_line._line(r, v, 3.5) == want, name
