"""Running as a service: the notify protocol over a real AF_UNIX socket, the shipped unit and
sysusers file checked by systemd's own tools, the udev rules, the log line format, and waiting
for a device that is not there yet."""

from __future__ import annotations

import os
import re
import shutil
import socket
import subprocess
import sys
from pathlib import Path

import pytest

from depthnav_daemon.daemon.notify import ServiceNotifier
from drivers.kinect.motor import VENDOR_MICROSOFT

ROOT = Path(__file__).resolve().parents[2]
FIXTURE = ROOT / "fixtures" / "corridor_step"
UNIT = ROOT / "configs" / "systemd" / "depthnav.service"
SYSUSERS = ROOT / "configs" / "systemd" / "depthnav.sysusers.conf"
RULES = ROOT / "configs" / "udev" / "59-depthnav.rules"
REQUIRE = os.environ.get("DEPTHNAV_REQUIRE_NATIVE") == "1"
RUN = (sys.executable, "-m", "depthnav_daemon", "run", "--device")


def _needs(tool: str) -> str:
    path = shutil.which(tool)
    if path is None:
        if REQUIRE:
            pytest.fail(f"{tool} is missing (apt-get install systemd)")
        pytest.skip(f"{tool} is not installed")
    return path


@pytest.fixture(scope="module", autouse=True)
def warm_kernels() -> None:
    """This user's kernel cache warm, so the daemons below start without a warm-up child (after
    an edit to a kernel that takes a minute or two, once)."""
    proc = subprocess.run(
        [sys.executable, "-m", "depthnav_daemon", "warmup"],
        capture_output=True,
        text=True,
        cwd=ROOT,
        timeout=900,
    )
    assert proc.returncode == 0, proc.stderr


@pytest.fixture
def notify_socket(tmp_path: Path):
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    path = tmp_path / "notify"
    sock.bind(str(path))
    sock.settimeout(30.0)
    yield sock, path
    sock.close()


def _messages(sock: socket.socket) -> list[str]:
    out = []
    sock.settimeout(0.0)
    while True:
        try:
            out.append(sock.recv(4096).decode())
        except BlockingIOError:
            return out


def test_the_daemon_says_ready_pets_the_watchdog_while_frames_flow_and_says_stopping(
    notify_socket,
) -> None:
    sock, path = notify_socket
    env = {**os.environ, "NOTIFY_SOCKET": str(path), "WATCHDOG_USEC": "2"}
    proc = subprocess.run(
        [*RUN, f"replay:{FIXTURE}", "--sink", "null", "--max-frames", "5"],
        capture_output=True,
        text=True,
        env=env,
        cwd=ROOT,
        timeout=120,
    )
    assert proc.returncode == 0, proc.stderr
    got = _messages(sock)
    # start-up steps first (each asking systemd for time), READY=1 once the first frame went out
    ready = next(i for i, m in enumerate(got) if m.startswith("READY=1"))
    assert got[ready].startswith("READY=1\nSTATUS=running on "), got
    assert all("EXTEND_TIMEOUT_USEC=" in m for m in got[:ready] if m.startswith("STATUS=")), got
    assert not any("WATCHDOG=1" in m for m in got[:ready]), got
    assert got[-1].startswith("STOPPING=1\nSTATUS=stopping after 5 frames"), got
    # WATCHDOG_PID is unset, so the 2 us watchdog is ours: petted on frames, between the two
    pets = [m for m in got[ready + 1 : -1] if m == "WATCHDOG=1"]
    assert len(pets) >= 1
    status = [m for m in got if m.startswith("STATUS=") and "frames/s" in m]
    assert status and re.match(r"STATUS=\d+\.\d frames/s, mount 0\.\d{3} m, tilt ", status[0])


