"""Start-up under systemd (issue 33 item 6): READY=1 only once the first frame went out, start-up
steps that ask for more time (EXTEND_TIMEOUT_USEC) while they last and no longer than their
budget, and a stop signal honoured within a second at any point of start-up: while waiting for
the device and while the kernels compile (in a child process, killed with it)."""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path

import pytest

from depthnav_daemon.config.loader import build_config
from depthnav_daemon.daemon.loop import run
from depthnav_daemon.daemon.notify import EXTEND_BY_S, ServiceNotifier
from depthnav_daemon.pipeline import Result
from depthnav_daemon.sinks.base import SinkContext
from drivers import create_driver
from drivers.base import DeviceInfo, Frame
from drivers.errors import DeviceOpenError, FrameTimeout

ROOT = Path(__file__).resolve().parents[2]
FIXTURE = ROOT / "fixtures" / "corridor_step"
SPEC = f"replay:{FIXTURE}?rate=max"
RUN = (sys.executable, "-m", "depthnav_daemon", "run", "--sink", "null", "--device")
WATCHDOG_USEC = "10000000"  # the shipped unit's WatchdogSec=10
STOP_WITHIN_S = 1.0


@pytest.fixture
def notify_socket(tmp_path: Path):
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    path = tmp_path / "notify"
    sock.bind(str(path))
    yield sock, path
    sock.close()


class Listener:
    """Every datagram on the test's notify socket, with when it came (monotonic seconds)."""

    def __init__(self, sock: socket.socket) -> None:
        self.sock = sock
        self.got: list[tuple[float, str]] = []
        self._stop = threading.Event()
        sock.settimeout(0.05)
        self.thread = threading.Thread(target=self._read, daemon=True)
        self.thread.start()

    def _read(self) -> None:
        while not self._stop.is_set():
            try:
                data = self.sock.recv(4096)
            except TimeoutError:
                continue
            except OSError:
                return
            self.got.append((time.monotonic(), data.decode()))

    def messages(self) -> list[str]:
        return [m for _, m in self.got]

    def wait_for(self, needle: str, timeout_s: float, count: int = 1) -> float:
        """When the ``count``-th message containing ``needle`` came."""
        end = time.monotonic() + timeout_s
        while time.monotonic() < end:
            hits = [t for t, m in self.got if needle in m]
            if len(hits) >= count:
                return hits[count - 1]
            time.sleep(0.02)
        raise AssertionError(f"no {needle!r} (x{count}) within {timeout_s} s: {self.messages()}")

    def close(self) -> None:
        self._stop.set()
        self.thread.join(1.0)


@pytest.fixture(scope="module")
def warm_cache() -> None:
    """This user's kernel cache marked warm, so a daemon started here compiles nothing (a no-op
    of a second or two when scripts/install.sh already ran)."""
    proc = subprocess.run(
        [sys.executable, "-m", "depthnav_daemon", "warmup"],
        capture_output=True,
        text=True,
        cwd=ROOT,
        timeout=900,
    )
    assert proc.returncode == 0, proc.stderr


class GatedDriver:
    """The corridor recording, held back (FrameTimeout) until the test opens the gate."""

    def __init__(self, gate: threading.Event) -> None:
        self.inner = create_driver(SPEC)
        self.gate = gate

    def open(self) -> DeviceInfo:
        return self.inner.open()

    def read_frame(self, timeout_s: float = 1.0) -> Frame | None:
        if not self.gate.wait(timeout_s):
            raise FrameTimeout("held back by the test")
        return self.inner.read_frame(timeout_s)

    def close(self) -> None:
        self.inner.close()


@dataclass
class ReadySink:
    """Notes, at each frame it is given, whether READY=1 was already sent."""

    notifier: ServiceNotifier
    name: str = "ready-probe"
    ready_at_write: list[bool] = field(default_factory=list)

    def open(self, context: SinkContext) -> None:
        pass

    def write(self, frame: Frame, result: Result) -> None:
        self.ready_at_write.append(any(m.startswith("READY=1") for m in self.notifier.sent))

    def close(self) -> None:
        pass


