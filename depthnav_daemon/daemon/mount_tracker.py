"""The live mount: configured first, then the accelerometer or a serial tilt source, then the floor.

The original's three tools were never wired together; here the floor pose estimate feeds the scan
and cliff stages. A configured mount is used until a tilt sensor or the floor says better; floor
estimates are smoothed; an estimate that jumps beyond a bound is logged and held back until several
consecutive estimates agree with each other (the sensor really was moved).

Every confident floor estimate also checks the mount in use (:meth:`MountTracker.check_floor`):
the tracker's :meth:`~MountTracker.trust` says where the mount came from, whether the floor
confirms it, and whether drop-offs computed with it can be trusted (a wrong mount turns the floor
itself into a "drop-off").

A mount nobody configured is not known at all until the floor gives one
(:attr:`MountTracker.confirmed`): its trust says so (``trusted`` False), the daemon searches every
plausible mount for the floor meanwhile (``frame_step.pose_prior``) and reports every range as
unknown.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass

from depthnav_daemon.config.loader import DaemonParams
from depthnav_daemon.pipeline import MountTrust
from depthnav_daemon.pipeline.geometry import MAX_ROLL_DEG, MAX_TILT_DEG, Mount

log = logging.getLogger(__name__)


_DAEMON = DaemonParams()  # the defaults of the fields below live there, once
_DEFAULT_MOUNT = Mount()


@dataclass(frozen=True, slots=True, kw_only=True)
class TrackerParams:
    """See DaemonParams for the meaning of each field."""

    smoothing: float = _DAEMON.pose_smoothing
    max_jump_m: float = _DAEMON.max_jump_m
    max_jump_deg: float = _DAEMON.max_jump_deg
    confirmations: int = _DAEMON.jump_confirmations
    # the applied mount follows the smoothed one only beyond this, so the stages' lookup tables
    # (built per mount, ~0.1 s) are not rebuilt for sub-millimetre wobble
    deadband_m: float = 0.002
    deadband_deg: float = 0.1

    @classmethod
    def from_daemon(cls, d: DaemonParams) -> TrackerParams:
        """The tracker's part of the daemon's configuration."""
        return cls(
            smoothing=d.pose_smoothing,
            max_jump_m=d.max_jump_m,
            max_jump_deg=d.max_jump_deg,
            confirmations=d.jump_confirmations,
        )


def _distance(a: Mount, b: Mount) -> tuple[float, float]:
    """(height difference m, largest angle difference deg) between two mounts."""
    return abs(a.height_m - b.height_m), max(
        abs(a.tilt_deg - b.tilt_deg), abs(a.roll_deg - b.roll_deg)
    )


def _level(m: Mount) -> tuple[float, float, float]:
    return (m.height_m, m.tilt_deg, m.roll_deg)


def _clamped(like: Mount, height_m: float, tilt_deg: float, roll_deg: float) -> Mount:
    """``like``'s placement on the robot with this height, tilt and roll (clamped to range)."""
    return like.with_level(
        min(max(height_m, 0.01), 10.0),
        min(max(tilt_deg, -MAX_TILT_DEG), MAX_TILT_DEG),
        min(max(roll_deg, -MAX_ROLL_DEG), MAX_ROLL_DEG),
    )


