"""``python -m depthnav_daemon`` runs the CLI."""

import os
import signal


def _early_stop(signum: int, _frame: object) -> None:
    # a signal while the CLI is still being imported: nothing is open or written yet, so end at
    # once with the CLI's exit codes (0 for SIGTERM, 130 for SIGINT); raising from inside an
    # import instead gave a KeyboardInterrupt exit (-2) or, once in 16 loaded runs, a hang
    os._exit(0 if signum == signal.SIGTERM else 130)


signal.signal(signal.SIGTERM, _early_stop)
signal.signal(signal.SIGINT, _early_stop)

from depthnav_daemon.cli import entry_point  # noqa: E402 - after the handlers, on purpose

entry_point()