def test_ready_waits_for_the_first_frame_and_start_up_asks_systemd_for_time(
    notify_socket,
) -> None:
    sock, path = notify_socket
    listener = Listener(sock)
    notifier = ServiceNotifier({"NOTIFY_SOCKET": str(path), "WATCHDOG_USEC": WATCHDOG_USEC})
    notifier.extend_period_s = 0.1  # the shipped 5 s, sped up
    gate = threading.Event()
    sink = ReadySink(notifier)
    cfg = build_config([], [], {"device": SPEC})
    done: list[object] = []
    thread = threading.Thread(
        target=lambda: done.append(
            run(
                cfg,
                threading.Event(),
                max_frames=3,
                driver_factory=lambda _s: GatedDriver(gate),
                sink_factory=lambda _s: sink,
                notifier=notifier,
            )
        )
    )
    thread.start()
    try:
        # the device is open, the sinks too, no frame yet: still starting, asking for time
        listener.wait_for("EXTEND_TIMEOUT_USEC=", 10.0, count=3)
        assert not any("READY=1" in m or "WATCHDOG=1" in m for m in listener.messages())
    finally:
        gate.set()
        thread.join(60.0)
    listener.wait_for("STOPPING=1", 5.0)
    listener.close()
    got = listener.messages()
    assert done and sink.ready_at_write[0] is False  # the first frame went out before READY=1
    assert all(sink.ready_at_write[1:])
    ready = next(i for i, m in enumerate(got) if m.startswith("READY=1\nSTATUS=running on "))
    steps = got[:ready]
    assert steps[0].startswith("STATUS=opening replay:") and "EXTEND_TIMEOUT_USEC=" in steps[0]
    assert any(m.startswith("STATUS=opening the sinks, first frame of ") for m in steps)
    assert f"EXTEND_TIMEOUT_USEC={int(EXTEND_BY_S * 1e6)}" in steps[-1]
    assert "WATCHDOG=1" in got[ready + 1 :]  # the frames after READY pet the watchdog
    # start-up is over: no more extensions after READY=1
    time.sleep(0.3)
    assert not any("EXTEND" in m for m in got[ready + 1 :])


def test_a_start_up_step_asks_for_time_only_within_its_budget(notify_socket) -> None:
    sock, path = notify_socket
    listener = Listener(sock)
    notifier = ServiceNotifier({"NOTIFY_SOCKET": str(path)})
    notifier.extend_period_s = 0.05
    notifier.starting("waiting for a device that never comes", budget_s=0.3)
    time.sleep(0.8)
    count = sum("EXTEND_TIMEOUT_USEC" in m for m in listener.messages())
    assert 3 <= count <= 8  # the first at once, then every 0.05 s until 0.3 s, then none
    time.sleep(0.3)
    assert sum("EXTEND_TIMEOUT_USEC" in m for m in listener.messages()) == count
    notifier.give_up("no device")
    listener.wait_for("STOPPING=1\nSTATUS=no device", 2.0)
    listener.close()
    quiet = ServiceNotifier({})
    quiet.starting("x", 10.0)
    quiet.status("y")
    assert quiet.sent == []


def _daemon(args: list[str], path: Path, env: dict[str, str] | None = None) -> subprocess.Popen:
    return subprocess.Popen(
        [*RUN, *args],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
        text=True,
        cwd=ROOT,
        env={
            **os.environ,
            "NOTIFY_SOCKET": str(path),
            "WATCHDOG_USEC": WATCHDOG_USEC,
            **(env or {}),
        },
    )


def _stop(proc: subprocess.Popen) -> tuple[float, int, str]:
    """SIGTERM: (seconds until the process ended, its exit code, its stderr)."""
    t0 = time.monotonic()
    proc.send_signal(signal.SIGTERM)
    try:
        code = proc.wait(timeout=30)
    finally:
        proc.kill()
    took = time.monotonic() - t0
    return took, code, proc.stderr.read() if proc.stderr else ""


