"""Faults during a run: a damaged recording, a full disk, outputs and inputs that go away.

Each test drives the real CLI in a child process (real files, sockets, ptys, signals) or the real
frame loop with real drivers, and checks the message, the exit code and that what was already
written is intact.
"""

from __future__ import annotations

import contextlib
import json
import logging
import os
import signal
import socket
import subprocess
import threading
import time
import tty
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from depthnav_daemon.config.loader import build_config
from depthnav_daemon.daemon.loop import run
from depthnav_daemon.sinks.null import NullSink
from drivers import create_driver
from drivers.base import DeviceInfo, Frame
from drivers.formats.recording import read_recording
from drivers.formats.recording_writer import write_recording
from drivers.kinect.motor import KinectMotor
from drivers.tilt.serialtilt import format_line
from tests.drivers.driverkit import skip_without
from tests.drivers.fake_kinect_usb import FakeUsbBackend, KinectMotorModel

from .kit import (
    ENDLESS,
    FAST,
    FIXTURE,
    ROOT,
    WAIT_S,
    depthnav,
    finish,
    free_tcp_port,
    json_lines,
    one_error_line,
    read_lines,
    small_disk,
    start,
)


# --- a disk that fills (kit.small_disk) -------------------------------------------------------
def test_disk_full_while_recording(tmp_path: Path) -> None:
    with small_disk(tmp_path, "1m") as (disk, preexec):
        small = read_recording(FIXTURE).frames()[:1]
        tiny = [
            Frame(0, 0.0, f.depth_mm[:48, :64].copy(), f.intrinsics.scaled(64, 48)) for f in small
        ]
        write_recording(disk / "earlier", tiny, description="already on the disk")
        before = (disk / "earlier" / "frames.npz").read_bytes()
        p = subprocess.run(
            [
                os.sys.executable,
                "-m",
                "depthnav_daemon",
                "record",
                "--device",
                f"{FAST}&loop=1",
                "--frames",
                "40",
                str(disk / "rec"),
            ],
            capture_output=True,
            text=True,
            timeout=120,
            cwd=ROOT,
            preexec_fn=preexec,
        )
        assert p.returncode == 1, p.stderr
        line = one_error_line(p.stderr)
        assert str(disk / "rec") in line
        assert "No space left on device" in line or "File too large" in line
        assert "free some disk space" in p.stderr
        # nothing half-written is left, and what was there before is untouched
        assert not (disk / "rec").exists() or not any((disk / "rec").iterdir())
        assert (disk / "earlier" / "frames.npz").read_bytes() == before
        assert len(read_recording(disk / "earlier").depth_mm) == 1


# the cut-off file has no footer: rerun warns that it falls back to a whole-file scan (expected)
@pytest.mark.filterwarnings("ignore:RRD file has no footer")
def test_disk_full_while_writing_an_rrd(tmp_path: Path) -> None:
    from rerun.chunk import RrdReader

    with small_disk(tmp_path, "8m") as (disk, preexec):
        rrd = disk / "run.rrd"
        p = subprocess.run(
            [
                os.sys.executable,
                "-m",
                "depthnav_daemon",
                "run",
                "--device",
                f"{FAST}&loop=1",
                "--sink",
                "stdout",
                "--sink",
                f"rerun:{rrd}",
                "--max-frames",
                "600",
            ],
            capture_output=True,
            text=True,
            timeout=300,
            cwd=ROOT,
            preexec_fn=preexec,
        )
        assert p.returncode == 0, p.stderr
        lines = json_lines(p.stdout)
        assert [m["seq"] for m in lines] == list(range(600))  # the other sink lost nothing
        assert f"sink rerun:{rrd} failed: rerun sink: writing {rrd} failed" in p.stderr
        assert "Traceback" not in p.stderr
        # the frames flushed before the disk filled read back (the footer is missing)
        rows = 0
        with contextlib.suppress(RuntimeError):  # the last message was cut off by the full disk
            for chunk in RrdReader(str(rrd)).stream():
                if chunk.entity_path == "/world/scan" and not chunk.is_static:
                    rows += chunk.num_rows
        assert rows > 0


