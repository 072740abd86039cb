"""``foxglove`` sink: a WebSocket client on loopback (the ``websockets`` package) subscribes,
decodes every advertised channel with its advertised protobuf schema, and checks the scans
against the stdout JSON of the same run; clients that vanish or stall change nothing else."""

from __future__ import annotations

import base64
import json
import signal
import socket
import struct
import subprocess
import threading
import time
from pathlib import Path
from typing import Any

import pytest

from tests.faults.kit import WAIT_S, depthnav, free_tcp_port, start
from tests.sinks.roskit import has_all_codes, same_ranges, special_recording

PROTOCOL = "foxglove.sdk.v1"
# websockets 16+ asks for connect() in a with-block; these clients live across helper calls
pytestmark = pytest.mark.filterwarnings("ignore:connect\\(\\) must be used:DeprecationWarning")


class Client:
    """A minimal Foxglove WebSocket client: subscribe to channels, decode messageData."""

    def __init__(self, port: int, sock: socket.socket | None = None, max_queue: int = 64) -> None:
        from websockets.sync.client import ClientConnection, connect

        self.ws: ClientConnection
        deadline = time.monotonic() + WAIT_S
        while True:  # the daemon starts its server after opening the device
            try:
                self.ws = connect(
                    f"ws://127.0.0.1:{port}",
                    subprotocols=[PROTOCOL],  # type: ignore[list-item]
                    sock=sock,
                    max_queue=max_queue,
                    open_timeout=WAIT_S,
                    # no keepalive thread: one left pinging a stopped daemon logged an error
                    # into the closed output of a later test
                    ping_interval=None,
                )
                break
            except OSError:
                assert time.monotonic() < deadline, "the foxglove server did not start"
                time.sleep(0.05)
        self.channels: dict[int, dict[str, Any]] = {}
        self.classes: dict[int, Any] = {}
        self.subs: dict[int, int] = {}

    def advertised(self, want: int) -> dict[str, dict[str, Any]]:
        """Read control messages until ``want`` channels are advertised; topic -> channel."""
        while len(self.channels) < want:
            msg = json.loads(self.ws.recv(timeout=WAIT_S))
            if msg["op"] == "advertise":
                for ch in msg["channels"]:
                    self.channels[ch["id"]] = ch
        return {ch["topic"]: ch for ch in self.channels.values()}

    def subscribe(self, topics: list[str]) -> None:
        subs = []
        for ch in self.channels.values():
            if ch["topic"] in topics:
                sub = len(self.subs) + 1
                self.subs[sub] = ch["id"]
                subs.append({"id": sub, "channelId": ch["id"]})
        self.ws.send(json.dumps({"op": "subscribe", "subscriptions": subs}))

    def decoder(self, channel: dict[str, Any]) -> Any:
        """A message class built from the channel's advertised FileDescriptorSet."""
        from google.protobuf import descriptor_pb2, descriptor_pool, message_factory

        fds = descriptor_pb2.FileDescriptorSet.FromString(base64.b64decode(channel["schema"]))
        pool = descriptor_pool.DescriptorPool()
        pending = list(fds.file)
        while pending:  # add each file once its dependencies are in
            done = [f for f in pending if all(_has(pool, d) for d in f.dependency)]
            assert done, "unresolvable schema"
            for f in done:
                pool.Add(f)
                pending.remove(f)
        return message_factory.GetMessageClass(pool.FindMessageTypeByName(channel["schemaName"]))

    def next_message(self) -> tuple[str, Any]:
        """(topic, decoded message) of the next messageData frame."""
        while True:
            data = self.ws.recv(timeout=WAIT_S)
            if isinstance(data, str):
                continue  # control messages (advertise, status, ...)
            assert data[0] == 1, f"opcode {data[0]}"
            sub, _ = struct.unpack_from("<IQ", data, 1)
            ch = self.channels[self.subs[sub]]
            payload = data[13:]
            if ch["encoding"] == "json":
                return ch["topic"], json.loads(payload)
            if sub not in self.classes:
                self.classes[sub] = self.decoder(ch)
            return ch["topic"], self.classes[sub].FromString(payload)


