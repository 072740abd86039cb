"""Test-only helpers of the ``ros2`` sink: DDS on loopback only, a free domain, and recordings
whose scans differ frame to frame (so a received scan names its frame)."""

from __future__ import annotations

import contextlib
import os
import random
import socket
from pathlib import Path

from depthnav_daemon.sim.synthetic import Box, Scene, render, step_down
from drivers.base import KINECT_V1, Frame, tilt_roll_to_accel
from drivers.formats.recording_writer import write_recording
from tests.sinks.roskit import MOUNT

# Cyclone DDS on 127.0.0.1 only: lo has no multicast, so discovery goes to unicast peers (the
# well-known ports of participant indices 0..20 on 127.0.0.1)
CYCLONE_LOOPBACK = (
    "<CycloneDDS><Domain Id='any'><General>"
    "<Interfaces><NetworkInterface address='127.0.0.1'/></Interfaces>"
    "<AllowMulticast>false</AllowMulticast></General>"
    "<Discovery><ParticipantIndex>auto</ParticipantIndex>"
    "<MaxAutoParticipantIndex>20</MaxAutoParticipantIndex>"
    "<Peers><Peer address='127.0.0.1'/></Peers></Discovery>"
    "</Domain></CycloneDDS>"
)
PORTS_PER_DOMAIN = 250  # RTPS: port = 7400 + 250 * domain + offsets (participant index * 2)


def loopback_env() -> dict[str, str]:
    """The environment of a child process that speaks DDS on loopback only."""
    env = dict(os.environ)
    env["CYCLONEDDS_URI"] = CYCLONE_LOOPBACK
    env.pop("ROS_DOMAIN_ID", None)
    return env


def _udp_free(port: int) -> bool:
    with contextlib.closing(socket.socket(socket.AF_INET, socket.SOCK_DGRAM)) as s:
        try:
            s.bind(("127.0.0.1", port))
        except OSError:
            return False
    return True


def free_domain() -> int:
    """A DDS domain in 100..232 whose discovery and user ports on 127.0.0.1 are all free (others
    on this machine may be running DDS tests at the same time)."""
    rng = random.Random(os.getpid())
    for _ in range(200):
        domain = rng.randint(100, 232)
        base = 7400 + PORTS_PER_DOMAIN * domain
        if all(_udp_free(base + offset) for offset in range(0, 60)):
            return domain
    raise RuntimeError("no free DDS domain in 100..232 on 127.0.0.1")


def varied_recording(path: Path, n: int = 8, size: tuple[int, int] = (320, 240)) -> Path:
    """Frames whose scans all hold NaN, +inf and -inf (as roskit.special_recording), with a wall
    that is 5 cm further away each frame, so no two frames have the same scan."""
    intr = KINECT_V1.scaled(*size)
    frames = []
    for i in range(n):
        scene = Scene(
            boxes=(Box(0.3, 0.25, 0.1, 0.1, 0.4), Box(2.0 + 0.05 * i, 0.0, 0.1, 1.0, 1.0)),
            holes=(step_down(1.4, 0.3, half_width_m=0.4),),
        )
        depth = render(scene, intr, MOUNT).depth_mm.copy()
        depth[:, int(size[0] * 0.8) : int(size[0] * 0.85)] = 0  # no reading: NaN bearings
        accel = tilt_roll_to_accel(MOUNT.tilt_deg, MOUNT.roll_deg)
        frames.append(Frame(i, 0.5 + i / 15.0, depth, intr, accel_mps2=accel))
    write_recording(path, frames, description="a wall moving away; NaN, +inf and -inf")
    return path
