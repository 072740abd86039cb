"""Errors of the daemon and the pipeline. Every message says what failed; ``hint`` what to do.

DepthnavError(Exception)     .hint, .exit_code = 1
 ├─ ConfigError              bad parameter, config file or command line (exit_code = 2)
 ├─ FrameError               a depth frame the pipeline cannot use (wrong dtype or shape)
 └─ SinkError                an output failed; the daemon drops that sink and goes on
"""

from __future__ import annotations


class DepthnavError(Exception):
    """Base of every depthnav error; ``exit_code`` is what the CLI returns for it."""

    exit_code = 1

    def __init__(self, message: str, hint: str | None = None) -> None:
        super().__init__(message)
        self.hint = hint


class ConfigError(DepthnavError, ValueError):
    """A parameter, config file or command-line value is invalid."""

    exit_code = 2


class FrameError(DepthnavError, ValueError):
    """A depth frame the pipeline cannot process (wrong dtype, shape or contents)."""


class SinkError(DepthnavError):
    """An output sink failed."""
