"""The rerun sink writes a real .rrd; rerun's own reader checks entities, counts and values."""

from __future__ import annotations

import contextlib
import os
import signal
import socket
import subprocess
import threading
import time
import warnings
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from depthnav_daemon.errors import ConfigError, SinkError
from depthnav_daemon.pipeline.geometry import rot_x, rot_y
from depthnav_daemon.pipeline.scan import obstacle_pixels
from depthnav_daemon.sinks import create_sink
from depthnav_daemon.sinks.rerun import rerun as rerun_sink
from depthnav_daemon.sinks.rerun.rerun import RerunSink
from tests.drivers.driverkit import skip_without

rrchunk = pytest.importorskip("rerun.chunk")


@pytest.fixture(autouse=True)
def offline_rerun(tmp_path, monkeypatch):
    """Keep rerun's config/analytics out of the real home and never reach a display."""
    home = tmp_path / "home"
    home.mkdir()
    for var, sub in (
        ("HOME", ""),
        ("XDG_CONFIG_HOME", ".config"),
        ("XDG_DATA_HOME", ".local/share"),
        ("XDG_CACHE_HOME", ".cache"),
    ):
        monkeypatch.setenv(var, str(home / sub))
    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)


def record(path, pairs, context, options: str = "") -> RerunSink:
    sink = create_sink(f"rerun:{path}{options}")
    assert isinstance(sink, RerunSink) and sink.mode == "save"
    sink.open(context)
    for frame, result in pairs:
        sink.write(frame, result)
    sink.close()
    sink.close()  # safe twice
    return sink


def temporal(path) -> dict[str, list]:
    """entity -> list of record batches of its non-static chunks."""
    out: dict[str, list] = {}
    for chunk in rrchunk.RrdReader(str(path)).stream():
        if not chunk.is_static:
            out.setdefault(chunk.entity_path, []).append(chunk.to_record_batch())
    return out


def column(batches, name) -> list:
    """All rows of one column, in frame order."""
    rows = []
    for rb in batches:
        rows += list(zip(rb.column("frame").to_pylist(), rb.column(name).to_pylist(), strict=True))
    return [v for _, v in sorted(rows, key=lambda fv: fv[0])]


def test_rrd_has_every_entity_per_frame(tmp_path, pairs, context):
    path = tmp_path / "run.rrd"
    record(path, pairs, context)
    reader = rrchunk.RrdReader(str(path))
    assert [r.application_id for r in reader.recordings()] == ["depthnav"]
    assert len(reader.blueprints()) == 1  # the default layout travels in the file
    reader.store()  # only a footer-complete file loads lazily
    ent = temporal(path)
    n = len(pairs)
    for entity in (
        "/world/sensor",
        "/world/sensor/depth",
        "/world/sensor/depth/band",
        "/world/sensor/depth/obstacles",
        "/world/sensor/depth/cliffs",
        "/world/scan",
        "/world/cliff/points",
        "/world/cliff/scan",
        "/stats/pose/height_m",
        "/stats/pose/tilt_deg",
        "/stats/pose/roll_deg",
        "/stats/timing/scan_ms",
        "/stats/timing/cliff_ms",
    ):
        assert sum(rb.num_rows for rb in ent[entity]) == n, entity
    assert column(ent["/world/scan"], "frame") == [r.seq for _, r in pairs]
    # one warning (frame 3); the accepted floor estimate of frame 2 logs nothing
    texts = column(ent["/log"], "TextLog:text")
    assert len(texts) == 1 and "low valid depth" in texts[0][0]