def _has(pool: Any, name: str) -> bool:
    try:
        pool.FindFileByName(name)
    except KeyError:
        return False
    return True


TOPICS = {
    "/scan": "foxglove.LaserScan",
    "/cliff/scan": "foxglove.LaserScan",
    "/cliff/points": "foxglove.PointCloud",
    "/tf": "foxglove.FrameTransforms",
    "/depth_sensor_pose": "foxglove.PoseInFrame",
    "/depthnav/depth/image_raw": "foxglove.RawImage",
    "/depthnav/depth/camera_info": "foxglove.CameraCalibration",
    "/depthnav/depth/annotations": "foxglove.ImageAnnotations",
    "/depthnav/timings": None,  # JSON
}


class Lines:
    """Reads the daemon's stdout all along (a full pipe would make the stdout sink skip lines)."""

    def __init__(self, proc: subprocess.Popen[str]) -> None:
        self.proc = proc
        self.lines: list[str] = []
        self.thread = threading.Thread(target=self._read, daemon=True)
        self.thread.start()

    def _read(self) -> None:
        assert self.proc.stdout is not None
        for line in self.proc.stdout:
            self.lines.append(line)

    def wait_for(self, count: int) -> None:
        deadline = time.monotonic() + WAIT_S
        while len(self.lines) < count:
            assert self.proc.poll() is None, "depthnav exited"
            assert time.monotonic() < deadline, f"only {len(self.lines)} of {count} lines came"
            time.sleep(0.01)

    def stop(self) -> tuple[int, list[dict], str]:
        self.proc.send_signal(signal.SIGTERM)
        try:
            self.proc.wait(timeout=WAIT_S)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait()
            raise AssertionError("depthnav did not stop after SIGTERM") from None
        self.thread.join(WAIT_S)
        err = Path(self.proc.stderr_path).read_text()  # type: ignore[attr-defined]
        return self.proc.returncode, [json.loads(x) for x in self.lines], err


def collect(client: Client, got: dict[str, list[Any]], scans: int, topics: int = 1) -> None:
    """Read messages until ``scans`` /scan messages and ``topics`` topics were seen."""
    while len(got.get("/scan", [])) < scans or len(got) < topics:
        topic, msg = client.next_message()
        got.setdefault(topic, []).append(msg)


def bad_clients(port: int) -> None:
    """One client that vanishes mid-stream (no close handshake), one that subscribes to the
    images and never reads (a 4 KiB receive buffer)."""
    gone = Client(port)
    gone.advertised(len(TOPICS))
    gone.subscribe(["/depthnav/depth/image_raw", "/scan"])
    gone.next_message()
    gone.ws.socket.close()
    tiny = socket.socket()
    tiny.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
    tiny.connect(("127.0.0.1", port))
    slow = Client(port, sock=tiny, max_queue=1)
    slow.advertised(len(TOPICS))
    slow.subscribe(["/depthnav/depth/image_raw"])


def test_live_view_matches_the_json_and_survives_bad_clients(tmp_path: Path) -> None:
    rec = special_recording(tmp_path / "rec", n=8)
    port = free_tcp_port()
    proc = start(
        "run",
        "--device", f"replay:{rec}?rate=realtime&loop=1",
        "--sink", f"foxglove://127.0.0.1:{port}",
        "--sink", "stdout",
    )  # fmt: skip
    out = Lines(proc)
    got: dict[str, list[Any]] = {}
    try:
        client = Client(port)
        channels = client.advertised(len(TOPICS))
        assert {t: c["schemaName"] for t, c in channels.items() if t != "/depthnav/timings"} == {
            t: s for t, s in TOPICS.items() if s
        }
        client.subscribe(list(TOPICS))
        collect(client, got, 4, len(TOPICS))
        bad_clients(port)
        out.wait_for(len(out.lines) + 40)  # the frame loop goes on: 40 more frames
        collect(client, got, len(got["/scan"]) + 4)  # and the good client is still served
    finally:
        code, msgs, err = out.stop()
    assert code == 0, err
    assert "Traceback" not in err
    seqs = [m["seq"] for m in msgs]
    assert seqs == list(range(len(seqs))), err  # nothing lost on stdout
    check_live(got, msgs)


