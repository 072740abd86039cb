"""``python -m depthnav_daemon`` runs the CLI."""

import os
import signal


def _early_stop(signum: int, _frame: object) -> None:
    # a signal while the CLI is still being imported: nothing is open or written yet, so end at
    # once with the CLI's exit codes (0 for SIGTERM and SIGHUP, 130 for SIGINT); raising from
    # inside an import instead gave a KeyboardInterrupt exit (-2) or, once in 16 loaded runs, a
    # hang
    os._exit(130 if signum == signal.SIGINT else 0)


for _sig in (signal.SIGTERM, signal.SIGINT, signal.SIGHUP):
    signal.signal(_sig, _early_stop)

from depthnav_daemon.cli import entry_point  # noqa: E402 - after the handlers, on purpose

entry_point()
