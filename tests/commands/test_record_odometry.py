"""``depthnav record --odometry`` and ``depthnav run --odometry`` as a user runs them: a real
JSON-lines odometry peer on loopback UDP, the real CLI in a subprocess."""

from __future__ import annotations

import json
import socket
import threading
from pathlib import Path

import numpy as np

from drivers.formats.recording import read_recording
from tests.test_cli import FIXTURE, depthnav


def _free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class Robot(threading.Thread):
    """Sends odometry lines, x growing ``step_m`` a line (1 mm by default), until stopped."""

    def __init__(self, port: int, step_m: float = 0.001) -> None:
        super().__init__(daemon=True)
        self.port, self.stop, self.step_m = port, threading.Event(), step_m

    def run(self) -> None:
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as tx:
            i = 0
            while not self.stop.wait(0.002):
                line = {"x_m": self.step_m * i, "y_m": 0.5, "yaw_rad": 0.25}
                tx.sendto(json.dumps(line).encode(), ("127.0.0.1", self.port))
                i += 1


def test_record_stores_the_odometry_of_every_frame(tmp_path: Path) -> None:
    port = _free_port()
    robot = Robot(port)
    robot.start()
    try:
        p = depthnav(
            "record",
            "--device",
            f"replay:{FIXTURE}?rate=realtime",
            "--frames",
            "4",
            "--odometry",
            f"odom+udp://127.0.0.1:{port}",
            str(tmp_path / "rec"),
        )
    finally:
        robot.stop.set()
    assert p.returncode == 0, p.stderr
    odom = read_recording(tmp_path / "rec").odom
    assert odom.shape == (4, 3)
    assert (np.diff(odom[:, 0]) > 0).all()  # the robot moved on between frames
    assert (odom[:, 1:] == [0.5, 0.25]).all()


def test_record_with_a_silent_odometry_source_records_without_it(tmp_path: Path) -> None:
    p = depthnav(
        "record",
        "--device",
        f"replay:{FIXTURE}?rate=max",
        "--frames",
        "2",
        "--odometry",
        f"odom+udp://127.0.0.1:{_free_port()}",
        str(tmp_path / "rec"),
    )
    assert p.returncode == 0, p.stderr
    assert read_recording(tmp_path / "rec").odom is None
    said = [x for x in p.stderr.splitlines() if "has sent nothing" in x]
    assert len(said) == 1 and "recording without it" in said[0]


def test_run_with_odometry_outputs_the_memory() -> None:
    # a robot standing still, and odometry counted fresh for 30 s: on a loaded machine a stalled
    # process would otherwise see a "jump" (a moving robot's poses seconds apart) or stale
    # odometry, and the memory would rightly reset or freeze instead of being "on"
    port = _free_port()
    robot = Robot(port, step_m=0.0)
    robot.start()
    try:
        p = depthnav(
            "run",
            "--device",
            f"replay:{FIXTURE}?rate=realtime",
            "--max-frames",
            "4",
            "--odometry",
            f"odom+udp://127.0.0.1:{port}",
            "--set",
            "odometry.stale_s=30",
        )
    finally:
        robot.stop.set()
    assert p.returncode == 0, p.stderr
    memory = [json.loads(x)["memory"] for x in p.stdout.splitlines()]
    on = [m for m in memory if m is not None]
    assert on and all(m["status"] == "on" for m in on)
    assert on[-1]["odom"]["y_m"] == 0.5 and len(on[-1]["scan"]["ranges"]) == 360
    assert on[-1]["cells"]["obstacle"] > 0  # the fixture's boxes and walls