def check_live(got: dict[str, list[Any]], msgs: list[dict]) -> None:
    by_time = {round(m["t_s"], 6): m for m in msgs}
    for scan in got["/scan"]:
        m = by_time[round(scan.timestamp.seconds + scan.timestamp.nanos * 1e-9, 6)]
        assert has_all_codes(m["scan"]["ranges"])
        same_ranges(list(scan.ranges), m["scan"]["ranges"])
        assert scan.frame_id == "depthnav_scan"
        assert scan.start_angle == pytest.approx(m["scan"]["angle_min"], abs=1e-6)
    image = got["/depthnav/depth/image_raw"][0]
    assert (image.width, image.height, image.encoding) == (320, 240, "16UC1")
    assert len(image.data) == 320 * 240 * 2
    tf = got["/tf"][0].transforms
    assert [(t.parent_frame_id, t.child_frame_id) for t in tf] == [
        ("base_link", "depthnav_scan"),
        ("base_link", "depthnav_optical"),
    ]
    cloud = got["/cliff/points"][0]
    assert cloud.point_stride == 12 and len(cloud.data) % 12 == 0 and len(cloud.data) > 0
    assert got["/depthnav/depth/annotations"][0].points  # the band at least
    assert set(got["/depthnav/timings"][0]["timings_ms"]) >= {"scan"}


def test_mcap_file_and_port_in_use(tmp_path: Path) -> None:
    from mcap.reader import make_reader

    rec = special_recording(tmp_path / "rec", n=2)
    out = tmp_path / "view.mcap"
    busy = socket.socket()
    busy.bind(("127.0.0.1", 0))
    busy.listen()
    port = busy.getsockname()[1]
    try:
        p = depthnav(
            "run",
            "--device", f"replay:{rec}?rate=max",
            "--sink", f"foxglove:{out}",
            "--sink", f"foxglove://127.0.0.1:{port}",
        )  # fmt: skip
    finally:
        busy.close()
    assert p.returncode == 0, p.stderr
    (line,) = [x for x in p.stderr.splitlines() if "ERROR" in x]
    assert f"cannot serve on 127.0.0.1:{port}" in line and "Address already in use" in line
    with open(out, "rb") as fh:
        summary = make_reader(fh).get_summary()
    assert summary is not None
    counts = {
        c.topic: summary.statistics.channel_message_counts[c.id] for c in summary.channels.values()
    }
    assert counts == dict.fromkeys(TOPICS, 2)


def test_camera_calibration_carries_the_lens_coefficients(tmp_path: Path) -> None:
    from google.protobuf import descriptor_pb2, descriptor_pool, message_factory
    from mcap.reader import make_reader

    rec = special_recording(tmp_path / "rec", n=1)
    out = tmp_path / "lens.mcap"
    lens = "&k1=-0.2&k2=0.05&p1=0.001&p2=-0.002&k3=0.01"
    p = depthnav("run", "--device", f"replay:{rec}?rate=max{lens}", "--sink", f"foxglove:{out}")
    assert p.returncode == 0, p.stderr
    with open(out, "rb") as fh:
        (schema, _, raw) = next(
            iter(make_reader(fh).iter_messages(topics=["/depthnav/depth/camera_info"]))
        )
    pool = descriptor_pool.DescriptorPool()
    pending = list(descriptor_pb2.FileDescriptorSet.FromString(schema.data).file)
    while pending:  # add each file once its dependencies are in
        done = [f for f in pending if all(_has(pool, d) for d in f.dependency)]
        assert done, "unresolvable schema"
        for f in done:
            pool.Add(f)
            pending.remove(f)
    cls = message_factory.GetMessageClass(pool.FindMessageTypeByName(schema.name))
    info = cls.FromString(raw.data)
    assert info.distortion_model == "plumb_bob"
    assert list(info.D) == pytest.approx([-0.2, 0.05, 0.001, -0.002, 0.01])