# --- a recording damaged in the middle --------------------------------------------------------
def test_resolution_change_mid_recording_ends_the_run_once(tmp_path: Path) -> None:
    """Before the fix the daemon 'reconnected' to the file and replayed frames 0-2 forever."""
    folder = tmp_path / "png"
    folder.mkdir()
    for i in range(6):
        shape = (40, 64) if i == 3 else (48, 64)
        Image.fromarray(np.full(shape, 6000, np.uint16)).save(folder / f"{i:03d}.png")
    (folder / "camera.toml").write_text(
        "depth_scale = 5000\n[intrinsics]\nfx = 60.0\nfy = 58.0\ncx = 31.0\ncy = 23.0\n"
    )
    p = depthnav(
        "run",
        "--device",
        f"replay:{folder}?rate=max",
        "--sink",
        "stdout",
        "--set",
        "daemon.reconnect_backoff_s=0.01",
        timeout=60,
    )
    assert p.returncode == 1, p.stderr
    line = one_error_line(p.stderr)
    assert "003.png" in line and "64x40" in line and "64x48" in line
    assert [m["seq"] for m in json_lines(p.stdout)] == [0, 1, 2]  # earlier output intact, once
    assert "reconnect" not in p.stderr


# --- outputs that go away ---------------------------------------------------------------------
def test_udp_receiver_that_disappears(tmp_path: Path) -> None:
    rx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    rx.bind(("127.0.0.1", 0))
    rx.settimeout(WAIT_S)
    port = rx.getsockname()[1]
    err = tmp_path / "err.txt"
    proc = start(
        "run",
        "--device",
        ENDLESS,
        "--sink",
        "stdout",
        "--sink",
        f"udp://127.0.0.1:{port}",
        stderr_path=err,
    )
    got = [rx.recv(65535) for _ in range(2)]
    rx.close()  # the receiver goes away: the next sends get ICMP port unreachable
    seen = read_lines(proc, 8)
    code, rest, _ = finish(proc)
    text = err.read_text()
    assert code == 0, text
    assert len(got) == 2
    seqs = [m["seq"] for m in json_lines("".join(seen) + rest)]
    assert seqs == list(range(len(seqs))) and len(seqs) >= 8
    assert f"udp sink: 127.0.0.1:{port} is not receiving (ConnectionRefusedError)" in text
    assert "Traceback" not in text and "dropped, the others go on" not in text  # never raised


@pytest.fixture
def pty_master() -> Iterator[tuple[int, str, int]]:
    master, slave = os.openpty()
    tty.setraw(master)
    tty.setraw(slave)
    name = os.ttyname(slave)
    # the test keeps a slave fd open so the master reads no EIO before the daemon opens its own
    yield master, name, slave
    for fd in (master, slave):
        with contextlib.suppress(OSError):
            os.close(fd)


def unplug(pty: tuple[int, str, int]) -> None:
    """The adapter is pulled: both ends close, the daemon's tty reads and writes fail (EIO)."""
    for fd in (pty[0], pty[2]):
        os.close(fd)


def _read_some(fd: int, n: int) -> bytes:
    os.set_blocking(fd, True)
    data = b""
    deadline = time.monotonic() + WAIT_S
    while len(data) < n and time.monotonic() < deadline:
        data += os.read(fd, 4096)
    return data


def test_mavlink_serial_port_that_vanishes(
    tmp_path: Path, pty_master: tuple[int, str, int]
) -> None:
    master, name, _ = pty_master
    err = tmp_path / "err.txt"
    proc = start(
        "run",
        "--device",
        ENDLESS,
        "--sink",
        "stdout",
        "--sink",
        f"mavlink:{name}?baud=921600",
        stderr_path=err,
    )
    assert _read_some(master, 17)[:1] in (b"\xfd", b"\xfe")  # MAVLink bytes arrive
    read_lines(proc, 2)
    unplug(pty_master)  # the USB-serial adapter is pulled: its tty is gone
    seen = read_lines(proc, 10)
    deadline = time.monotonic() + WAIT_S
    while "dropped, the others go on" not in err.read_text() and time.monotonic() < deadline:
        seen += read_lines(proc, 1)
    code, rest, _ = finish(proc)
    text = err.read_text()
    assert code == 0, text
    assert f"sink mavlink:{name}?baud=921600 failed: mavlink sink: serial {name}" in text
    assert "Traceback" not in text
    json_lines("".join(seen) + rest)


