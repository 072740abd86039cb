"""Mount trust through the real frame loop: a synthetic camera whose configured mount is wrong (the
floor contradicts it, its drop-offs are flagged everywhere), a right one (confirmed, no flag), and
the built-in default that nothing confirms."""

from __future__ import annotations

import json
import logging
import threading
from dataclasses import dataclass, field

import numpy as np
import pytest

from depthnav_daemon.config.loader import build_config
from depthnav_daemon.daemon.loop import _status, run
from depthnav_daemon.pipeline import Result
from depthnav_daemon.pipeline.geometry import Mount
from depthnav_daemon.sim.synthetic import Box, Scene, render, wall
from depthnav_daemon.sinks.base import SinkContext
from depthnav_daemon.sinks.json import message as jsonmsg
from depthnav_daemon.sinks.text import TextSink
from drivers.base import DeviceInfo, Frame
from tests.pipeline.scenes import ASYM_640

TRUE_MOUNT = Mount(0.5, 12.0, 0.0)
# open floor and one box: with the right mount there is no drop-off at all
SCENE = Scene(boxes=(Box(1.6, 0.3, 0.3, 0.3, 0.4),))


@dataclass
class SceneDriver:
    """Renders SCENE from the camera's true mount: what a real camera on the robot would give."""

    mounts: list[Mount]  # the true mount of each frame
    scene: Scene = SCENE
    seq: int = 0

    def open(self) -> DeviceInfo:
        return DeviceInfo("synthetic", None, "synthetic", ASYM_640)

    def read_frame(self, timeout_s: float = 1.0) -> Frame | None:
        if self.seq >= len(self.mounts):
            return None
        view = render(self.scene, ASYM_640, self.mounts[self.seq])
        frame = Frame(self.seq, self.seq / 30.0, view.depth_mm, ASYM_640)
        self.seq += 1
        return frame

    def close(self) -> None:
        pass


@dataclass
class Collect:
    name: str = "collect"
    results: list[tuple[Frame, Result]] = field(default_factory=list)

    def open(self, context: SinkContext) -> None:
        pass

    def write(self, frame: Frame, result: Result) -> None:
        self.results.append((frame, result))

    def close(self) -> None:
        pass


def run_scene(
    *sets: str, frames: int = 3, mounts: list[Mount] | None = None, scene: Scene = SCENE
) -> Collect:
    sink = Collect()
    cfg = build_config([], list(sets), {"device": "synthetic"})
    driver = SceneDriver(mounts or [TRUE_MOUNT] * frames, scene)
    report = run(
        cfg, threading.Event(), driver_factory=lambda _s: driver, sink_factory=lambda _s: sink
    )
    assert report.frames == len(driver.mounts)
    return sink


def message(frame: Frame, result: Result) -> dict:
    return json.loads(jsonmsg.dumps(jsonmsg.frame_message(frame, result, "0", 1.0)))


def test_a_wrong_pinned_mount_is_contradicted_and_its_dropoffs_flagged(caplog) -> None:
    # configured 0.2 m too low: the floor lies 0.2 m below where the daemon expects it, so the
    # cliff stage sees a drop-off on every bearing
    with caplog.at_level(logging.WARNING):
        sink = run_scene("mount.height_m=0.3", "mount.tilt_deg=12.0", "daemon.tilt_source='config'")
    frame, result = sink.results[-1]
    trust = result.mount_trust
    assert trust is not None
    assert (trust.source, trust.pinned, trust.floor) == ("config", True, "contradicted")
    assert trust.floor_height_m == pytest.approx(TRUE_MOUNT.height_m, abs=0.02)
    assert trust.floor_tilt_deg == pytest.approx(TRUE_MOUNT.tilt_deg, abs=1.0)
    assert result.mount.height_m == pytest.approx(0.3)  # pinned: the floor does not replace it
    assert not trust.dropoffs_trusted and result.warning == trust.note
    assert "floor says height 0.50 m" in trust.note and "not trusted" in trust.note
    assert result.cliff is not None and len(result.cliff.points_m) > 50  # the false drop-offs
    msg = message(frame, result)
    assert msg["mount"]["floor"] == "contradicted" and msg["mount"]["source"] == "config"
    assert msg["mount"]["floor_height_m"] == pytest.approx(0.5, abs=0.02)
    assert msg["mount"]["dropoffs_trusted"] is False and msg["cliff"]["trusted"] is False
    assert msg["warning"] == trust.note
    line = TextSink().format(frame, result)
    assert "(config, pinned, floor contradicted)" in line and "drop-off UNTRUSTED" in line
    assert _status(30.0, result) == (
        "30.0 frames/s, mount 0.300 m, tilt 12.0 deg, roll 0.0 deg "
        "(config, pinned, floor contradicted); drop-offs NOT trusted"
    )
    # said once on the terminal, not once per frame
    notes = [r for r in caplog.records if "drop-offs are not trusted" in r.getMessage()]
    assert len(notes) == 1


