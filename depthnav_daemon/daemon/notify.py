"""The systemd notify protocol, spoken by the daemon itself (no extra dependency).

Under a ``Type=notify`` unit systemd sets ``NOTIFY_SOCKET``; the daemon sends, as single datagrams:
while it starts, ``STATUS=`` and ``EXTEND_TIMEOUT_USEC=`` every few seconds for each step that may
take long (waiting for the device, compiling the kernels, the first frame; each step within its
own budget, so a start-up that hangs still meets ``TimeoutStartSec=``); ``READY=1`` once the
first frame went out; then ``STATUS=...`` (frame rate and mount) every few seconds, ``WATCHDOG=1``
only while frames flow (so a stalled loop is restarted under ``WatchdogSec=``; none before
READY=1, which would start systemd's watchdog early), and ``STOPPING=1`` when it stops. Outside
systemd every call does nothing.

The protocol is a few lines over an AF_UNIX datagram socket (sd_notify(3)); a path starting with
``@`` is in the abstract namespace.
"""

from __future__ import annotations

import logging
import os
import socket
import threading
from collections.abc import Callable, Mapping

log = logging.getLogger(__name__)

STATUS_PERIOD_S = 5.0
# while a start-up step lasts: EXTEND_TIMEOUT_USEC every EXTEND_PERIOD_S, each asking for
# EXTEND_BY_S more (three periods: one late message is no failure)
EXTEND_PERIOD_S = 5.0
EXTEND_BY_S = 15.0
# the start-up steps' budgets: opening a device that is there (USB enumeration, a firmware
# upload; on top of [daemon] wait_for_device_s), and the sinks' opening (a ROS 2 participant, a
# viewer) with the first frame's tables
OPEN_MARGIN_S = 30.0
FIRST_FRAME_S = 60.0


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
        self._lock = threading.RLock()  # the start-up thread sends too
        self.is_ready = False
        self.extend_period_s = EXTEND_PERIOD_S
        self._step_until = 0.0  # the current start-up step's budget ends (clock seconds)
        self._started: threading.Event | None = None  # set when start-up is over
        self.sent: list[str] = []  # what was sent, for the summary and tests

    @property
    def enabled(self) -> bool:
        """True under systemd (a notify socket was given)."""
        return self._address is not None

    def starting(self, status: str, budget_s: float) -> None:
        """A start-up step that may take long begins (it ends with the next step, ``ready`` or
        ``stopping``): says ``status``, and asks systemd to wait, again every few seconds, for
        at most ``budget_s``.
        """
        if not self.enabled or self.is_ready:
            return
        with self._lock:
            self._step_until = self._clock() + budget_s
            if self._started is None:
                self._started = threading.Event()
                threading.Thread(
                    target=self._extend, args=(self._started,), name="systemd start-up", daemon=True
                ).start()
        self._send(f"STATUS={status}\nEXTEND_TIMEOUT_USEC={int(EXTEND_BY_S * 1e6)}")

    def status(self, status: str) -> None:
        """Say how a start-up step goes (``STATUS=`` only)."""
        self._send(f"STATUS={status}")

    def _extend(self, started: threading.Event) -> None:
        """The start-up thread: EXTEND_TIMEOUT_USEC while the step's budget lasts."""
        while not started.wait(self.extend_period_s):
            with self._lock:  # never after READY=1 or STOPPING=1 (they set ``started`` first)
                if not started.is_set() and self._clock() < self._step_until:
                    self._send(f"EXTEND_TIMEOUT_USEC={int(EXTEND_BY_S * 1e6)}")

    def _start_up_over(self) -> None:
        with self._lock:
            if self._started is not None:
                self._started.set()

    def ready(self, status: str) -> None:
        """The first frame went out: start-up is over."""
        self._start_up_over()
        self.is_ready = True
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
        self._start_up_over()
        self._send(f"STOPPING=1\nSTATUS={status}")

    def give_up(self, why: str) -> None:
        """Start-up failed before the frame loop: say so, and stop asking systemd to wait."""
        self.stopping(why)
        self.close()

    def close(self) -> None:
        self._start_up_over()
        with self._lock:
            if self._sock is not None:
                self._sock.close()
                self._sock = None

    def _send(self, message: str) -> None:
        with self._lock:
            if self._address is None:
                return
            try:
                if self._sock is None:
                    self._sock = socket.socket(
                        socket.AF_UNIX, socket.SOCK_DGRAM | socket.SOCK_CLOEXEC
                    )
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