def test_no_watchdog_without_frames_and_nothing_outside_systemd(notify_socket) -> None:
    sock, path = notify_socket
    clock = [100.0]
    n = ServiceNotifier({"NOTIFY_SOCKET": str(path), "WATCHDOG_USEC": "4000000"}, lambda: clock[0])
    assert n.watchdog_period_s == 2.0  # half of WatchdogSec, as sd_watchdog_enabled advises
    n.ready("up")
    clock[0] += 10.0  # no frame for 10 s: no WATCHDOG=1, so systemd restarts a stalled loop
    assert _messages(sock) == ["READY=1\nSTATUS=up"]
    n.frame(1, lambda fps: f"{fps:.1f}")
    clock[0] += 1.0
    n.frame(2, lambda fps: f"{fps:.1f}")  # within both periods: nothing
    clock[0] += 4.0
    n.frame(12, lambda fps: f"{fps:.1f}")  # 5 s after the first status: 11 frames in 5 s
    assert _messages(sock) == ["WATCHDOG=1", "STATUS=0.1", "WATCHDOG=1", "STATUS=2.2"]
    n.close()
    quiet = ServiceNotifier({})
    quiet.ready("up")
    quiet.frame(1, str)
    quiet.stopping("bye")
    assert not quiet.enabled and quiet.sent == []


def test_a_watchdog_meant_for_another_process_is_not_ours(notify_socket) -> None:
    _, path = notify_socket
    env = {"NOTIFY_SOCKET": str(path), "WATCHDOG_USEC": "4000000", "WATCHDOG_PID": "1"}
    assert ServiceNotifier(env).watchdog_period_s == 0.0


def test_the_shipped_unit_passes_systemd_analyze_verify(tmp_path: Path) -> None:
    analyze = _needs("systemd-analyze")
    depthnav = Path(sys.executable).with_name("depthnav")
    text = UNIT.read_text()
    assert "Type=notify" in text and "WatchdogSec=" in text and "Restart=on-failure" in text
    assert "NoNewPrivileges=yes" in text and "User=depthnav" in text
    unit = tmp_path / "depthnav.service"
    unit.write_text(text.replace("/opt/depthnav/.venv/bin/depthnav", str(depthnav)))
    proc = subprocess.run(
        [analyze, "verify", str(unit)], capture_output=True, text=True, timeout=60
    )
    # unknown keys are only warnings: a clean unit prints nothing
    assert proc.returncode == 0 and proc.stderr.strip() == "", proc.stderr
    bad = tmp_path / "bad.service"
    bad.write_text(unit.read_text().replace("WatchdogSec=", "WatchdogSecs="))
    proc = subprocess.run([analyze, "verify", str(bad)], capture_output=True, text=True)
    assert "Unknown key" in proc.stderr  # the check above can fail