@pytest.mark.parametrize("tilt_source", ["auto", "config"])
def test_a_right_mount_is_confirmed_and_not_flagged(tilt_source: str) -> None:
    sink = run_scene(
        "mount.height_m=0.5", "mount.tilt_deg=12.0", f"daemon.tilt_source='{tilt_source}'"
    )
    for frame, result in sink.results:
        trust = result.mount_trust
        assert trust is not None and trust.floor == "confirmed" and trust.dropoffs_trusted
        assert trust.floor_height_m is None and trust.note is None and result.warning is None
        msg = message(frame, result)
        assert msg["mount"]["floor"] == "confirmed" and msg["cliff"]["trusted"] is True
        assert msg["warning"] is None
        assert len(result.cliff.points_m) == 0  # the test scene has no drop-off
        assert "UNTRUSTED" not in TextSink().format(frame, result)
        assert _status(30.0, result).endswith("floor confirmed)")
    assert sink.results[-1][1].mount_trust.source == (
        "floor" if tilt_source == "auto" else "config"
    )


def test_the_unconfirmed_default_mount_is_not_trusted() -> None:
    # UC3M's living room in miniature: a camera 1.0 m high, level, a wall 2.8 m ahead leaves too
    # little floor for an estimate on every frame (the wide search of an unconfigured mount finds
    # the wall, a "floor" seen from 84 deg down, beyond its 80 deg), no tilt sensor, no [mount]:
    # the built-in 0.5 m makes the floor beyond 2.5 m a drop-off
    sink = run_scene(
        "daemon.pose_every_frames=1",
        mounts=[Mount(1.0, 0.0, 0.0)] * 3,
        scene=Scene(boxes=(wall(2.8),)),
    )
    for frame, result in sink.results:
        assert result.pose is not None and not result.pose.ok
        trust = result.mount_trust
        assert (trust.source, trust.floor, trust.dropoffs_trusted) == ("default", "unknown", False)
        assert trust.trusted is False  # the mount is unconfirmed: every range is unknown
        assert np.isnan(result.scan.ranges).all() and np.isnan(result.cliff.scan.ranges).all()
        # the drop-offs' floor points stay, flagged untrusted
        assert result.mount.height_m == 0.5 and len(result.cliff.points_m) > 100
        assert "not configured" in result.warning and "unconfirmed" in result.warning
        msg = message(frame, result)
        assert msg["cliff"]["trusted"] is False and msg["mount"]["source"] == "default"
        assert msg["mount"]["trusted"] is False and msg["scan"]["trusted"] is False
        assert set(msg["scan"]["ranges"]) == {None}
        assert "(default, floor unknown)" in TextSink().format(frame, result)
    # the same with no floor estimate at all
    sink = run_scene("daemon.pose_every_frames=0")
    trust = sink.results[-1][1].mount_trust
    assert (trust.source, trust.floor, trust.dropoffs_trusted) == ("default", "unknown", False)
    # the built-in values pinned on purpose (tilt_source = "config") count as configured
    sink = run_scene("daemon.pose_every_frames=0", "daemon.tilt_source='config'")
    trust = sink.results[-1][1].mount_trust
    assert (trust.source, trust.pinned, trust.dropoffs_trusted) == ("config", True, True)
    # a configured mount the floor has not checked yet is trusted
    sink = run_scene("daemon.pose_every_frames=0", "mount.height_m=0.5", "mount.tilt_deg=12.0")
    trust = sink.results[-1][1].mount_trust
    assert (trust.source, trust.floor, trust.dropoffs_trusted) == ("config", "unknown", True)
    # with the floor estimate on, the default is replaced by the floor's mount and confirmed
    sink = run_scene()
    trust = sink.results[0][1].mount_trust
    assert (trust.source, trust.floor, trust.dropoffs_trusted) == ("floor", "confirmed", True)