def test_values_match_the_results(tmp_path, pairs, context):
    path = tmp_path / "run.rrd"
    record(path, pairs, context)
    ent = temporal(path)
    heights = [v[0] for v in column(ent["/stats/pose/height_m"], "Scalars:scalars")]
    assert heights == pytest.approx([r.mount.height_m for _, r in pairs])
    timing = [v[0] for v in column(ent["/stats/timing/scan_ms"], "Scalars:scalars")]
    assert timing == pytest.approx([r.timings_s["scan"] * 1000 for _, r in pairs])
    secs = sorted(
        ns / 1e9
        for rb in ent["/world/sensor"]
        for ns in rb.column("sensor_time").cast("int64").to_pylist()
    )
    assert secs == pytest.approx([r.timestamp_s for _, r in pairs], abs=1e-6)
    frame, result = pairs[1]
    # depth image: the very bytes of the frame, with meter = 1000 (millimetres)
    buf = column(ent["/world/sensor/depth"], "DepthImage:buffer")[1][0]
    assert np.array_equal(
        np.frombuffer(bytes(buf), np.uint16).reshape(frame.depth_mm.shape), frame.depth_mm
    )
    assert column(ent["/world/sensor/depth"], "DepthImage:meter")[1] == [1000.0]
    # scan points: every finite range, on its bearing (x forward, y left)
    pts = np.asarray(column(ent["/world/scan"], "Points3D:positions")[1])
    r = result.scan.ranges.astype(np.float64)
    ok = np.isfinite(r)
    a = result.scan.angles[ok]
    assert len(pts) == ok.sum() > 0
    assert np.allclose(pts[:, 0], r[ok] * np.cos(a), atol=1e-4)
    assert np.allclose(pts[:, 1], r[ok] * np.sin(a), atol=1e-4)
    # cliff points on the floor (z = 0), blocks drawn at (col, row) with the block size
    cliff_pts = np.asarray(column(ent["/world/cliff/points"], "Points3D:positions")[1])
    assert np.allclose(cliff_pts[:, :2], result.cliff.points_m, atol=1e-5) and np.all(
        cliff_pts[:, 2] == 0
    )
    centers = np.asarray(column(ent["/world/sensor/depth/cliffs"], "Boxes2D:centers")[1])
    blocks = np.asarray(result.cliff.blocks)
    bs = context.cliff_block_size
    assert np.allclose(centers, blocks[:, ::-1] - 0.5 + bs / 2.0)
    # obstacle overlay: exactly the scan's obstacle pixels
    seg = np.frombuffer(
        bytes(column(ent["/world/sensor/depth/obstacles"], "SegmentationImage:buffer")[1][0]),
        np.uint8,
    ).reshape(frame.depth_mm.shape)
    want = obstacle_pixels(frame.depth_mm, frame.intrinsics, result.mount, context.scan_params)
    assert want.any() and np.array_equal(seg == 1, want)


def test_sensor_pose_transform_pins_tilt_sign(tmp_path, pairs, context):
    path = tmp_path / "run.rrd"
    record(path, pairs[:1], context)
    ent = temporal(path)
    _, result = pairs[0]
    t = column(ent["/world/sensor"], "Transform3D:translation")[0][0]
    assert t == pytest.approx([0.0, 0.0, result.mount.height_m])
    mat = (
        np.asarray(column(ent["/world/sensor"], "Transform3D:mat3x3")[0][0]).reshape(3, 3).T
    )  # stored column-major
    assert np.allclose(mat, rot_y(result.mount.tilt_rad) @ rot_x(result.mount.roll_rad), atol=1e-6)
    forward = mat @ [1.0, 0.0, 0.0]
    assert forward[2] < 0  # tilt 12 deg = nose down: the optical axis points at the floor
    left = mat @ [0.0, 1.0, 0.0]
    assert left[2] > 0  # roll 1.5 deg = left side up


def test_sensor_transform_places_the_sensor_on_the_robot(tmp_path, pairs, context):
    # the scan and cliff points are drawn in the base frame: the sensor (its depth image and
    # frustum) must sit where [mount] puts it, turned by its yaw
    from dataclasses import replace

    from depthnav_daemon.pipeline.geometry import rot_z

    frame, result = pairs[0]
    m = result.mount
    placed = replace(m, x_m=0.2, y_m=-0.1, yaw_deg=30.0)
    path = tmp_path / "placed.rrd"
    record(
        path,
        [(frame, replace(result, mount_state=replace(result.mount_state, mount=placed)))],
        context,
    )
    ent = temporal(path)
    t = column(ent["/world/sensor"], "Transform3D:translation")[0][0]
    assert t == pytest.approx([0.2, -0.1, m.height_m])
    mat = np.asarray(column(ent["/world/sensor"], "Transform3D:mat3x3")[0][0]).reshape(3, 3).T
    want = rot_z(placed.yaw_rad) @ rot_y(m.tilt_rad) @ rot_x(m.roll_rad)
    assert np.allclose(mat, want, atol=1e-6)
    forward = mat @ [1.0, 0.0, 0.0]
    assert forward[1] > 0 and forward[2] < 0  # turned left (yaw 30 deg), nose down


