"""Hardening round 3 (issue 35 classes 9 and 12): start-up with standard fds closed, and stop
signals during the ``depthnav`` console script's own imports.

Every case runs the CLI in a child process.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path

import pytest

from tests.faults.kit import FAST, FIXTURE, ROOT, json_lines, signal_at_import

CONSOLE_SCRIPT = Path(sys.executable).with_name("depthnav")

# command -> arguments (OUT is replaced by a path in the test's folder); fast ones only: bench
# and warmup time and compile things, their start-up is the same code
COMMANDS: dict[str, list[str]] = {
    "run": ["run", "--device", FAST, "--sink", "stdout", "--max-frames", "2"],
    "replay": ["replay", str(FIXTURE), "--sink", "stdout", "--max-frames", "2"],
    "calibrate": ["calibrate", "--device", FAST, "--frames", "3", "--json"],
    "record": ["record", "--device", FAST, "--frames", "2", "OUT"],
    "mount": ["mount", "--height-m", "0.5", "--tilt-deg", "10"],
    "snapshot": ["snapshot", "--device", FAST, "OUT.png"],
    "devices": ["devices"],
    "info": ["info"],
}
PRINTS = {"run", "replay", "calibrate", "mount", "info"}  # their result goes to stdout
CASES = [(c, 2) for c in COMMANDS] + [(c, 1) for c in ("run", "calibrate", "mount", "record")]
CASES += [(c, 0) for c in ("run", "record")]


def _closing(fd: int) -> Callable[[], None]:
    def close() -> None:
        os.close(fd)

    return close


@pytest.mark.parametrize(("command", "fd"), CASES, ids=[f"{c}-fd{fd}" for c, fd in CASES])
def test_a_command_with_a_standard_fd_closed(tmp_path: Path, command: str, fd: int) -> None:
    """Found: ``2>&-`` made every command exit 1 with nothing on stdout (sys.stderr is None;
    AttributeError before main's guard). A closed fd is now /dev/null for depthnav's own files'
    sake; a closed stdout is still said to the stdout sink and the printing commands."""
    args = [a.replace("OUT", str(tmp_path / "out")) for a in COMMANDS[command]]
    proc = subprocess.run(
        [sys.executable, "-m", "depthnav_daemon", *args],
        stdin=subprocess.DEVNULL,
        capture_output=True,
        text=True,
        cwd=ROOT,
        timeout=180,
        preexec_fn=_closing(fd),
    )
    err = proc.stderr
    assert "Traceback" not in err and "internal error" not in err, err
    if fd == 1 and command == "run":  # the stdout sink cannot start: one line, exit 1
        assert proc.returncode == 1
        assert "stdout is closed" in err and err.count("error:") == 1
        return
    assert proc.returncode == 0, err
    if fd == 2:
        assert err == ""  # it went to /dev/null
        if command in ("run", "replay"):
            assert [m["seq"] for m in json_lines(proc.stdout)] == [0, 1]
        elif command in PRINTS:
            assert proc.stdout.strip()
    if fd == 1 and command in PRINTS:
        assert "stdout is closed: what this command prints is lost" in err
    if command == "record":  # depthnav's files never took the closed fd's number
        from drivers.formats.recording import read_recording

        assert read_recording(tmp_path / "out").depth_mm.shape[0] == 2
    if command == "snapshot":
        assert (tmp_path / "out.png").read_bytes().startswith(b"\x89PNG")


@pytest.mark.skipif(not CONSOLE_SCRIPT.exists(), reason="depthnav is not installed as a script")
@pytest.mark.parametrize(
    ("module", "sig", "code"),
    [("numpy", signal.SIGTERM, 0), ("numpy", signal.SIGINT, 130), ("drivers", signal.SIGHUP, 0)],
    ids=["TERM-in-numpy", "INT-in-numpy", "HUP-in-drivers"],
)
def test_a_stop_signal_in_the_console_scripts_imports(module: str, sig: int, code: int) -> None:
    """Found: SIGTERM or SIGINT in the first 0.2-0.25 s killed ``depthnav`` by the signal (20 of
    20 at 0.20 s): the console script imports depthnav_daemon.cli before entry_point() installs
    the start-up handlers, and cli imported drivers (numpy) at its top. It now imports only the
    standard library there; the signal comes from an import hook at the first import of
    ``module``, the same point every run."""
    proc = subprocess.run(
        [str(CONSOLE_SCRIPT), "run", "--device", FAST, "--sink", "stdout", "--max-frames", "2"],
        capture_output=True,
        text=True,
        cwd=ROOT,
        timeout=120,
        env=signal_at_import(module, sig),
    )
    assert proc.returncode == code, (proc.returncode, proc.stderr)
    assert proc.stdout == ""  # stopped before anything was opened
    assert "Traceback" not in proc.stderr and "Exception ignored" not in proc.stderr
