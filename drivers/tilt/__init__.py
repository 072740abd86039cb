"""Tilt sources: attitude from something other than the depth device (an IMU on a serial link,
an autopilot), for sensors without an accelerometer. Not depth drivers: the daemon reads the
latest reading beside each frame.

Specs: ``serialtilt:PORT[?protocol=line|mavlink&baud=N]`` (``serialtilt``).
"""

from __future__ import annotations

import importlib
from dataclasses import dataclass
from typing import Protocol

from drivers.errors import DeviceSpecError
from drivers.spec import parse_spec

TILT_SOURCES: dict[str, tuple[str, str]] = {  # scheme -> (module, class); imported when used
    "serialtilt": ("drivers.tilt.serialtilt", "SerialTiltSource"),
}


@dataclass(frozen=True, slots=True)
class TiltReading:
    """One attitude reading in depthnav's convention (drivers.base)."""

    tilt_deg: float  # positive = pitched down
    roll_deg: float  # positive = left side up
    timestamp_s: float  # host monotonic time of arrival


class TiltSource(Protocol):
    """A background reader of attitude. Constructing it does no I/O; ``start`` opens it."""

    def start(self) -> None:
        """Open the source and start reading (raises DeviceOpenError)."""

    def latest(self, max_age_s: float | None = None) -> TiltReading | None:
        """The newest reading no older than ``max_age_s``, or None (raises DriverError once the
        source is lost)."""

    def stop(self) -> None:
        """Stop reading and close; safe to call twice."""


def create_tilt_source(text: str) -> TiltSource:
    """Build (but do not start) the tilt source named by a spec."""
    scheme = parse_spec(text).scheme
    if scheme not in TILT_SOURCES:
        raise DeviceSpecError(
            f"unknown tilt source {text!r}", hint=f"use one of: {', '.join(sorted(TILT_SOURCES))}"
        )
    module_name, class_name = TILT_SOURCES[scheme]
    return getattr(importlib.import_module(module_name), class_name).from_spec(text)