def test_static_scene_logged_once(tmp_path, pairs, context):
    path = tmp_path / "run.rrd"
    record(path, pairs, context)
    static = {}
    for chunk in rrchunk.RrdReader(str(path)).stream():
        if chunk.is_static:
            static[chunk.entity_path] = static.get(chunk.entity_path, 0) + chunk.num_rows
    assert static["/world"] == 1 and static["/world/floor"] == 1
    assert static["/world/sensor/depth"] == 1  # the pinhole: the intrinsics never changed


def test_every_and_image_options(tmp_path, pairs, context):
    path = tmp_path / "thin.rrd"
    sink = record(path, pairs, context, "?every=2&image=0")
    assert sink.logged == 3
    ent = temporal(path)
    assert "/world/sensor/depth" not in ent and "/world/sensor/depth/obstacles" not in ent
    assert column(ent["/world/scan"], "frame") == [0, 2, 4]


def test_no_cliff_stage(tmp_path, pairs, context):
    path = tmp_path / "nocliff.rrd"
    frame, result = pairs[0]
    record(path, [(frame, replace(result, cliff=None))], context)
    ent = temporal(path)
    assert "/world/cliff/points" not in ent
    assert column(ent["/world/sensor/depth/cliffs"], "Boxes2D:centers") in ([None], [[]])


def test_spawn_without_display_fails_fast(context):
    sink = create_sink("rerun")
    with pytest.raises(SinkError, match="no display") as info:
        sink.open(context)
    assert "rerun:FILE.rrd" in info.value.hint
    sink.close()


def test_save_into_missing_folder(tmp_path, context):
    sink = create_sink(f"rerun:{tmp_path}/nope/run.rrd")
    with pytest.raises(SinkError, match="does not exist"):
        sink.open(context)


def test_save_where_no_file_can_be_made(context):
    sink = create_sink("rerun:/proc/depthnav-test.rrd")  # /proc exists, but takes no new files
    with pytest.raises(SinkError, match="cannot write"):
        sink.open(context)
    sink.close()


@pytest.mark.parametrize(
    "spec", ["rerun:run.txt", "rerun://host:9876", "rerun:x.rrd?every=0", "rerun?fps=3"]
)
def test_bad_specs(spec):
    with pytest.raises(ConfigError):
        create_sink(spec)


def test_grpc_spec_builds_proxy_url():
    assert create_sink("rerun+grpc://10.0.0.5:9000").target == "rerun+http://10.0.0.5:9000/proxy"
    assert create_sink("rerun+grpc://").target == "rerun+http://127.0.0.1:9876/proxy"


def test_module_name_does_not_shadow_rerun():
    import rerun

    # sinks/rerun/rerun.py does `import rerun as rr`: that must be the SDK, not the module itself
    assert "depthnav_daemon" not in rerun.__file__ and hasattr(rerun, "RecordingStream")


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def scan_rows(path: Path) -> int:
    """Temporal rows of /world/scan in a (possibly still growing, footer-less) .rrd."""
    if not path.exists():
        return 0
    try:
        with warnings.catch_warnings():  # "no footer": expected while the server still writes
            warnings.simplefilter("ignore")
            chunks = list(rrchunk.RrdReader(str(path)).stream())
    except Exception:  # a file the server has only just created
        return 0
    return sum(c.num_rows for c in chunks if c.entity_path == "/world/scan" and not c.is_static)


def _rerun_server(tmp_path: Path, save: str) -> tuple[subprocess.Popen, int]:
    """The real rerun binary (not the Python shim) serving gRPC on a free loopback port and
    saving what it receives to ``save``; (process, port) once it listens."""
    import rerun_cli

    binary = Path(rerun_cli.__file__).with_name("rerun")
    skip_without(not binary.exists(), "rerun_cli's rerun binary", "pip install rerun-sdk")
    port, log_path = free_port(), tmp_path / "server.log"
    with open(log_path, "wb") as log_file:
        server = subprocess.Popen(
            [str(binary), "--bind", "127.0.0.1", "--port", str(port), "--save", save],
            stdout=log_file,
            stderr=subprocess.STDOUT,
            start_new_session=True,
        )
    deadline = time.monotonic() + 30
    while b"Listening for gRPC" not in log_path.read_bytes():
        if server.poll() is not None or time.monotonic() > deadline:
            os.killpg(server.pid, signal.SIGKILL)
            raise AssertionError(log_path.read_text())
        time.sleep(0.1)
    return server, port