def test_serial_tilt_source_that_vanishes_does_not_stop_the_run(
    tmp_path: Path, pty_master: tuple[int, str, int]
) -> None:
    """Before the fix the IMU's DeviceLost escaped the frame loop: exit 1, the robot blind."""
    master, name, _ = pty_master
    os.write(master, format_line(15.0, 0.0) * 3)
    err = tmp_path / "err.txt"
    proc = start(
        "run",
        "--device",
        f"replay:{FIXTURE}?rate=realtime&loop=1",
        "--sink",
        "stdout",
        "--set",
        f'daemon.serial_tilt="serialtilt:{name}"',
        "--set",
        "daemon.tilt_source=serial",
        stderr_path=err,
    )
    read_lines(proc, 3)
    unplug(pty_master)
    deadline = time.monotonic() + WAIT_S
    seen: list[str] = []
    while "going on without the serial tilt source" not in err.read_text():
        assert time.monotonic() < deadline, err.read_text()
        seen += read_lines(proc, 1)
    seen += read_lines(proc, 5)  # frames keep coming
    code, rest, _ = finish(proc)
    text = err.read_text()
    assert code == 0, text
    assert f"serial tilt source {name} stopped" in text and "Traceback" not in text
    json_lines("".join(seen) + rest)


def test_rerun_viewer_that_is_closed(tmp_path: Path) -> None:
    """The viewer dies mid-run. Once rerun's send quota is full every rerun call blocks until a
    viewer answers: before the fix the frame loop froze (no output on any sink) and SIGTERM could
    not end the daemon. Depth images at max rate fill the quota within a few seconds."""
    rerun_cli = pytest.importorskip("rerun_cli")
    binary = Path(rerun_cli.__file__).with_name("rerun")
    port = free_tcp_port()
    log_path = tmp_path / "viewer.log"
    with open(log_path, "wb") as log_file:
        viewer = subprocess.Popen(
            [
                str(binary),
                "--bind",
                "127.0.0.1",
                "--port",
                str(port),
                "--save",
                str(tmp_path / "v.rrd"),
            ],
            stdout=log_file,
            stderr=subprocess.STDOUT,
            start_new_session=True,
        )
    try:
        deadline = time.monotonic() + WAIT_S
        while b"Listening for gRPC" not in log_path.read_bytes():
            assert viewer.poll() is None and time.monotonic() < deadline, log_path.read_text()
            time.sleep(0.1)
        err = tmp_path / "err.txt"
        proc = start(
            "run",
            "--device",
            f"{FAST}&loop=1",
            "--sink",
            "stdout",
            "--sink",
            f"rerun+grpc://127.0.0.1:{port}",
            stderr_path=err,
        )
        read_lines(proc, 3)
        os.killpg(viewer.pid, signal.SIGKILL)  # the user closes the viewer (or it crashes)
        viewer.wait(timeout=WAIT_S)
        seen = read_lines(proc, 1000)  # ~0.6 GB of depth images later, the frame loop goes on
        code, rest, _ = finish(proc, timeout=WAIT_S)  # and the daemon still stops
        text = err.read_text()
        assert code == 0, text
        assert "Traceback" not in text
        # whether the viewer's queue fills (frames skipped for it) or rerun drops the data for
        # the gone viewer itself depends on how fast each side runs: either is fine, as long as
        # the sink says what became of its frames and the other sink got every frame
        assert (
            "is not keeping up (gone?); frames skipped for it" in text
            or "frames logged to rerun+http://127.0.0.1" in text
        ), text
        json_lines("".join(seen) + rest)
    finally:
        if viewer.poll() is None:
            os.killpg(viewer.pid, signal.SIGKILL)
            viewer.wait(timeout=10)


