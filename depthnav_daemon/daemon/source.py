"""The device the frame loop reads: a driver, reopened with backoff when it is lost."""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable

from depthnav_daemon.config.loader import DaemonParams
from depthnav_daemon.errors import DepthnavError
from drivers.base import DeviceInfo, Driver
from drivers.errors import DeviceLost, DeviceOpenError, DriverError, DriverNotAvailable

log = logging.getLogger(__name__)


class DeviceSource:
    """The driver plus reconnect-with-backoff when it is lost."""

    def __init__(
        self,
        spec: str,
        params: DaemonParams,
        stop: threading.Event,
        factory: Callable[[str], Driver],
    ) -> None:
        self.spec = spec
        self._cfg = params
        self._stop = stop
        self._factory = factory
        self.driver: Driver = factory(spec)
        self.info: DeviceInfo | None = None
        self.reconnects = 0

    def open(self) -> DeviceInfo:
        """Open the device; with ``wait_for_device_s``, wait for it with backoff and say so.

        Raises:
            DriverError: it cannot be opened (within the wait), or a stop came meanwhile.
        """
        deadline = time.monotonic() + self._cfg.wait_for_device_s
        backoff = max(self._cfg.reconnect_backoff_s, 0.1)
        while True:
            try:
                self.info = self.driver.open()
                return self.info
            except (DeviceOpenError, DeviceLost, DriverNotAvailable) as exc:
                left = deadline - time.monotonic()
                if left <= 0 or self._stop.is_set():
                    raise
                wait = min(backoff, left)
                log.warning(
                    "waiting for device %s (%s); trying again in %.1f s, for %.0f s more",
                    self.spec,
                    str(exc).splitlines()[0],
                    wait,
                    left,
                )
                if self._stop.wait(wait):
                    raise
                backoff = min(backoff * 2, max(self._cfg.reconnect_backoff_max_s, 0.1))
                self.close()
                self.driver = self._factory(self.spec)

    def close(self) -> None:
        try:
            self.driver.close()
        except DriverError as exc:
            log.warning("closing %s: %s", self.spec, exc)

    def reconnect(self, why: str) -> bool:
        """Close and reopen the device with backoff; False when stopped meanwhile."""
        self.close()
        backoff = self._cfg.reconnect_backoff_s
        attempt = 0
        while not self._stop.is_set():
            attempt += 1
            limit = self._cfg.reconnect_attempts
            if limit and attempt > limit:
                raise DepthnavError(
                    f"device {self.spec} lost ({why}) and {limit} reconnect attempts failed",
                    hint="check the cable and power; depthnav devices lists what can be opened",
                )
            log.warning(
                "device %s lost (%s); reconnect attempt %d in %.1f s",
                self.spec,
                why,
                attempt,
                backoff,
            )
            if self._stop.wait(backoff):
                return False
            try:
                self.driver = self._factory(self.spec)
                self.open()
            except DriverError as exc:
                why = str(exc)
                backoff = min(max(backoff * 2, 0.1), self._cfg.reconnect_backoff_max_s)
                continue
            self.reconnects += 1
            log.warning("device %s reconnected", self.spec)
            return True
        return False
