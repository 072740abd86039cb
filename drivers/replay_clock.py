"""The replay's clock: recorded stamps made into times that always increase.

Looping: pass k of a recording is shifted by k * (latest - first + one frame period), so time goes
on from the end of the pass before whatever epoch the recording's stamps start at (a bag stamped
in UNIX time looped three times stays near its own epoch, not at 2, 3, 4 times it).

Order: a frame whose stamp is not after the last one handed out (a duplicate, a step back) keeps
the last stamp plus ``NUDGE_S``; said once per replay, counted at the end. Sinks (ROS bags,
Foxglove, the memory) then never see time stand still or go back.
"""

from __future__ import annotations

import logging
import time

log = logging.getLogger(__name__)

# A frame whose recorded stamp is not after the last one's gets the last one plus this (s): a
# whole millisecond, so the step survives the JSON line's microseconds and any dt taken from it.
NUDGE_S = 1e-3


class ReplayClock:
    """Loop offsets and increasing stamps of one replay.

    Args:
        name: what the warnings name (the recording's path).
        fps: frame rate (Hz) for the loop gap of a one-frame recording.
    """

    def __init__(self, name: str, fps: float) -> None:
        self.name = name
        self.fps = fps
        self.offset_s = 0.0  # added to this pass's recorded stamps (s)
        self._first: float | None = None  # this pass's first recorded stamp (s)
        self._latest = 0.0  # this pass's latest recorded stamp (s)
        self._count = 0  # recorded items read in this pass
        self.last_s: float | None = None  # the last time handed out (s)
        self.nudged = 0  # frames whose time was moved forward

    def note(self, stamp_s: float) -> None:
        """A recorded item was read (played or skipped): its raw stamp (s)."""
        if self._first is None:
            self._first = self._latest = stamp_s
        else:
            self._latest = max(self._latest, stamp_s)
        self._count += 1

    def next_pass(self) -> None:
        """The recording starts again: shift the next pass by this one's length plus a period."""
        if self._first is None:
            return
        span = self._latest - self._first
        # one frame period: the pass's mean spacing (1/fps for a single frame)
        period = span / (self._count - 1) if self._count > 1 and span > 0 else 1.0 / self.fps
        self.offset_s += span + period
        self._first, self._count = None, 0

    def time(self, stamp_s: float, seq: int, *, shift: bool = True) -> float:
        """The time (s) to hand out for a recorded stamp: shifted by the loop offset (unless
        ``shift`` is off: a driver that loops itself), moved past the last time if not after it."""
        t_s = stamp_s + self.offset_s if shift else stamp_s
        last = self.last_s
        if last is not None and not t_s > last:
            self.nudged += 1
            if self.nudged == 1:
                log.warning(
                    "%s: frame %d is stamped %.6f s, not after the frame before (%.6f s); kept at "
                    "%.6f s so time keeps increasing (said once, counted at the end)",
                    self.name, seq, t_s, last, last + NUDGE_S,
                )  # fmt: skip
            t_s = last + NUDGE_S
        self.last_s = t_s
        return t_s

    def close(self) -> None:
        """Say how many stamps were moved (beyond the one warned about)."""
        if self.nudged > 1:
            log.warning(
                "%s: %d frames' stamps moved forward to keep time increasing",
                self.name,
                self.nudged,
            )
        self.nudged = 0


class Pacer:
    """Sleeps a replay at the recorded rate: anchored at the first frame, each frame waits until
    its recorded time is due on the monotonic clock; never past the read's timeout (a long gap
    in a recording is not a hang: the anchor then shifts). A reader that is late gets the frame
    at once, so no frame is skipped."""

    def __init__(self) -> None:
        self._wall0: float | None = None  # monotonic time of recorded time 0

    def wait(self, t_s: float, timeout_s: float) -> None:
        """Sleep until recorded time ``t_s`` (s) is due, at most ``timeout_s`` (s)."""
        now = time.monotonic()
        if self._wall0 is None:
            self._wall0 = now - t_s
        delay = self._wall0 + t_s - now
        if delay > timeout_s:
            time.sleep(max(timeout_s, 0.0))
            self._wall0 -= delay - timeout_s
        elif delay > 0:
            time.sleep(delay)