def test_sigterm_while_waiting_for_the_device_ends_start_up_within_a_second(
    notify_socket, warm_cache
) -> None:
    sock, path = notify_socket
    listener = Listener(sock)
    proc = _daemon(["openni://", "--set", "daemon.wait_for_device_s=600"], path)
    listener.wait_for("STATUS=opening openni://\nEXTEND_TIMEOUT_USEC=", 60.0)
    time.sleep(1.0)  # inside the wait's backoff
    took, code, err = _stop(proc)
    listener.wait_for("STOPPING=1", 2.0)
    listener.close()
    print(f"SIGTERM while waiting for the device: exit after {took:.2f} s")  # noqa: T201
    assert code == 0 and took < STOP_WITHIN_S, (took, err)
    assert "waiting for device openni://" in err and "Traceback" not in err
    assert not any("READY=1" in m for m in listener.messages())


def _children_with(marker: str) -> list[int]:
    """Processes whose environment holds ``marker`` (the test's own cache folder)."""
    out = []
    for p in Path("/proc").iterdir():
        if not p.name.isdigit():
            continue
        try:
            if marker.encode() in (p / "environ").read_bytes():
                out.append(int(p.name))
        except OSError:
            continue
    return out


def test_sigterm_while_the_kernels_compile_ends_start_up_within_a_second(
    notify_socket, tmp_path: Path
) -> None:
    sock, path = notify_socket
    listener = Listener(sock)
    cache = tmp_path / "empty-kernel-cache"  # a fresh install: nothing compiled
    proc = _daemon([SPEC], path, {"NUMBA_CACHE_DIR": str(cache)})
    listener.wait_for("STATUS=compiling kernels (first run only)\nEXTEND_TIMEOUT_USEC=", 60.0)
    listener.wait_for("STATUS=compiling kernels 1/", 120.0)  # the child is compiling
    took, code, err = _stop(proc)
    listener.wait_for("STOPPING=1", 2.0)
    listener.close()
    print(f"SIGTERM during the compile: exit after {took:.2f} s")  # noqa: T201
    assert code == 0 and took < STOP_WITHIN_S, (took, err)
    assert "compiling kernels into" in err and "warm-up: compiling kernels: 1/" in err, err
    assert "Traceback" not in err
    assert not any("READY=1" in m for m in listener.messages())
    time.sleep(0.2)
    assert _children_with(str(cache)) == []  # the compiling child went with it


class AbsentDriver:
    """A sensor that is not plugged in yet."""

    def __init__(self, spec: str) -> None:
        self.spec = spec

    def open(self) -> DeviceInfo:
        raise DeviceOpenError(f"{self.spec}: no such device", hint="plug it in")

    def read_frame(self, timeout_s: float = 1.0) -> Frame | None:
        raise AssertionError("never opened")

    def close(self) -> None:
        pass


@pytest.mark.parametrize("sensors", [1, 2])
def test_a_stop_while_waiting_for_the_sensors_ends_the_run_within_a_second(
    notify_socket, sensors: int
) -> None:
    sock, path = notify_socket
    listener = Listener(sock)
    notifier = ServiceNotifier({"NOTIFY_SOCKET": str(path), "WATCHDOG_USEC": WATCHDOG_USEC})
    over: dict[str, object] = {"daemon": {"wait_for_device_s": 600.0}}
    if sensors == 1:
        over["device"] = "absent:0"
    else:
        over["sensor"] = [{"name": f"s{i}", "device": f"absent:{i}"} for i in range(sensors)]
    stop = threading.Event()
    reports: list[object] = []
    thread = threading.Thread(
        target=lambda: reports.append(
            run(build_config([], [], over), stop, driver_factory=AbsentDriver, notifier=notifier)
        )
    )
    thread.start()
    listener.wait_for("EXTEND_TIMEOUT_USEC=", 10.0)
    time.sleep(0.5)
    t0 = time.monotonic()
    stop.set()
    thread.join(5.0)
    took = time.monotonic() - t0
    listener.wait_for("STOPPING=1", 2.0)
    listener.close()
    assert not thread.is_alive() and took < STOP_WITHIN_S, took
    assert reports and reports[0].stopped and reports[0].frames == 0  # a stop, not a failure