class MountTracker:
    """Holds the mount the stages use and where it came from ("config", "accel", "serial",
    "floor")."""

    def __init__(self, configured: Mount, params: TrackerParams, *, pinned: bool = False) -> None:
        self.mount = configured
        self._smoothed = configured
        self.source = "config"
        self._params = params
        self._floor_seen = False
        self._pending: list[Mount] = []
        self.rejected = 0
        # nobody configured a mount: the built-in 0.5 m / 0 deg is a guess, not a measurement
        # (pinned, it is what the user asked for)
        self._default = not pinned and _level(configured) == _level(_DEFAULT_MOUNT)
        self._pinned = pinned
        self._floor = "unknown"
        self._floor_mount: Mount | None = None  # the floor's estimate while it contradicts
        # trust()'s last answer and what it rested on: (mount, floor mount, source, floor, trust)
        self._last_trust: tuple[Mount, Mount | None, str, str, MountTrust] | None = None

    @property
    def confirmed(self) -> bool:
        """Whether the mount is known: configured (or pinned), or given by the floor. False while
        nobody configured it and no confident floor estimate has been taken; once True, it stays
        True (later floor estimates only refine or move a known mount)."""
        return not self._default or self._floor_seen

    def check_floor(self, height_m: float, tilt_deg: float, roll_deg: float) -> None:
        """Compare a confident floor estimate with the mount in use (after :meth:`from_floor` has
        taken it, if it does): within ``max_jump_m`` / ``max_jump_deg`` it confirms the mount,
        beyond them it contradicts it (a pinned mount, or a jump not yet accepted)."""
        est = _clamped(self.mount, height_m, tilt_deg, roll_deg)
        dh, da = _distance(est, self.mount)
        agrees = dh <= self._params.max_jump_m and da <= self._params.max_jump_deg
        self._floor = "confirmed" if agrees else "contradicted"
        self._floor_mount = None if agrees else est

    def trust(self) -> MountTrust:
        """The current verdict on the mount in use (frozen: the same object while nothing it
        rests on changes; making it anew every frame cost ~2 % of the frame loop)."""
        last = self._last_trust
        if (
            last is not None
            and last[0] is self.mount
            and last[1] is self._floor_mount
            and last[2] == self.source
            and last[3] == self._floor
        ):
            return last[4]
        trust = self._trust()
        self._last_trust = (self.mount, self._floor_mount, self.source, self._floor, trust)
        return trust

    def _trust(self) -> MountTrust:
        source = "default" if self.source == "config" and self._default else self.source
        floor, est, m = self._floor, self._floor_mount, self.mount
        if floor == "confirmed":
            return MountTrust(source=source, pinned=self._pinned, floor=floor)
        if est is not None:
            return MountTrust(
                source=source,
                pinned=self._pinned,
                floor=floor,
                floor_height_m=est.height_m,
                floor_tilt_deg=est.tilt_deg,
                floor_roll_deg=est.roll_deg,
                dropoffs_trusted=False,
                note=(
                    f"the floor says height {est.height_m:.2f} m, tilt {est.tilt_deg:.1f} deg, "
                    f"roll {est.roll_deg:.1f} deg but the mount in use is {m.height_m:.2f} m, "
                    f"{m.tilt_deg:.1f} deg, {m.roll_deg:.1f} deg ({source}"
                    f"{', pinned' if self._pinned else ''}): drop-offs are not trusted"
                ),
            )
        if not self.confirmed:
            return MountTrust(
                source=source,
                pinned=self._pinned,
                floor=floor,
                dropoffs_trusted=False,
                trusted=False,
                note=(
                    f"the mount is not configured (the built-in height {m.height_m:.2f} m, "
                    + (
                        f"tilt from the {source}"
                        if source in ("accel", "serial")
                        else f"tilt {m.tilt_deg:.1f} deg"
                    )
                    + ") and the floor has not given it yet: mount unconfirmed, every range "
                    "unknown and drop-offs not trusted until it does "
                    "(set [mount] or run depthnav calibrate)"
                ),
            )
        return MountTrust(source=source, pinned=self._pinned, floor=floor)

    def from_tilt_sensor(self, tilt_deg: float, roll_deg: float, source: str) -> None:
        """Use a tilt sensor's reading (accelerometer or serial IMU) until the floor gives a pose.

        The sensor gives tilt and roll only; the height stays as configured.
        """
        if self._floor_seen or not (math.isfinite(tilt_deg) and math.isfinite(roll_deg)):
            return
        if self.source != source:
            log.info("mount tilt %.1f deg, roll %.1f deg from the %s", tilt_deg, roll_deg, source)
            self._apply(_clamped(self.mount, self.mount.height_m, tilt_deg, roll_deg), force=True)
        else:  # smooth sensor noise
            a = self._params.smoothing
            m = self._smoothed
            self._apply(
                _clamped(
                    m,
                    m.height_m,
                    m.tilt_deg + a * (tilt_deg - m.tilt_deg),
                    m.roll_deg + a * (roll_deg - m.roll_deg),
                )
            )
        self.source = source

    def _apply(self, smoothed: Mount, force: bool = False) -> None:
        """Track ``smoothed``; move the applied mount when it drifts beyond the deadband."""
        self._smoothed = smoothed
        dh, da = _distance(smoothed, self.mount)
        if force or dh > self._params.deadband_m or da > self._params.deadband_deg:
            self.mount = smoothed

    def from_floor(self, height_m: float, tilt_deg: float, roll_deg: float) -> str | None:
        """Apply a confident floor estimate; returns a log-worthy note when something notable
        happened."""
        new = _clamped(self.mount, height_m, tilt_deg, roll_deg)
        if not self._floor_seen:
            self._floor_seen = True
            old, self.source = self.mount, "floor"
            self._apply(new, force=True)
            self._pending.clear()
            return (
                f"mount from the floor: height {new.height_m:.3f} m, tilt {new.tilt_deg:.2f} deg, "
                f"roll {new.roll_deg:.2f} deg (was {old.height_m:.3f} m, {old.tilt_deg:.2f} deg, "
                f"{old.roll_deg:.2f} deg)"
            )
        dh, da = _distance(new, self._smoothed)
        p = self._params
        if dh <= p.max_jump_m and da <= p.max_jump_deg:
            self._pending.clear()
            m = self._smoothed
            a = p.smoothing
            self._apply(
                _clamped(
                    m,
                    m.height_m + a * (new.height_m - m.height_m),
                    m.tilt_deg + a * (new.tilt_deg - m.tilt_deg),
                    m.roll_deg + a * (new.roll_deg - m.roll_deg),
                )
            )
            return None
        # a jump: hold it back until enough consecutive estimates agree with each other
        if self._pending and any(
            _distance(new, q)[0] > p.max_jump_m or _distance(new, q)[1] > p.max_jump_deg
            for q in self._pending
        ):
            self._pending.clear()
        self._pending.append(new)
        if len(self._pending) >= p.confirmations:
            self._apply(self._pending[-1], force=True)
            self._pending.clear()
            return (
                f"mount jump accepted after {p.confirmations} agreeing floor estimates: height "
                f"{self.mount.height_m:.3f} m, tilt {self.mount.tilt_deg:.2f} deg, "
                f"roll {self.mount.roll_deg:.2f} deg"
            )
        self.rejected += 1
        return (
            f"floor estimate (height {new.height_m:.3f} m, tilt {new.tilt_deg:.2f} deg, "
            f"roll {new.roll_deg:.2f} deg) "
            f"jumps {dh:.3f} m / {da:.2f} deg from the running mount; not applied "
            f"({len(self._pending)}/{p.confirmations} agreeing estimates)"
        )
