"""The systemd notify protocol, spoken by the daemon itself (no extra dependency).

Under a ``Type=notify`` unit systemd sets ``NOTIFY_SOCKET``; the daemon sends, as single datagrams:
``READY=1`` once the device and the sinks are open, ``STATUS=...`` (frame rate and mount) every
few seconds, ``WATCHDOG=1`` only while frames flow (so a stalled loop is restarted under
``WatchdogSec=``), and ``STOPPING=1`` when it stops. Outside systemd every call does nothing.

The protocol is a few lines over an AF_UNIX datagram socket (sd_notify(3)); a path starting with
``@`` is in the abstract namespace.
"""

from __future__ import annotations

import logging
import os
import socket
from collections.abc import Callable, Mapping

log = logging.getLogger(__name__)

STATUS_PERIOD_S = 5.0


class ServiceNotifier:
    """Tells systemd how the daemon is; every method is a no-op without ``NOTIFY_SOCKET``.

    Args:
        environ: the process environment (``NOTIFY_SOCKET``, ``WATCHDOG_USEC``, ``WATCHDOG_PID``).
        clock: monotonic seconds.
    """

    def __init__(
        self, environ: Mapping[str, str] = os.environ, clock: Callable[[], float] | None = None
    ) -> None:
        import time

        self._clock = clock or time.monotonic
        self._address = _address(environ.get("NOTIFY_SOCKET", ""))
        self._sock: socket.socket | None = None
        self.watchdog_period_s = _watchdog_period_s(environ)
        self._next_watchdog = 0.0
        self._next_status = 0.0
        self._frames_at_status = 0
        self._status_t = 0.0
        self.sent: list[str] = []  # what was sent, for the summary and tests

    @property
    def enabled(self) -> bool:
        """True under systemd (a notify socket was given)."""
        return self._address is not None

    def ready(self, status: str) -> None:
        """The device and the sinks are open: start-up is over."""
        now = self._clock()
        self._status_t, self._next_status = now, now  # the first frame says the mount at once
        self._send(f"READY=1\nSTATUS={status}")

    def frame(self, frames: int, status: Callable[[float], str]) -> None:
        """A frame went out: pet the watchdog when due, and say how it goes every few seconds.

        Args:
            frames: frames processed so far.
            status: the status line for a frame rate (frames per second).
        """
        if not self.enabled:
            return
        now = self._clock()
        if self.watchdog_period_s and now >= self._next_watchdog:
            self._next_watchdog = now + self.watchdog_period_s
            self._send("WATCHDOG=1")
        if now >= self._next_status:
            elapsed = now - self._status_t
            fps = (frames - self._frames_at_status) / elapsed if elapsed > 0 else 0.0
            self._frames_at_status, self._status_t = frames, now
            self._next_status = now + STATUS_PERIOD_S
            self._send(f"STATUS={status(fps)}")

    def stopping(self, status: str) -> None:
        """The daemon is stopping (a signal, the end of a recording, a failure)."""
        self._send(f"STOPPING=1\nSTATUS={status}")

    def close(self) -> None:
        if self._sock is not None:
            self._sock.close()
            self._sock = None

    def _send(self, message: str) -> None:
        if self._address is None:
            return
        try:
            if self._sock is None:
                self._sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM | socket.SOCK_CLOEXEC)
            self._sock.sendto(message.encode(), self._address)
            self.sent.append(message)
        except OSError as exc:
            # systemd gone or the socket full: the daemon's job goes on, say so once
            log.warning("systemd notify socket: %s; no more notifications", exc)
            self._address = None


def _address(path: str) -> str | bytes | None:
    """The socket address of ``NOTIFY_SOCKET``: a path, or ``@name`` in the abstract namespace."""
    if not path:
        return None
    if path.startswith("@"):
        return b"\0" + path[1:].encode()
    if not path.startswith("/"):
        log.warning("NOTIFY_SOCKET=%r is not a socket path; not notifying systemd", path[:100])
        return None
    return path


def _watchdog_period_s(environ: Mapping[str, str]) -> float:
    """Half of ``WATCHDOG_USEC`` (sd_watchdog_enabled(3)'s advice), 0 when off or not for us."""
    usec = environ.get("WATCHDOG_USEC", "")
    pid = environ.get("WATCHDOG_PID", "")
    if not usec.isascii() or not usec.isdigit() or (pid and pid != str(os.getpid())):
        return 0.0
    return int(usec) / 2e6