def test_a_moved_sensor_is_contradicted_until_the_jump_is_accepted(caplog) -> None:
    moved = Mount(0.7, 12.0, 0.0)  # someone raised the sensor by 0.2 m after 2 frames
    with caplog.at_level(logging.INFO):
        sink = run_scene(
            "daemon.pose_every_frames=1",
            "daemon.jump_confirmations=3",
            mounts=[TRUE_MOUNT] * 2 + [moved] * 4,
        )
    floors = [r.mount_trust.floor for _, r in sink.results]
    # frames 2 and 3 hold the jump back (contradicted); the 3rd agreeing estimate (frame 4) is
    # accepted and confirms the moved mount
    assert floors == ["confirmed"] * 2 + ["contradicted"] * 2 + ["confirmed"] * 2
    # the accepted jump is applied from the first frame after its tables exist (built on a
    # worker, daemon/stage_tables.py: the frames go on with the old mount meanwhile, and their
    # drop-offs, resting on the old mount, are not trusted)
    used = [round(r.mount.height_m, 1) for _, r in sink.results]
    assert used[:4] == [0.5] * 4 and used[4:] in ([0.5, 0.5], [0.5, 0.7], [0.7, 0.7])
    wanted = [0.5] * 4 + [0.7] * 2
    trusted = [r.mount_trust.dropoffs_trusted for _, r in sink.results]
    assert trusted == [
        f == "confirmed" and u == w for f, u, w in zip(floors, used, wanted, strict=True)
    ]
    pending = [r.mount_trust.note for _, r in sink.results if r.mount_trust.floor == "confirmed"]
    assert all(n is None or "pending" in n for n in pending)
    if trusted[-1]:
        assert any("trusted again" in r.getMessage() for r in caplog.records)


def test_a_merge_is_as_trusted_as_its_least_trusted_sensor() -> None:
    from dataclasses import replace

    from depthnav_daemon.daemon.multi import Merger
    from depthnav_daemon.pipeline.merge import SensorState

    sink = run_scene("mount.height_m=0.5", "mount.tilt_deg=12.0", frames=1)
    frame, good = sink.results[0]
    doubtful = replace(
        good.mount_trust, floor="contradicted", dropoffs_trusted=False, note="the floor says..."
    )
    bad = replace(good, mount_state=replace(good.mount_state, trust=doubtful))
    merger = Merger(["left", "right"], 1.0)
    states = [SensorState("left", "ok", 0.0, good), SensorState("right", "ok", 0.0, bad)]
    merged = merger.merged(good, states)
    assert merged.mount_trust == doubtful
    assert message(frame, merged)["cliff"]["trusted"] is False
    # with the doubtful sensor out of the merge (stale), the merge is trusted again
    states[1] = SensorState("right", "stale", 5.0, bad)
    assert merger.merged(good, states).mount_trust == good.mount_trust


def test_a_frame_served_with_the_old_mount_while_tables_build_is_not_trusted() -> None:
    from depthnav_daemon.daemon.frame_step import _pending
    from depthnav_daemon.pipeline import MountTrust

    confirmed = MountTrust(source="floor", floor="confirmed")
    wanted = Mount(0.7, 12.0, 0.0)
    assert _pending(confirmed, wanted, wanted) is confirmed
    assert _pending(confirmed, Mount(0.705, 12.2, 0.1), wanted) is confirmed  # within the deadband
    held = _pending(confirmed, TRUE_MOUNT, wanted)
    assert not held.dropoffs_trusted and held.floor == "confirmed"
    assert "pending" in held.note and "0.50 m" in held.note and "0.70 m" in held.note


def test_the_verdict_is_made_once_and_anew_when_what_it_rests_on_changes() -> None:
    from depthnav_daemon.daemon.mount_tracker import MountTracker, TrackerParams

    tracker = MountTracker(TRUE_MOUNT, TrackerParams())
    first = tracker.trust()
    assert tracker.trust() is first  # nothing changed: the same frozen verdict
    tracker.check_floor(0.9, 30.0, 0.0)  # the floor contradicts the mount
    contradicted = tracker.trust()
    assert contradicted.floor == "contradicted" and contradicted.floor_height_m == 0.9
    assert tracker.trust() is contradicted
    tracker.mount = Mount(0.6, 12.0, 0.0)  # the mount in use moved: its note names the new one
    assert "0.60 m" in (tracker.trust().note or "")
    tracker.check_floor(0.6, 12.0, 0.0)
    assert tracker.trust().floor == "confirmed" and tracker.trust().dropoffs_trusted
    tracker.from_floor(0.6, 12.0, 0.0)  # the source changes to the floor
    assert tracker.trust().source == "floor"