def test_the_service_user_file_is_valid_for_systemd_sysusers(tmp_path: Path) -> None:
    sysusers = _needs("systemd-sysusers")
    (tmp_path / "etc").mkdir()
    proc = subprocess.run(
        [sysusers, "--dry-run", f"--root={tmp_path}", str(SYSUSERS)],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert proc.returncode == 0, proc.stderr
    assert "Creating user 'depthnav'" in proc.stdout + proc.stderr


def test_udev_rules_give_plugdev_every_sensor_depthnav_opens() -> None:
    rule = re.compile(  # final assignments (":="): see the file's header
        r'SUBSYSTEM=="usb", ATTR\{idVendor\}=="([0-9a-f]{4})"'
        r'(?:, ATTR\{idProduct\}=="([0-9a-f]{4})")?, MODE:="0660", GROUP:="plugdev"'
    )
    # a RealSense's video and IMU (iio) nodes too, matched by the USB device above them
    node = re.compile(
        r'(?:SUBSYSTEM=="video4linux"|KERNEL=="iio\*"), ATTRS\{idVendor\}=="8086", '
        r'MODE:="0660", GROUP:="plugdev"'
    )
    found = set()
    nodes = 0
    for line in RULES.read_text().splitlines():
        if line.strip() and not line.startswith("#"):
            m = rule.fullmatch(line)
            nodes += bool(node.fullmatch(line))
            assert m or node.fullmatch(line), f"not a rule of the expected form: {line}"
            if m:
                found.add((m.group(1), m.group(2)))
    assert ("8086", None) in found and nodes == 2  # Intel RealSense: USB, video, IMU
    microsoft = f"{VENDOR_MICROSOFT:04x}"
    assert {(microsoft, "02ae"), (microsoft, "02b0")} <= found  # Kinect camera and motor
    assert (microsoft, "02c2") in found  # Kinect for Windows' hub (motor, accelerometer)
    assert ("1d27", None) in found  # PrimeSense / Xtion (OpenNI2)


def test_log_lines_carry_a_timestamp_when_stderr_is_not_a_terminal() -> None:
    proc = subprocess.run(
        [*RUN, f"replay:{FIXTURE}", "--sink", "null", "--max-frames", "1"],
        capture_output=True,
        text=True,
        cwd=ROOT,
        timeout=120,
    )
    assert proc.returncode == 0, proc.stderr
    lines = proc.stderr.splitlines()
    assert lines and all(
        re.match(r"\d{4}-\d\d-\d\dT\d\d:\d\d:\d\d\.\d{3} depthnav: [A-Z]+: ", line)
        for line in lines
    ), proc.stderr


def test_under_journald_log_lines_carry_syslog_priorities(tmp_path: Path) -> None:
    err = tmp_path / "stderr"
    with open(err, "w") as fh:
        st = os.fstat(fh.fileno())  # systemd names the journal stream by device:inode
        proc = subprocess.run(
            [*RUN, f"replay:{FIXTURE}", "--sink", "null", "--max-frames", "1"],
            stderr=fh,
            env={**os.environ, "JOURNAL_STREAM": f"{st.st_dev}:{st.st_ino}"},
            cwd=ROOT,
            timeout=120,
        )
    assert proc.returncode == 0
    lines = err.read_text().splitlines()
    assert lines and all(re.match(r"<[2-7]>depthnav: [A-Z]+: ", line) for line in lines), lines
    assert any(line.startswith("<6>depthnav: INFO: ") for line in lines)


def test_waiting_for_a_device_that_never_comes_says_so_then_fails_with_a_hint() -> None:
    proc = subprocess.run(
        [*RUN, "openni://", "--sink", "null", "--set", "daemon.wait_for_device_s=1"],
        capture_output=True,
        text=True,
        cwd=ROOT,
        timeout=120,
    )
    assert proc.returncode == 1, proc.stderr
    assert "waiting for device openni://" in proc.stderr
    assert "depthnav: hint:" in proc.stderr and "Traceback" not in proc.stderr


COMPILE_ONE = """
import logging, sys
import numpy as np
from depthnav_daemon.cli import configure_logging
from depthnav_daemon.commands.common import announce_compiles
from depthnav_daemon.pipeline.pose_kernels import count_candidates_kernel
configure_logging(0, False)
announce_compiles()
z = np.zeros((2, 3), dtype=np.uint16)
print(count_candidates_kernel(np.ones((4, 6), dtype=np.uint16), 0, 2, 0, 2, z, z + 5))
"""


def test_a_cold_kernel_cache_says_compiling_first_run_only_and_a_warm_one_says_nothing(
    tmp_path: Path,
) -> None:
    env = {**os.environ, "NUMBA_CACHE_DIR": str(tmp_path / "cache")}
    runs = [
        subprocess.run(
            [sys.executable, "-c", COMPILE_ONE],
            capture_output=True,
            text=True,
            env=env,
            cwd=ROOT,
            timeout=300,
        )
        for _ in range(2)
    ]
    for proc in runs:
        assert proc.returncode == 0 and proc.stdout.strip() == "6", proc.stderr
    cold, warm = runs[0].stderr, runs[1].stderr
    assert "compiling kernels (first run only" in cold and "compiling kernels: 1/" in cold, cold
    assert "compiling" not in warm, warm
