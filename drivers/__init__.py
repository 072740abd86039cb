"""Depth sensor drivers: one module per backend, chosen by a device spec string.

Specs (each driver module's docstring gives its full grammar and options):

    kinect | kinect://<index>[?accel=usb|freenect|none&lib=PATH&fakenect=DIR]   Kinect 360 (1414)
    openni:// | openni://<uri> | openni:<file.oni>[?mode=WxH@FPS&rate=..&loop=..]  OpenNI2
    replay:<path>[?rate=realtime|max&loop=0|1&...]                               recorded frames
    realsense[://<serial>][?mode=WxH@FPS&preset=..] | realsense?file=REC.db3     Intel RealSense

This package never imports depthnav_daemon.
"""

from __future__ import annotations

import contextlib
import importlib
import logging
import threading
from collections.abc import Iterator

from drivers.base import Driver, Frame
from drivers.errors import DeviceSpecError, DriverError, DriverNotAvailable
from drivers.spec import Spec, parse_spec

log = logging.getLogger(__name__)

__all__ = [
    "DRIVERS",
    "create_driver",
    "describe_backends",
    "detect_devices",
    "iter_frames",
    "opened",
    "parse_spec",
]

DRIVERS: dict[str, tuple[str, str]] = {  # scheme -> (module, class); imported only when used
    "kinect": ("drivers.kinect.driver", "KinectDriver"),
    "openni": ("drivers.openni.driver", "OpenNIDriver"),
    "replay": ("drivers.replay", "ReplayDriver"),
    "realsense": ("drivers.realsense.driver", "RealSenseDriver"),
}
ALIASES = {"xtion": "openni://"}
PIP_PACKAGES = {"openni": "openni", "usb": "pyusb", "serial": "pyserial", "PIL": "pillow"}


def _driver_class(scheme: str, text: str) -> type:
    if scheme not in DRIVERS:
        known = ", ".join(sorted([*DRIVERS, *ALIASES]))
        raise DeviceSpecError(
            f"unknown device scheme {scheme!r} in {text!r}", hint=f"use one of: {known}"
        )
    module_name, class_name = DRIVERS[scheme]
    try:
        module = importlib.import_module(module_name)
    except ModuleNotFoundError as exc:
        top = (exc.name or "").split(".")[0]
        if top not in PIP_PACKAGES:  # a bug in our own code: let it surface
            raise
        raise DriverNotAvailable(
            f"the {scheme!r} driver needs the Python package {PIP_PACKAGES[top]!r}",
            hint=f"pip install {PIP_PACKAGES[top]}",
        ) from exc
    cls: type = getattr(module, class_name)
    return cls


def create_driver(spec: str) -> Driver:
    """Build (but do not open) the driver named by a device spec.

    Raises:
        DeviceSpecError: unknown scheme or option (the message lists the valid ones).
        DriverNotAvailable: the driver's Python package is missing.
    """
    parsed: Spec = parse_spec(ALIASES.get(spec.strip(), spec) if isinstance(spec, str) else spec)
    driver: Driver = _driver_class(parsed.scheme, parsed.text).from_spec(parsed)  # type: ignore[attr-defined]
    return driver


@contextlib.contextmanager
def opened(driver: Driver) -> Iterator[Driver]:
    """Open a driver for the duration of a ``with`` block; always closes it."""
    driver.open()
    try:
        yield driver
    finally:
        driver.close()


def iter_frames(
    driver: Driver, stop_event: threading.Event | None = None, timeout_s: float = 1.0
) -> Iterator[Frame]:
    """Yield frames from an open driver until it ends (None) or ``stop_event`` is set.

    A ``FrameTimeout`` propagates to the caller, which decides whether to retry.
    """
    while stop_event is None or not stop_event.is_set():
        frame = driver.read_frame(timeout_s)
        if frame is None:
            return
        yield frame


def detect_devices() -> list[tuple[str, str]]:
    """Devices that can be opened here, as (spec, description); never raises."""
    found: list[tuple[str, str]] = []
    for scheme in DRIVERS:
        try:
            detect = getattr(_driver_class(scheme, scheme), "detect", None)
            if detect is not None:
                found.extend(detect())
        except Exception:  # discovery must never fail the command
            log.debug("device detection for %s failed", scheme, exc_info=True)
    return found


def describe_backends() -> list[tuple[str, str]]:
    """Each backend's availability, as (backend, status), for ``depthnav info``; never raises."""
    out: list[tuple[str, str]] = []
    for scheme in DRIVERS:
        try:
            status = getattr(_driver_class(scheme, scheme), "backend_status", None)
            out.extend(status() if status else [(scheme, "available")])
        except DriverError as exc:
            out.append((scheme, f"missing: {exc}"))
        except Exception as exc:  # `depthnav info` reports, never fails
            log.debug("backend status for %s failed", scheme, exc_info=True)
            out.append((scheme, f"error: {exc}"))
    out.append(("serialtilt", _serial_tilt_status()))
    return out


def _serial_tilt_status() -> str:
    try:
        import pymavlink
        import serial
    except ImportError as exc:
        return f"missing: {exc.name} (pip install pyserial pymavlink)"
    return f"pyserial {serial.VERSION}, pymavlink {getattr(pymavlink, '__version__', '?')}"