def test_connect_to_a_real_grpc_server(tmp_path, pairs, context):
    """rerun+grpc:// against the real rerun binary, which saves what it receives to an .rrd."""
    out = tmp_path / "received.rrd"
    server, port = _rerun_server(tmp_path, str(out))
    try:
        sink = create_sink(f"rerun+grpc://127.0.0.1:{port}")
        sink.open(context)
        for frame, result in pairs[:3]:
            sink.write(frame, result)
        sink.close()  # flushes to the server
        # the server writes what it received in its own time: wait (bounded) for all 3 frames
        deadline = time.monotonic() + 30
        while scan_rows(out) < 3 and time.monotonic() < deadline:
            time.sleep(0.2)
        server.send_signal(signal.SIGINT)  # Ctrl-C: the server closes the file
        # ... usually at once; once in a loaded full suite it had not ended 30 s later, with all
        # 3 frames in its (footer-less) file. Its shutdown is rerun's business: what is tested is
        # that the frames reached it, which the file shows either way (read without a footer).
        with contextlib.suppress(subprocess.TimeoutExpired):
            server.wait(timeout=30)
    finally:
        if server.poll() is None:
            os.killpg(server.pid, signal.SIGKILL)
            server.wait(timeout=10)
    assert scan_rows(out) == 3


def test_default_blueprint_views(tmp_path, pairs, context):
    from depthnav_daemon.sinks.rerun.layout import DEPTH_VIEW
    from depthnav_daemon.sinks.rerun.topdown import BASE_VIEW

    path = tmp_path / "run.rrd"
    record(path, pairs[:1], context)
    reader = rrchunk.RrdReader(str(path))
    views = {}
    for chunk in reader.stream(store=reader.blueprints()[0]):
        rb = chunk.to_record_batch()
        if "ViewBlueprint:display_name" in rb.schema.names:
            name = rb.column("ViewBlueprint:display_name").to_pylist()[0][0]
            kind = rb.column("ViewBlueprint:class_identifier").to_pylist()[0][0]
            origin = rb.column("ViewBlueprint:space_origin").to_pylist()[0][0]
            views[name] = (kind, origin)
    assert views == {
        BASE_VIEW: ("2D", "/topdown"),
        DEPTH_VIEW: ("2D", "/world/sensor/depth"),
        "3D": ("3D", "/world"),
        "Height [m]": ("TimeSeries", "/stats/pose"),
        "Tilt [deg]": ("TimeSeries", "/stats/pose"),
        "Roll [deg]": ("TimeSeries", "/stats/pose"),
        "Timing [ms], after warm-up": ("TimeSeries", "/stats/timing_after_warmup"),
        "Log": ("TextLog", "/log"),
    }


def test_a_second_writer_of_the_same_rrd_is_refused_and_the_first_file_stays_whole(
    tmp_path, pairs, context
):
    """Two daemons given one .rrd both claimed their frames and the file held none: the first
    holds an exclusive lock while it writes; the second is refused in one line."""
    path = tmp_path / "shared.rrd"
    first = create_sink(f"rerun:{path}")
    first.open(context)
    second = create_sink(f"rerun:{path}")
    with pytest.raises(SinkError, match="another process is writing") as info:
        second.open(context)
    assert "own .rrd" in info.value.hint
    for frame, result in pairs:
        first.write(frame, result)
    first.close()
    ent = temporal(path)
    assert len(column(ent["/world/scan"], "Points3D:positions")) == len(pairs)
    record(path, pairs, context)  # the lock is released at close: the file can be written again


def rgba(rgb) -> int:
    """rerun's packed colour, 0xRRGGBBAA."""
    r, g, b = rgb
    return (r << 24) | (g << 16) | (b << 8) | 0xFF


