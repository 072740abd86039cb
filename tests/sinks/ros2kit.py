"""Test-only helpers of the ``ros2`` sink: DDS on loopback only, a free domain, and recordings
whose scans differ frame to frame (so a received scan names its frame)."""

from __future__ import annotations

import contextlib
import glob
import hashlib
import importlib.util
import os
import platform
import random
import shutil
import socket
import subprocess
import tempfile
from pathlib import Path

import pytest

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
FASTDDS_SUB = Path(__file__).parent / "fastdds_sub"  # LaserScan.idl, subscriber.cpp, CMakeLists
FASTDDS_TOOLS = "libfastrtps-dev fastddsgen cmake g++"
BUILD_TIMEOUT_S = 600


def require_cyclonedds() -> None:
    """Skip without the cyclonedds package; fail instead under DEPTHNAV_REQUIRE_NATIVE=1 on
    x86_64, where the dev install brings it."""
    if importlib.util.find_spec("cyclonedds") is not None:
        return
    message = "cyclonedds not installed (pip install 'depthnav[ros2]')"
    if os.environ.get("DEPTHNAV_REQUIRE_NATIVE") == "1" and platform.machine() == "x86_64":
        pytest.fail(message + "; DEPTHNAV_REQUIRE_NATIVE=1 forbids skipping", pytrace=False)
    pytest.skip(message)


def _fastrtps_cmake() -> str | None:
    """The Fast DDS CMake package's version file, if libfastrtps-dev is installed."""
    found = sorted(glob.glob("/usr/lib/*/cmake/fastrtps/fastrtps-config-version.cmake"))
    found += sorted(glob.glob("/usr/local/lib/cmake/fastrtps/fastrtps-config-version.cmake"))
    return found[0] if found else None


def fastdds_tools_missing() -> bool:
    return _fastrtps_cmake() is None or not all(
        shutil.which(tool) for tool in ("fastddsgen", "cmake", "c++")
    )


def _run(cmd: list[str], cwd: Path, what: str) -> None:
    p = subprocess.run(
        cmd, cwd=cwd, capture_output=True, text=True, timeout=BUILD_TIMEOUT_S, check=False
    )
    if p.returncode != 0:
        tail = "\n".join((p.stdout + p.stderr).splitlines()[-30:])
        pytest.fail(f"{what} failed ({p.returncode}):\n{tail}", pytrace=False)


def fastdds_subscriber() -> Path:
    """The Fast DDS subscriber of tests/sinks/fastdds_sub, generated with fastddsgen and built
    with cmake once per source and Fast DDS version (cached in the temp folder, built under a
    private name and renamed into place, so parallel runs never see half a build)."""
    key = hashlib.sha256()
    for name in ("LaserScan.idl", "subscriber.cpp", "CMakeLists.txt"):
        key.update((FASTDDS_SUB / name).read_bytes())
    key.update(Path(_fastrtps_cmake() or "").read_bytes())
    home = Path(tempfile.gettempdir()) / f"depthnav-fastdds-sub-{key.hexdigest()[:16]}"
    exe = home / "build" / "subscriber"
    if exe.exists():
        return exe
    work = Path(tempfile.mkdtemp(prefix=home.name + ".building-"))
    try:
        (work / "gen").mkdir()
        _run(
            ["fastddsgen", "-replace", "-d", str(work / "gen"), str(FASTDDS_SUB / "LaserScan.idl")],
            work,
            "fastddsgen",
        )
        _run(
            [
                "cmake", "-S", str(FASTDDS_SUB), "-B", str(work / "build"),
                f"-DGEN_DIR={work / 'gen'}", "-DCMAKE_BUILD_TYPE=Release",
            ],
            work,
            "cmake (configure)",
        )  # fmt: skip
        _run(["cmake", "--build", str(work / "build"), "-j2"], work, "cmake --build")
        try:
            os.rename(work, home)  # atomic; fails if a parallel run got there first
        except OSError:
            shutil.rmtree(work, ignore_errors=True)
    except BaseException:
        shutil.rmtree(work, ignore_errors=True)
        raise
    return exe


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
    rng = random.SystemRandom()
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
