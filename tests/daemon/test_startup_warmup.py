"""The warm-up covers what the daemon runs (so a warmed service compiles nothing at its first
frame), and a start with an empty kernel cache under the shipped unit's settings never outlives
systemd's patience: it asks for time while the child compiles, READY=1 comes with the first
frame, the watchdog after it (issue 33 item 6, "What it must show")."""

from __future__ import annotations

import os
import re
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

from depthnav_daemon.config.loader import build_config
from depthnav_daemon.daemon.loop import run
from depthnav_daemon.pipeline._jit import KERNELS
from depthnav_daemon.tools.warmup import warm_up
from tests.daemon.test_startup_notify import Listener, notify_socket  # noqa: F401 - a fixture

ROOT = Path(__file__).resolve().parents[2]
FIXTURES = ROOT / "fixtures"
CORRIDOR = f"replay:{FIXTURES / 'corridor_step'}?rate=max"
DRIVE = f"replay:{FIXTURES / 'drive_step'}?rate=max"  # a recording with odometry: memory on
UNIT = ROOT / "configs" / "systemd" / "depthnav.service"
PLACED = {"height_m": 0.55, "tilt_deg": 15.0, "x_m": 0.2, "y_m": -0.1, "yaw_deg": 20.0}


def _signatures() -> dict[str, int]:
    return {f"{k.py_func.__module__}.{k.py_func.__name__}": len(k.signatures) for k in KERNELS}


def test_after_the_warm_up_the_daemon_compiles_nothing() -> None:
    """Real recordings through the real drivers (read-only frames), the paths only the daemon
    reaches: a placed mount, the memory with expiry, several sensors, the paper scan."""
    warm_up()  # loads from this user's cache, or compiles once
    before = _signatures()
    runs = [
        {"device": CORRIDOR},
        {"device": DRIVE, "mount": PLACED, "memory": {"max_age_s": 2.0}},
        {"device": CORRIDOR, "scan": {"method": "paper"}, "mount": PLACED},
        {
            "sensor": [
                {"name": "front", "device": CORRIDOR, "mount": PLACED},
                {"name": "side", "device": DRIVE, "mount": {**PLACED, "yaw_deg": -60.0}},
            ]
        },
    ]
    for extra in runs:
        report = run(build_config([], [], {"sinks": ["null"], **extra}), threading.Event())
        assert report.frames >= 5
    grew = {k: (before.get(k), n) for k, n in _signatures().items() if n != before.get(k)}
    assert grew == {}, f"compiled after the warm-up (add the case to tools/warmup.py): {grew}"


def _all_kernels() -> list:
    """Every kernel of every stage module (KERNELS after importing them all)."""
    import importlib
    import pkgutil

    from depthnav_daemon import pipeline

    for mod in pkgutil.iter_modules(pipeline.__path__):
        importlib.import_module(f"{pipeline.__name__}.{mod.name}")
    return list(KERNELS)


def _unit_settings() -> dict[str, str]:
    text = UNIT.read_text()
    env = dict(re.findall(r"^Environment=(\w+)=(.*)$", text, re.M))
    keys = dict(re.findall(r"^(WatchdogSec|TimeoutStartSec)=(\d+)$", text, re.M))
    return {**env, **keys}


@pytest.mark.slow
def test_an_empty_kernel_cache_under_the_shipped_unit_never_outlives_the_start_timeout(
    notify_socket,  # noqa: F811 - the fixture
    tmp_path: Path,
) -> None:
    unit = _unit_settings()
    sock, path = notify_socket
    listener = Listener(sock)
    cache = tmp_path / "numba"  # the unit's NUMBA_CACHE_DIR, empty: a fresh install
    env = {
        **os.environ,
        "NOTIFY_SOCKET": str(path),
        "WATCHDOG_USEC": str(int(unit["WatchdogSec"]) * 1_000_000),
        "NUMBA_CACHE_DIR": str(cache),
    }
    spec = f"replay:{FIXTURES / 'corridor_step'}?rate=realtime&loop=1"
    argv = [sys.executable, "-m", "depthnav_daemon", "run", "--device", spec, "--sink", "null"]
    t0 = time.monotonic()
    proc = subprocess.Popen(argv, stderr=subprocess.PIPE, text=True, env=env, cwd=ROOT)
    try:
        ready_t = listener.wait_for("READY=1", 1200.0)
        listener.wait_for("WATCHDOG=1", 15.0)
        time.sleep(1.0)
    finally:
        proc.terminate()
        proc.wait(30)
        listener.close()
    err = proc.stderr.read() if proc.stderr else ""
    # systemd's start timeout as the messages move it: TimeoutStartSec from the start, each
    # EXTEND_TIMEOUT_USEC to that long after it came; READY=1 must come before it runs out
    deadline = t0 + int(unit["TimeoutStartSec"])
    for t, message in listener.got:
        assert t < deadline, f"systemd would have killed it {t - deadline:.1f} s before {message!r}"
        if message.startswith("READY=1"):
            break
        m = re.search(r"EXTEND_TIMEOUT_USEC=(\d+)", message)
        if m:
            deadline = max(deadline, t + int(m[1]) / 1e6)
    before = [m for t, m in listener.got if t < ready_t]
    assert not any("WATCHDOG=1" in m for m in before)  # systemd's watchdog starts with READY
    compile_s = ready_t - t0
    print(f"empty cache: READY=1 after {compile_s:.1f} s")  # noqa: T201
    assert compile_s > int(unit["TimeoutStartSec"]) / 10  # it did compile, in the child:
    assert "warm-up: compiling kernels: 1/" in err and "kernels compiled in" in err, err
    # ... and not in the daemon itself
    assert "compiling kernels (first run only" not in err
    assert not re.search(r"depthnav: INFO: compiling kernels: \d", err), err
    # every kernel there is went into the cache (a kernel added to the stages but not to the
    # warm-up would compile at the first frame it reaches): numba's index file per kernel
    cached = {p.name for p in cache.rglob("*.nbi")}
    missing = [
        f"{k.py_func.__module__}.{k.py_func.__qualname__}"
        for k in _all_kernels()
        if not any(
            n.startswith(f"{k.py_func.__module__.rsplit('.', 1)[1]}.{k.py_func.__qualname__}-")
            for n in cached
        )
    ]
    assert missing == [], f"not warmed (add them to tools/warmup.py): {missing}"
    # the next start finds the cache warm: no child, READY within seconds
    again = subprocess.run(
        [*argv, "--max-frames", "3"],
        capture_output=True,
        text=True,
        env=env,
        cwd=ROOT,
        timeout=120,
    )
    assert again.returncode == 0 and "warm-up:" not in again.stderr, again.stderr
