"""Errors raised by drivers. Every message says what failed; ``hint`` says what to do next.

DriverError(Exception)                  .hint
 ├─ DeviceSpecError                     a device spec that does not parse or names nothing known
 ├─ DriverNotAvailable                  a missing library (libOpenNI2, libfreenect, a pip package)
 ├─ DeviceOpenError                     .reason: OpenFailure (NOT_FOUND, PERMISSION, BUSY, ...)
 ├─ RecordingError                      a recording that is missing, corrupt or truncated
 ├─ FrameTimeout(DriverError, TimeoutError)   no frame within the timeout; the caller may retry
 └─ DeviceLost                          the device went away mid-stream (unplugged, stream error)
"""

from __future__ import annotations

import enum


class DriverError(Exception):
    """Base of every driver error.

    Args:
        message: what failed, one line, fit to show the user.
        hint: what to do next, one line, or None.
    """

    def __init__(self, message: str, hint: str | None = None) -> None:
        super().__init__(message)
        self.hint = hint


class DeviceSpecError(DriverError):
    """A device spec that does not parse, or names an unknown scheme or option."""


class DriverNotAvailable(DriverError):
    """A native library or Python package the driver needs is missing."""


class OpenFailure(enum.Enum):
    """Why a device could not be opened."""

    NOT_FOUND = "not found"
    PERMISSION = "permission denied"
    BUSY = "busy"
    UNSUPPORTED = "unsupported model"
    OTHER = "failed"


class DeviceOpenError(DriverError):
    """The device exists in the spec but could not be opened."""

    def __init__(
        self, message: str, hint: str | None = None, reason: OpenFailure = OpenFailure.OTHER
    ) -> None:
        super().__init__(message, hint)
        self.reason = reason


class RecordingError(DriverError):
    """A recording file or folder is missing, corrupt or truncated."""


class FrameTimeout(DriverError, TimeoutError):
    """No frame arrived within the timeout; the device may still recover."""


class DeviceLost(DriverError):
    """The device stopped for good (unplugged, stream error, end of a native playback)."""