def test_untrusted_dropoffs_are_amber_and_the_trust_is_logged(tmp_path, pairs, context):
    """While the mount is not trusted, the scan and the drop-offs are amber in every view (the
    depth overlay's class too), the top-down view's title says so and the Log tab comes first;
    the trust is logged when it changes."""
    from depthnav_daemon.pipeline import MountTrust
    from depthnav_daemon.sinks.rerun.depth import CLASS_CLIFF, CLASS_CLIFF_UNTRUSTED
    from depthnav_daemon.sinks.rerun.layout import UNTRUSTED_VIEW
    from depthnav_daemon.sinks.rerun.topdown import (
        BASE_VIEW,
        CLIFF_RGB,
        SCAN_RGB,
        UNTRUSTED_CLIFF_RGB,
        UNTRUSTED_RGB,
    )
    from tests.sinks.test_rerun_layout import blueprint_stores, views_of

    good = MountTrust(source="config", floor="confirmed")
    bad = MountTrust(
        source="config",
        pinned=True,
        floor="contradicted",
        floor_height_m=0.7,
        floor_tilt_deg=12.0,
        floor_roll_deg=0.0,
        dropoffs_trusted=False,
        note="the floor says height 0.70 m ...: drop-offs are not trusted",
    )
    trusts = [good, bad, bad, good]
    flagged = [
        replace(r, mount_state=replace(r.mount_state, trust=t))
        for (_, r), t in zip(pairs, trusts, strict=False)
    ]
    path = tmp_path / "run.rrd"
    record(path, [(f, r) for (f, _), r in zip(pairs, flagged, strict=False)], context)
    ent = temporal(path)
    want = [rgba(UNTRUSTED_CLIFF_RGB if not t.dropoffs_trusted else CLIFF_RGB) for t in trusts]
    for entity, col in (
        ("/world/cliff/points", "Points3D:colors"),
        ("/world/cliff/scan", "LineStrips3D:colors"),
        ("/topdown/cliff", "Points2D:colors"),
        ("/topdown/cliff/scan", "LineStrips2D:colors"),
    ):
        assert [c[0] for c in column(ent[entity], col)] == want, entity
    scan = [rgba(UNTRUSTED_RGB if not t.dropoffs_trusted else SCAN_RGB) for t in trusts]
    for entity, col in (
        ("/topdown/scan", "LineStrips2D:colors"),
        ("/world/scan", "Points3D:colors"),
    ):
        assert [c[0] for c in column(ent[entity], col)] == scan, entity
    # the depth overlay: the drop-offs' lower floor in the untrusted class on untrusted frames
    shape = pairs[0][0].depth_mm.shape
    for buf, t in zip(
        column(ent["/world/sensor/depth/obstacles"], "SegmentationImage:buffer"),
        trusts,
        strict=True,
    ):
        seg = np.frombuffer(bytes(buf[0]), np.uint8).reshape(shape)
        shown, hidden = (CLASS_CLIFF, CLASS_CLIFF_UNTRUSTED)[:: 1 if t.dropoffs_trusted else -1]
        assert (seg == shown).any() and not (seg == hidden).any()
    # the layout was sent again at each change: the untrusted one names it, the Log tab first
    stores = blueprint_stores(path)
    assert len(stores) == 3
    names = [views_of(rows) for rows in stores]
    assert BASE_VIEW in names[0] and BASE_VIEW in names[2] and UNTRUSTED_VIEW in names[1]
    log_view = names[1]["Log"][2].lstrip("/")
    tabs = [c for c in stores[1].values() if log_view in c.get("ContainerBlueprint:contents", [])]
    assert tabs[0]["ContainerBlueprint:active_tab"] == [log_view]
    # the trust is logged when it changes (frames 0, 1, 3), besides frame 3's own warning
    texts = [t[0] for t in column(ent["/log"], "TextLog:text")]
    levels = [t[0] for t in column(ent["/log"], "TextLog:level")]
    trust_lines = [(t, lv) for t, lv in zip(texts, levels, strict=True) if "mount from" in t]
    assert [lv for _, lv in trust_lines] == ["INFO", "WARN", "INFO"]
    assert "floor confirmed: drop-offs trusted" in trust_lines[0][0]
    assert "(pinned)" in trust_lines[1][0] and "drawn amber" in trust_lines[1][0]
    # the contradicting floor estimate is plotted on every untrusted frame
    floor = ent["/stats/pose/height_floor_m"]
    assert set(column(floor, "frame")) == {1, 2}
    assert [v[0] for v in column(floor, "Scalars:scalars")] == pytest.approx([0.7, 0.52], abs=1e-6)