def test_rerun_viewer_that_never_came(tmp_path: Path) -> None:
    port = free_tcp_port()  # nothing listens there
    p = depthnav(
        "run",
        "--device",
        f"{FAST}&loop=1",
        "--sink",
        "stdout",
        "--sink",
        f"rerun+grpc://127.0.0.1:{port}",
        "--max-frames",
        "800",
        timeout=120,
    )
    assert p.returncode == 0, p.stderr
    assert [m["seq"] for m in json_lines(p.stdout)] == list(range(800))
    assert "Traceback" not in p.stderr  # and it ended: the 120 s bound above is generous


# --- inputs that go away ----------------------------------------------------------------------
class ReplayWithMotor:
    """Depth from the real replay driver, accelerometer from the real pyusb motor code over the
    emulated 045e:02b0 (tests/drivers/fake_kinect_usb.py), as on a Kinect."""

    def __init__(self, model: KinectMotorModel) -> None:
        self.depth = create_driver(FAST + "&loop=1")
        self.motor = KinectMotor(backend=FakeUsbBackend(model))

    def open(self) -> DeviceInfo:
        self.motor.open()  # DeviceOpenError while unplugged
        return self.depth.open()

    def read_frame(self, timeout_s: float = 1.0) -> Frame | None:
        frame = self.depth.read_frame(timeout_s)
        state = self.motor.read_state()  # DeviceLost on errno 19
        return (
            None
            if frame is None
            else Frame(
                frame.seq, frame.timestamp_s, frame.depth_mm, frame.intrinsics, state.accel_mps2
            )
        )

    def close(self) -> None:
        self.motor.close()
        self.depth.close()


def test_usb_unplug_errno_19_reconnects_with_backoff(caplog: pytest.LogCaptureFixture) -> None:
    model = KinectMotorModel(counts=(0, 790, -212))
    model.unplug_after_reads = 4
    attempts: list[int] = []

    def factory(_spec: str) -> ReplayWithMotor:
        attempts.append(len(attempts))
        if len(attempts) == 4:  # plugged back in after three failed attempts
            model.unplugged, model.unplug_after_reads = False, None
        return ReplayWithMotor(model)

    cfg = build_config(
        [],
        ["daemon.reconnect_backoff_s=0.1", "daemon.reconnect_backoff_max_s=1.0"],
        {"device": "kinect-on-a-bench", "sinks": ["null"]},
    )
    sink = NullSink()
    with caplog.at_level(logging.WARNING, logger="depthnav_daemon"):
        report = run(
            cfg,
            threading.Event(),
            max_frames=10,
            driver_factory=factory,
            sink_factory=lambda _s: sink,
        )
    assert report.frames == 10 and sink.frames == 10 and report.reconnects == 1
    text = caplog.text
    assert (
        "device kinect-on-a-bench lost (the Kinect motor (045e:02b0) went away: unplugged?)" in text
    )
    # the wait doubles after each failed attempt (the daemon's own figures, not a clock)
    assert "reconnect attempt 1 in 0.1 s" in text
    assert "(no Kinect found (045e:02ae/02b0)" in text and "reconnect attempt 2 in 0.2 s" in text
    assert "reconnect attempt 3 in 0.4 s" in text and "device kinect-on-a-bench reconnected" in text


def test_fakenect_recording_that_ends(tmp_path: Path) -> None:
    """The real fakenect library in the child process: the run ends at the end, stdout is pure
    JSON."""
    from drivers.formats.fakenect import write_fakenect
    from drivers.kinect.freenect import find_library

    skip_without(find_library(fakenect=True) is None, "libfreenect0.5")
    write_fakenect(tmp_path / "fk", read_recording(FIXTURE).frames()[:4])
    p = depthnav(
        "run", "--device", f"kinect?fakenect={tmp_path / 'fk'}", "--sink", "stdout", timeout=120
    )
    assert p.returncode == 0, p.stderr
    assert [m["seq"] for m in json_lines(p.stdout)] == [0, 1, 2, 3]
    assert "Traceback" not in p.stderr


