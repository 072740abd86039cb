"""Sinks that cannot start, through the CLI as a user meets them: each failure said once, "going on
without it" only when another sink did start, and a rerun viewer that is not there (nothing
listening, or an HTTP server) refused in one line instead of "N frames logged"."""

from __future__ import annotations

import http.server
import os
import threading
from collections.abc import Iterator

import pytest

from tests.faults.kit import FAST, depthnav, free_tcp_port, one_error_line

pytest.importorskip("rerun")
NO_PORT = "mavlink:/nonexistent/ttyDEPTHNAV"
HEADLESS = {k: v for k, v in os.environ.items() if k not in ("DISPLAY", "WAYLAND_DISPLAY")}
RUST_LOG_MARKS = ("\x1b[", "re_grpc_client", "re_sdk", " WARN ", " ERROR ")


def run_sinks(*sinks: str, frames: int = 3):
    args = ["run", "--device", FAST, "--max-frames", str(frames)]
    for s in sinks:
        args += ["--sink", s]
    return depthnav(*args, env=HEADLESS)


def no_rust_lines(stderr: str) -> None:
    assert not any(mark in stderr for mark in RUST_LOG_MARKS), stderr


def test_the_only_sink_failing_is_one_error_line() -> None:
    p = run_sinks(NO_PORT)
    assert p.returncode == 1, p.stderr
    line = one_error_line(p.stderr)
    assert f"sink {NO_PORT} could not start" in line and "no output sink could start" in line
    assert "going on without it" not in p.stderr
    # said once, in words: pyserial's message repeated the path three times
    assert [ln for ln in p.stderr.splitlines() if "ttyDEPTHNAV" in ln] == [line]
    assert "cannot open serial port '/nonexistent/ttyDEPTHNAV': No such file or directory" in line
    assert "hint: check the port name" in p.stderr


def test_every_sink_failing_names_each_once_and_never_goes_on() -> None:
    p = run_sinks(NO_PORT, "rerun")  # a missing serial port, and no display to spawn a viewer on
    assert p.returncode == 1, p.stderr
    assert "going on without it" not in p.stderr
    assert p.stderr.count(f"sink {NO_PORT} could not start") == 1
    assert p.stderr.count("sink rerun could not start: rerun sink: no display") == 1
    assert "no output sink could start (2 tried, see above)" in one_error_line(p.stderr)


def test_a_failing_sink_beside_a_working_one_is_left_out() -> None:
    p = run_sinks(NO_PORT, "null")
    assert p.returncode == 0, p.stderr
    assert p.stderr.count("going on without it") == 1
    assert "3 frames processed" in p.stderr and "error:" not in p.stderr


def test_rerun_grpc_with_nothing_listening() -> None:
    port = free_tcp_port()
    p = run_sinks(f"rerun+grpc://127.0.0.1:{port}", frames=12)
    assert p.returncode == 1, p.stderr
    line = one_error_line(p.stderr)
    assert f"no rerun viewer at 127.0.0.1:{port}" in line and "Connection refused" in line
    assert f"rerun --port {port}" in p.stderr  # the hint
    assert "frames logged" not in p.stderr
    no_rust_lines(p.stderr)
    # beside another sink: left out in one line, the run goes on
    p = run_sinks(f"rerun+grpc://127.0.0.1:{port}", "null")
    assert p.returncode == 0, p.stderr
    assert p.stderr.count("going on without it") == 1 and "frames logged" not in p.stderr
    no_rust_lines(p.stderr)


@pytest.fixture
def http_server() -> Iterator[int]:
    """A plain HTTP/1 server on loopback: something listens, but it is no rerun viewer."""
    server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), http.server.SimpleHTTPRequestHandler)
    thread = threading.Thread(target=server.serve_forever, daemon=True)
    thread.start()
    yield server.server_address[1]
    server.shutdown()
    server.server_close()


def test_rerun_grpc_at_an_http_server(http_server: int) -> None:
    p = run_sinks(f"rerun+grpc://127.0.0.1:{http_server}", frames=12)
    assert p.returncode == 1, p.stderr
    line = one_error_line(p.stderr)
    assert f"the server at 127.0.0.1:{http_server} is not a rerun viewer" in line
    assert "frames logged" not in p.stderr
    no_rust_lines(p.stderr)
