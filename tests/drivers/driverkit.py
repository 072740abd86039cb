"""Test-only helpers for the driver tests: small synthetic frames with asymmetric intrinsics."""

from __future__ import annotations

import math
import os
import socket
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from drivers.base import Frame, Intrinsics
from drivers.formats.fakenect import disparity_to_mm_table

REPO = Path(__file__).resolve().parents[2]

# Asymmetric on purpose (fx != fy, cx != W/2, H != W) so swapped axes fail.
SMALL = Intrinsics(64, 48, 61.5, 57.25, 30.25, 22.75)
VGA = Intrinsics(640, 480, 583.0, 575.5, 318.25, 243.75)


def ramp_frames(
    n: int = 4, intr: Intrinsics = SMALL, seed: int = 7, accel: bool = True
) -> list[Frame]:
    """``n`` frames: random uint16 depth (fixed seed), a few holes, 30 fps timestamps."""
    rng = np.random.default_rng(seed)
    frames = []
    for i in range(n):
        depth = rng.integers(400, 9000, size=(intr.height, intr.width), dtype=np.uint16)
        depth[rng.random(depth.shape) < 0.05] = 0
        tilt = math.radians(5.0 + i)
        acc = (0.1 * i, -9.81 * math.cos(tilt), -9.81 * math.sin(tilt)) if accel else None
        frames.append(
            Frame(seq=i, timestamp_s=i / 30.0, depth_mm=depth, intrinsics=intr, accel_mps2=acc)
        )
    return frames


def kinect_exact_frames(n: int = 3, intr: Intrinsics = VGA, seed: int = 11) -> list[Frame]:
    """VGA frames whose depths are all exact 11-bit disparity depths, so every format is
    lossless."""
    rng = np.random.default_rng(seed)
    table = disparity_to_mm_table()
    raw = rng.integers(300, 1050, size=(n, intr.height, intr.width))
    raw[rng.random(raw.shape) < 0.05] = 2047
    depth = table[raw].astype(np.uint16)
    return [
        Frame(
            seq=i,
            timestamp_s=i / 30.0,
            depth_mm=depth[i],
            intrinsics=intr,
            accel_mps2=(0.0, -9.7, -1.4),
        )
        for i in range(n)
    ]


def run_isolated(
    code: str, *args: str, env: dict[str, str] | None = None, timeout_s: float = 60.0
) -> subprocess.CompletedProcess[str]:
    """Run Python code in a child process, so a native crash fails one test, not the run."""
    full_env = {
        **os.environ,
        "PYTHONPATH": str(REPO),
        **(env or {}),
    }
    return subprocess.run(
        [sys.executable, "-c", code, *args],
        capture_output=True,
        text=True,
        timeout=timeout_s,
        env=full_env,
        cwd=str(REPO),
    )


def contract_report(spec: str, max_frames: int = 8, timeout_s: float = 5.0) -> dict:
    """Run one driver through the Driver contract and report what it did (no assertions here).

    Kept free of pytest so it can run in a child process for native backends.
    """
    import hashlib

    import drivers
    from drivers.errors import DriverError

    report: dict = {"spec": spec, "frames": [], "problems": []}
    driver = drivers.create_driver(spec)
    info = driver.open()
    report["info"] = {
        "name": info.name,
        "spec": info.spec,
        "has_accel": info.has_accel,
        "intrinsics": None
        if info.intrinsics is None
        else list((info.intrinsics.width, info.intrinsics.height)),
    }
    try:
        for _ in range(max_frames):
            frame = driver.read_frame(timeout_s)
            if frame is None:
                report["ended"] = True
                report["after_end"] = driver.read_frame(timeout_s) is None
                break
            depth = frame.depth_mm
            if depth.dtype != np.uint16 or depth.shape != (
                frame.intrinsics.height,
                frame.intrinsics.width,
            ):
                report["problems"].append(f"frame {frame.seq}: {depth.dtype} {depth.shape}")
            if depth.flags.writeable:
                report["problems"].append(f"frame {frame.seq}: depth is writeable")
            if info.intrinsics is not None and frame.intrinsics != info.intrinsics:
                report["problems"].append(f"frame {frame.seq}: intrinsics differ from open()")
            if frame.accel_mps2 is not None:
                if not info.has_accel:
                    report["problems"].append(
                        f"frame {frame.seq}: accel but open() said has_accel=False"
                    )
                norm = math.sqrt(sum(a * a for a in frame.accel_mps2))
                if len(frame.accel_mps2) != 3 or not 5.0 <= norm <= 15.0:
                    report["problems"].append(
                        f"frame {frame.seq}: implausible accel {frame.accel_mps2}"
                    )
            report["frames"].append(
                {
                    "seq": frame.seq,
                    "t": frame.timestamp_s,
                    "sha": hashlib.sha256(depth.tobytes()).hexdigest()[:16],
                    "accel": frame.accel_mps2 is not None,
                }
            )
    finally:
        driver.close()
        driver.close()
    try:
        driver.read_frame(0.1)
        report["problems"].append("read_frame after close() did not raise")
    except DriverError:
        pass
    return report


CONTRACT_CHILD = """
import json, sys
from tests.drivers.driverkit import contract_report
print(json.dumps(contract_report(sys.argv[1], int(sys.argv[2]))))
"""


def contract_report_isolated(spec: str, max_frames: int = 8) -> dict:
    """:func:`contract_report` in a child process (for native backends)."""
    import json

    proc = run_isolated(CONTRACT_CHILD, spec, str(max_frames), timeout_s=120.0)
    if proc.returncode != 0:
        raise AssertionError(f"{spec}: child exited {proc.returncode}: {proc.stderr[-2000:]}")
    return json.loads(proc.stdout.strip().splitlines()[-1])


def skip_without(missing: bool, package: str, install: str | None = None) -> None:
    """Skip when a native package (or other outside part: ``install`` says how to get it) is
    missing, or fail if DEPTHNAV_REQUIRE_NATIVE=1 (CI sets it: there it must be present)."""
    if not missing:
        return
    import pytest

    message = f"{package} not installed ({install or f'apt-get install {package}'})"
    if os.environ.get("DEPTHNAV_REQUIRE_NATIVE") == "1":
        pytest.fail(message + "; DEPTHNAV_REQUIRE_NATIVE=1 forbids skipping", pytrace=False)
    pytest.skip(message)


def wait_until(pred, timeout_s: float = 10.0) -> None:
    """Poll ``pred`` every 10 ms until it is true; fail the test after ``timeout_s``."""
    end = time.monotonic() + timeout_s
    while not pred():
        assert time.monotonic() < end, "timed out"
        time.sleep(0.01)


def free_udp_port() -> int:
    """A UDP port on 127.0.0.1 that nothing is bound to now."""
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]