def test_disk_full_while_calibrate_writes_the_config(tmp_path: Path) -> None:
    """Before the fix: 'internal error: OSError'. The robot's config must stay as it was."""
    with small_disk(tmp_path, "1m") as (disk, preexec):
        robot = disk / "robot.toml"
        robot.write_text('device = "kinect"\n[scan]\nrange_max_m = 4.0\n')
        robot.chmod(0o644)
        before = robot.read_bytes()
        if preexec is None:  # fill the tmpfs; with the file-size fallback nothing more is needed
            with contextlib.suppress(OSError), open(disk / "filler", "wb") as fh:
                fh.write(b"\0" * (2 << 20))
        p = subprocess.run(
            [
                os.sys.executable,
                "-m",
                "depthnav_daemon",
                "calibrate",
                "--device",
                FAST,
                "--frames",
                "4",
                "--write",
                str(robot),
            ],
            capture_output=True,
            text=True,
            timeout=120,
            cwd=ROOT,
            preexec_fn=preexec,
        )
        assert p.returncode == 1, p.stderr
        line = one_error_line(p.stderr)
        assert str(robot) in line and "the file was not changed" in line
        assert robot.read_bytes() == before
        assert sorted(x.name for x in disk.iterdir() if x.name != "filler") == ["robot.toml"]


def test_stdout_closed_or_full() -> None:
    """A daemon started with stdout closed (>&-) or on a full device (/dev/full)."""
    cmd = [os.sys.executable, "-m", "depthnav_daemon", "run", "--device", FAST, "--max-frames", "3"]
    closed = subprocess.run(
        [*cmd, "--sink", "stdout"],
        stderr=subprocess.PIPE,
        text=True,
        timeout=120,
        cwd=ROOT,
        preexec_fn=lambda: os.close(1),
    )
    assert closed.returncode == 1, closed.stderr
    assert "sink stdout could not start: stdout is closed" in closed.stderr
    assert "no output sink could start" in one_error_line(closed.stderr)
    with open("/dev/full", "w") as full:
        p = subprocess.run(
            [*cmd, "--sink", "stdout", "--sink", "null"],
            stdout=full,
            stderr=subprocess.PIPE,
            text=True,
            timeout=120,
            cwd=ROOT,
        )
    assert p.returncode == 0, p.stderr
    assert (
        "sink stdout failed: writing to stdout failed: [Errno 28] No space left on device"
        in p.stderr
    )
    assert "3 frames processed; dropped sinks: stdout" in p.stderr
    assert "Traceback" not in p.stderr


def test_stdout_reader_that_stalls_does_not_freeze_the_other_outputs(tmp_path: Path) -> None:
    """The consumer of stdout stops reading (hung, SIGSTOPped) without closing the pipe. Before the
    fix the next full pipe blocked the frame loop: the UDP scan (and MAVLink) stopped too."""
    rx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    # room for every datagram while this process waits for a CPU (a loaded 2-core machine lost
    # 14 of them with the default buffer: a gap in seq that was the test's, not the daemon's)
    for opt in (getattr(socket, "SO_RCVBUFFORCE", None), socket.SO_RCVBUF):
        with contextlib.suppress(OSError, TypeError):
            rx.setsockopt(socket.SOL_SOCKET, opt, 16 << 20)
            break
    rx.bind(("127.0.0.1", 0))
    rx.settimeout(WAIT_S)
    err = tmp_path / "err.txt"
    proc = start(
        "run",
        "--device",
        ENDLESS,
        "--sink",
        "stdout",
        "--sink",
        f"udp://127.0.0.1:{rx.getsockname()[1]}",
        stderr_path=err,
    )
    # nobody reads stdout: a 64 KiB pipe holds a handful of lines; the scan must keep coming
    seqs = [json.loads(rx.recv(65535))["seq"] for _ in range(60)]
    rx.close()
    code, out, _ = finish(proc)  # now the reader drains what is there
    text = err.read_text()
    assert code == 0, text
    assert seqs == list(range(60))
    assert "stdout sink: the reader is not reading (stalled?); lines skipped" in text
    lines = json_lines(out)  # whole lines only, in order, with a gap where lines were skipped
    got = [m["seq"] for m in lines]
    assert got == sorted(got) and len(got) < 60
