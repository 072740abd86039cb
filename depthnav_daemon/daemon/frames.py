"""The device's frames for a frame loop (loop.py, and each sensor's thread in multi.py), with
reconnects: a device that falls silent or is lost is reopened with backoff until it comes back,
the reconnects run out or the loop is stopped."""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Iterator

from depthnav_daemon.config.loader import Config
from depthnav_daemon.daemon.report import RunReport
from depthnav_daemon.daemon.source import DeviceSource
from drivers.base import Frame
from drivers.errors import DriverError, FrameTimeout, RecordingError

log = logging.getLogger(__name__)

POLL_S = 0.25  # longest a read blocks, so a stop request is seen within a second


def frames_of(
    source: DeviceSource, cfg: Config, stop: threading.Event, report: RunReport
) -> Iterator[tuple[Frame, float]]:
    """The device's frames, each with its host arrival time (monotonic seconds), until it ends or
    ``stop`` is set; reconnects a silent or lost device."""
    d = cfg.daemon
    last_frame_wall = time.monotonic()
    while not stop.is_set():
        try:
            frame = source.driver.read_frame(timeout_s=min(d.frame_timeout_s, POLL_S))
        except FrameTimeout:
            silent = time.monotonic() - last_frame_wall
            if silent > d.frame_timeout_s * d.max_consecutive_timeouts:
                if not source.reconnect(f"no frame for {silent:.1f} s"):
                    return
                last_frame_wall = time.monotonic()
            continue
        except RecordingError:
            # a bad file does not heal by reopening it: replaying it again would repeat the
            # frames before the bad one forever, so a damaged recording ends the run
            raise
        except DriverError as exc:
            if not source.reconnect(str(exc)):
                return
            last_frame_wall = time.monotonic()
            continue
        if frame is None:
            log.info("end of %s after %d frames", cfg.device, report.frames)
            return
        last_frame_wall = time.monotonic()
        yield frame, last_frame_wall
