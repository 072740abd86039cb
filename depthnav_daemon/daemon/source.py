"""The device the frame loop reads: a driver, reopened with backoff when it is lost."""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable

from depthnav_daemon.config.loader import DaemonParams
from depthnav_daemon.errors import DepthnavError
from drivers.base import DeviceInfo, Driver
from drivers.errors import DriverError

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
        self.info = self.driver.open()
        return self.info

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