def test_a_viewer_that_goes_away_is_not_claimed_delivered(tmp_path, pairs, context, caplog):
    """The viewer dies mid-run: the summary says the frames were not confirmed delivered."""
    server, port = _rerun_server(tmp_path, "/dev/null")
    try:
        sink = create_sink(f"rerun+grpc://127.0.0.1:{port}")
        sink.open(context)  # the viewer is there: the probe lets it through
        sink.write(*pairs[0])
    finally:
        os.killpg(server.pid, signal.SIGKILL)
        server.wait(timeout=10)
    with caplog.at_level("INFO"):
        for frame, result in pairs[1:]:
            sink.write(frame, result)
        sink.close()
    text = caplog.text
    assert "not confirmed delivered" in text and "frames logged" not in text


def test_check_viewer_refuses_a_silent_listener_and_a_closed_port():
    from depthnav_daemon.sinks.rerun.viewer import check_viewer

    with socket.socket() as listener:  # accepts connections (backlog) but never answers
        listener.bind(("127.0.0.1", 0))
        listener.listen(1)
        port = listener.getsockname()[1]
        with pytest.raises(SinkError, match="does not answer") as info:
            check_viewer(f"rerun+http://127.0.0.1:{port}/proxy", timeout_s=0.5)
        assert f"rerun --port {port}" in info.value.hint
    with pytest.raises(SinkError, match=f"no rerun viewer at 127.0.0.1:{port}"):
        check_viewer(f"rerun+http://127.0.0.1:{port}/proxy", timeout_s=0.5)


class _StuckWriter:
    """A sink's real recording whose file writer is stuck, as rerun's was on a full disk under load:
    a flush times out, disconnect() does not return until released."""

    def __init__(self, rec) -> None:
        self.rec, self.flushes, self.release = rec, 0, threading.Event()

    def flush(self, timeout_sec: float) -> None:
        self.flushes += 1
        raise RuntimeError(f"flush timed out after {timeout_sec} s")

    def disconnect(self) -> None:
        self.release.wait()
        self.rec.disconnect()

    def __getattr__(self, name: str):
        return getattr(self.rec, name)


def test_a_stuck_file_writer_never_holds_the_daemon(tmp_path, pairs, context, monkeypatch, caplog):
    """The writer stuck: the sink fails at its next file check, close() flushes no more (that
    only waits) and leaves the blocked disconnect behind, marked for the CLI's quick exit."""
    monkeypatch.setattr(rerun_sink, "DISCONNECT_S", 600.0)  # a failed file's is FAILED_DISCONNECT_S
    monkeypatch.setattr(rerun_sink, "_abandoned", [])
    path = tmp_path / "stuck.rrd"
    sink = create_sink(f"rerun:{path}")
    sink.open(context)
    sink.write(*pairs[0])
    stuck = _StuckWriter(sink._rec)
    sink._rec, sink._next_check = stuck, 0.0  # the next write checks the file
    try:
        with pytest.raises(SinkError, match=r"writing .* failed"):
            sink.write(*pairs[1])
        with caplog.at_level("WARNING"):
            sink.close()  # returns: before the fix, rerun's disconnect() blocked for ever
        assert stuck.flushes == 1  # the failed file is not flushed again at close
        assert rerun_sink.abandoned_viewers() == [sink.name]
        assert "does not close (rerun's writer is stuck)" in caplog.text
    finally:
        stuck.release.set()  # the real recording closes now


def test_a_sink_that_fails_to_open_never_waits_on_a_stuck_recording(tmp_path, context, monkeypatch):
    """open() fails (no such folder) and its recording's disconnect blocks: open() still reports
    its error at once and leaves the recording behind, marked for the CLI's quick exit."""
    monkeypatch.setattr(rerun_sink, "_abandoned", [])
    rr = rerun_sink._import_rerun()
    made: list[_StuckWriter] = []

    class _Rerun:
        def __getattr__(self, name: str):
            return getattr(rr, name)

        def RecordingStream(self, *args, **kwargs):  # noqa: N802 - rerun's name
            made.append(_StuckWriter(rr.RecordingStream(*args, **kwargs)))
            return made[-1]

    monkeypatch.setattr(rerun_sink, "_import_rerun", _Rerun)
    sink = create_sink(f"rerun:{tmp_path / 'missing' / 'x.rrd'}")
    try:
        with pytest.raises(SinkError, match="does not exist"):
            sink.open(context)  # before: rec.disconnect() unbounded, here for ever
        assert rerun_sink.abandoned_viewers() == [sink.name]
    finally:
        for stuck in made:
            stuck.release.set()
