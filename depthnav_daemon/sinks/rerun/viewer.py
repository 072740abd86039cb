"""Checking that a rerun viewer listens before the rerun sink connects to it: rerun's own connect
never fails (with nothing listening it retries in the background and the frames go nowhere)."""

from __future__ import annotations

import socket
from urllib.parse import urlsplit

from depthnav_daemon.errors import SinkError

DEFAULT_GRPC = ("127.0.0.1", 9876)
PROBE_TIMEOUT_S = 2.0  # connecting to and hearing from a viewer at start
# the HTTP/2 client connection preface and an empty SETTINGS frame (RFC 9113 3.4, 6.5)
H2_PREFACE = b"PRI * HTTP/2.0\r\n\r\nSM\r\n\r\n" + b"\x00\x00\x00\x04\x00\x00\x00\x00\x00"
H2_FRAME_HEADER = 9  # bytes: length (3), type, flags, stream id (4)
H2_SETTINGS = 0x04  # frame type, the 4th byte of a frame header


def check_viewer(url: str, timeout_s: float = PROBE_TIMEOUT_S) -> None:
    """Check that a rerun viewer (a gRPC server: HTTP/2) listens at ``url`` before connecting.

    rerun's own connect never fails: with nothing listening it retries in the background, the
    frames go nowhere, and the run ends claiming them logged. An HTTP/2 server answers the
    client preface with a SETTINGS frame; anything else (refused, silent, HTTP/1) is not a viewer.

    Raises:
        SinkError: nothing listens, it does not answer, or it is not a gRPC server.
    """
    parts = urlsplit(url)
    host, port = parts.hostname or DEFAULT_GRPC[0], parts.port or DEFAULT_GRPC[1]
    where = f"{host}:{port}"
    hint = (
        f"start a viewer there (rerun --port {port}), or save to a file with --sink rerun:FILE.rrd"
    )
    try:
        with socket.create_connection((host, port), timeout=timeout_s) as sock:
            sock.sendall(H2_PREFACE)
            answer = b""
            while len(answer) < H2_FRAME_HEADER:
                chunk = sock.recv(H2_FRAME_HEADER - len(answer))
                if not chunk:
                    break
                answer += chunk
    except TimeoutError:
        raise SinkError(
            f"rerun sink: the server at {where} does not answer (no rerun viewer)", hint=hint
        ) from None
    except OSError as exc:
        raise SinkError(
            f"rerun sink: no rerun viewer at {where} ({exc.strerror or exc})", hint=hint
        ) from None
    if len(answer) < H2_FRAME_HEADER or answer[3] != H2_SETTINGS:
        raise SinkError(
            f"rerun sink: the server at {where} is not a rerun viewer (it does not speak gRPC)",
            hint=hint,
        )
