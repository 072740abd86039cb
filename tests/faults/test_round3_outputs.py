"""Hardening round 3 (issue 35 class 13, issue 32 item 6): a sink asked for that never started
is said at the end of the run; the foxglove server's log of hostile clients is rate-limited.

Every case runs the CLI in a child process against real peers (a second daemon on the same
``.rrd``, a websocket client and raw TCP connections on loopback).
"""

from __future__ import annotations

import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest

from tests.faults.kit import (
    ENDLESS,
    FAST,
    ROOT,
    WAIT_S,
    finish,
    free_tcp_port,
    json_lines,
    read_lines,
    start,
)

pytestmark = pytest.mark.filterwarnings("ignore:connect\\(\\) must be used:DeprecationWarning")


def test_a_sink_that_never_started_is_said_at_the_end(tmp_path: Path) -> None:
    """Found: a second daemon writing the same .rrd logged "going on without it" among its
    start-up lines and ended 0, its summary silent. The run still goes on (exit 0: the other
    outputs served every frame); its last lines say the sink never ran, in the summary too."""
    rrd = tmp_path / "run.rrd"
    first = start("run", "--device", ENDLESS, "--sink", f"rerun:{rrd}", "--sink", "stdout")
    try:
        read_lines(first, 1)  # its sinks are open: the .rrd is locked
        second = subprocess.run(
            [sys.executable, "-m", "depthnav_daemon", "run", "--device", FAST,
             "--sink", f"rerun:{rrd}", "--sink", "stdout", "--max-frames", "3"],
            capture_output=True, text=True, cwd=ROOT, timeout=120,
        )  # fmt: skip
    finally:
        code, _, err = finish(first)
    assert code == 0, err
    assert second.returncode == 0, second.stderr
    assert [m["seq"] for m in json_lines(second.stdout)] == [0, 1, 2]
    lines = second.stderr.splitlines()
    assert any(f"sink rerun:{rrd} could not start" in x for x in lines), second.stderr
    never = [x for x in lines if f"WARNING: sink rerun:{rrd} never ran" in x]
    assert len(never) == 1, second.stderr
    assert "another process is writing" in never[0] and "3 frames went to the other" in never[0]
    assert f"3 frames processed; dropped sinks: rerun:{rrd} (never started)" in lines[-1]


def _client_flood(port: int, messages: int, handshakes: int) -> None:
    """One client that sends ``messages`` of each invalid kind, then ``handshakes`` raw TCP
    connections that send HTTP without the websocket upgrade."""
    from websockets.sync.client import connect

    deadline = time.monotonic() + WAIT_S
    while True:
        try:
            ws = connect(
                f"ws://127.0.0.1:{port}",
                subprotocols=["foxglove.sdk.v1"],  # type: ignore[list-item]
                ping_interval=None,
                open_timeout=WAIT_S,
            )
            break
        except OSError:
            assert time.monotonic() < deadline, "the foxglove server did not start"
            time.sleep(0.05)
    from websockets.exceptions import ConnectionClosed

    try:
        for i in range(messages):
            ws.send(f"not json {i}\x1b[31m")  # ESC: quoted back by the server's error
            ws.send(b"\xff\x00 unknown binary opcode")
        ws.close()
    except ConnectionClosed:
        pass  # the server may drop such a client; its lines are what is checked
    for _ in range(handshakes):
        with socket.create_connection(("127.0.0.1", port), timeout=WAIT_S) as raw:
            raw.sendall(b"GET / HTTP/1.1\r\nHost: x\r\n\r\n")
            raw.recv(100)


def test_foxglove_logs_each_kind_of_bad_client_once_with_a_count() -> None:
    """Found: 20,000 log lines for one client (each invalid message), one per failed
    handshake. Now each kind is logged once per 10 s, the rest counted at the end."""
    port = free_tcp_port()
    proc = start("run", "--device", ENDLESS, "--sink", f"foxglove://127.0.0.1:{port}",
                 "--sink", "stdout")  # fmt: skip
    try:
        read_lines(proc, 1)
        _client_flood(port, 500, 30)
        read_lines(proc, 5)  # the frame loop goes on
    finally:
        code, rest, err = finish(proc, signal.SIGTERM)
    assert code == 0, err
    assert "Traceback" not in err
    invalid = [x for x in err.splitlines() if "Invalid message from" in x]
    failed = [x for x in err.splitlines() if "handshake failed" in x]
    assert 1 <= len(invalid) <= 2 and 1 <= len(failed) <= 2, err
    assert "\x1b" not in err  # escaped
    counts = [x for x in err.splitlines() if "from clients were not shown" in x]
    held = sum(int(x.split("foxglove sink: ")[1].split()[0]) for x in counts)
    # the server reads a few hundred of the 1000 invalid messages before it drops the client
    assert held >= 100, err
    assert len(err.splitlines()) < 40, err
    json_lines(rest)  # stdout stayed whole
