"""What the frame loop decides for each frame, in order: the tilt sensor's reading, whether the
floor pose stage runs, the mount the stages use, then the stages themselves.

The state between frames lives here (the mount tracker, the stage tables, the RANSAC generator,
the pose schedule); the stages stay pure functions.

A mount nobody configured is unknown until the floor gives it: meanwhile the floor is searched on
every frame over every plausible mount (``depthnav calibrate``'s range, ``pose.wide_prior``), and
every range the frame reports (the scan and the cliff scan) is unknown (NaN), its trust saying
``trusted`` False. Once the floor's mount serves the frames (its tables built), the output is
normal and the search narrows to the mount (:func:`pose_prior`), for good.

The robot's own body ([robot] footprint): the readings inside it become "no reading" before the
stages see the frame (``pipeline.footprint``; its table per camera and mount is built with the
stages' tables): the stages with the table of the mount they use, the floor search with that of
the mount the last frame used (while that mount is known).
"""

from __future__ import annotations

import dataclasses
import logging
import time
from collections.abc import Callable

import numpy as np

from depthnav_daemon.config.loader import Config
from depthnav_daemon.daemon.mount_tracker import MountTracker, TrackerParams
from depthnav_daemon.daemon.stage_tables import SmallChange, StageTables, with_body
from depthnav_daemon.pipeline import MountState, MountTrust, Result, StageParams, prepare, process
from depthnav_daemon.pipeline.footprint import body_table, remove_body
from depthnav_daemon.pipeline.geometry import MAX_MOUNT_HEIGHT_M, MAX_ROLL_DEG, MAX_TILT_DEG, Mount
from depthnav_daemon.pipeline.laser_scan import LaserScan
from depthnav_daemon.pipeline.pose import (
    PoseEstimate,
    PoseParams,
    estimate_pose,
    prepare_pose,
    tilt_roll_from_accel,
    wide_prior,
)
from drivers.base import Frame
from drivers.errors import DriverError
from drivers.tilt import TiltSource

log = logging.getLogger(__name__)

PRIOR_HALF_WIDTH_DEG = 10.0
PRIOR_HALF_HEIGHT_M = 0.3
MIN_PRIOR_HEIGHT_M = 0.05


class FrameStep:
    """Turns each frame into a Result: mount decisions first, then ``pipeline.process``.

    Args:
        cfg: the effective configuration.
        params: the stages to run; the loop may replace it once the sinks are known.
        tilt_source: a started tilt source (serial IMU), or None.
    """

    def __init__(self, cfg: Config, params: StageParams, tilt_source: TiltSource | None) -> None:
        d = cfg.daemon
        self.params = params
        self._daemon = d
        self._pose_params = cfg.pose
        self._tilt_source = tilt_source
        # whether a frame's accelerometer reading may set the tilt (else only a serial source)
        self._tilt_from_accel = d.tilt_source in ("auto", "accel")
        self._tracker = MountTracker(
            cfg.mount, TrackerParams.from_daemon(d), pinned=d.tilt_source == "config"
        )
        self._trusted: bool | None = None  # drop-offs trusted on the last frame (None: no frame)
        # the mount serving the frames is known (configured, or the floor's with its tables
        # built): until then every range is unknown; never False again once True
        self._known = self._tracker.confirmed
        self._said_known = self._known
        if not self._known and d.pose_every_frames <= 0 and d.pose_every_s <= 0:
            log.warning(
                "no [mount] configured and the floor estimate is off (daemon.pose_every_frames "
                "= 0): the mount stays unknown and every range is reported unknown (NaN); set "
                "[mount] or run depthnav calibrate"
            )
        self._body = cfg.robot.footprint()  # None: no footprint
        self._body_used: Mount | None = None  # the mount the last frame's stages used
        self._said_body = False
        # the frame the stages processed last (without the body's readings), for sinks that
        # draw the depth as the stages saw it
        self.stage_frame: Frame | None = None
        self._tables = StageTables(
            with_body(lambda intr, mount: prepare(intr, mount, self.params), self._body),
            prepare_prior=prepare_pose,
            defer_start=True,
        )
        self._rng = np.random.default_rng(d.seed)
        self._since_pose = d.pose_every_frames  # estimate on the first frame
        self._last_pose_t: float | None = None
        self._accel_tilt: tuple[object, tuple[float, float]] | None = None  # last conversion

    @property
    def rejected_pose_jumps(self) -> int:
        """Floor estimates held back as jumps so far."""
        return self._tracker.rejected

    def run(self, frame: Frame) -> Result:
        """The frame's Result.

        Raises:
            FrameError: the frame cannot be processed (the loop skips it).
        """
        accel = self._tilt_from_accel and frame.accel_mps2 is not None
        if accel or self._tilt_source is not None:
            self._read_tilt_source(frame)  # (a call that finds nothing to read cost ~0.5 %)
        want_pose = self._pose_due(frame)
        pose, pose_s = None, None
        raw, body_s, masked_with = frame, 0.0, None
        if want_pose and self._body is not None and self._known:
            # the floor search sees the frame without the body as the last frame's mount (on
            # the first frame the configured one) saw it: that mount's table exists
            t0 = time.perf_counter()
            masked_with = self._body_used or self._tracker.mount
            frame = self._without_body(raw, masked_with)
            body_s = time.perf_counter() - t0
        if want_pose:
            # a new prior window's table is built on the worker: meanwhile the estimate searches
            # the last window (whose table exists) rather than this frame building it
            prior = self._tables.prior_for(
                frame.intrinsics, pose_prior(self._pose_params, self._tracker)
            )
            t0 = time.perf_counter()
            pose = estimate_pose(frame.depth_mm, frame.intrinsics, prior, self._rng)
            pose_s = time.perf_counter() - t0
            _apply_pose(self._tracker, pose, self._daemon.tilt_source)
        # a new mount serves the frames once its tables exist (built on a worker by StageTables,
        # with the pose stage's window around it; a camera's first frame builds them itself);
        # meanwhile frames use the nearest ready mount
        wanted = self._tracker.mount
        used = self._tables.mount_for(frame.intrinsics, wanted, self._prior_for_wanted)
        if not self._known:
            used = self._serve_known(frame, wanted, used)
        trust = _pending(self._tracker.trust(), used, wanted)
        if trust.dropoffs_trusted != self._trusted:
            self._say_trust(trust)
        state = MountState(
            mount=used, source=self._tracker.source, trust=trust, pose=pose, pose_s=pose_s
        )
        if self._body is not None:
            t0 = time.perf_counter()
            if used != masked_with:
                frame = self._without_body(raw, used)
            self._body_used = used
            body_s += time.perf_counter() - t0
        self.stage_frame = frame
        result = process(frame, state, self.params, time.perf_counter)
        if self._body is not None:
            result.timings_s["body"] = body_s
        if not trust.trusted:
            result = unknown_ranges(result, trust.note)
        if want_pose:
            self._since_pose, self._last_pose_t = 0, frame.timestamp_s
        self._since_pose += 1
        self._tables.start_queued()  # a build decided on this frame starts after its stages
        return result

    def _without_body(self, frame: Frame, mount: Mount) -> Frame:
        """``frame`` with the readings of the robot's body (seen from ``mount``) removed (0);
        ``frame`` itself when none are."""
        assert self._body is not None
        table = body_table(frame.intrinsics, mount, self._body)
        depth, removed = remove_body(frame.depth_mm, table)
        if not self._said_body:
            self._said_body = True
            log.info(
                "robot footprint: %d pixels of this camera can see the robot's body; %d readings "
                "of it removed from the first frame",
                table.size,
                removed,
            )
        return frame if removed == 0 else dataclasses.replace(frame, depth_mm=depth)

    def _prior_for_wanted(self) -> PoseParams | None:
        """The pose stage's window around the tracker's mount (for a build to make ahead), or
        None when the pose stage never runs."""
        d = self._daemon
        if d.pose_every_frames <= 0 and d.pose_every_s <= 0:
            return None
        return pose_prior(self._pose_params, self._tracker)

    def _serve_known(self, frame: Frame, wanted: Mount, used: Mount) -> Mount:
        """The mount to serve a frame with until the tables serve a known mount: ``used`` while
        the tracker knows none; once the floor has given one, ``wanted``, its tables built on
        this frame (once: 0.14 s at 640x480 on the 2-core test machine, as a camera's first
        frame does; a cache hit of 0.2 ms on the next frames) rather than ``used`` (the mount
        nobody knows, whose ranges are all unknown) for the 5-10 frames (20-60 on a loaded
        machine) the worker takes."""
        if not self._tracker.confirmed:
            return used
        if not self._said_known:
            self._said_known = True
            log.info(
                "mount %.3f m, tilt %.2f deg, roll %.2f deg from the floor: ranges are reported "
                "from this frame on",
                wanted.height_m,
                wanted.tilt_deg,
                wanted.roll_deg,
            )
        if used is wanted:  # the tables serve it: from here on they serve known mounts only
            self._known = True
            return used
        prepare(frame.intrinsics, wanted, self.params)
        return wanted

    def _say_trust(self, trust: MountTrust) -> None:
        """Log when drop-offs stop (warning) or start again (info) being trusted."""
        first, self._trusted = self._trusted is None, trust.dropoffs_trusted
        if not trust.dropoffs_trusted:
            log.warning("%s", trust.note)
        elif not first:
            log.info("mount %s by the floor: drop-offs are trusted again", trust.floor)

    def close(self) -> None:
        """Stop the table builder."""
        self._tables.close()

    def _pose_due(self, frame: Frame) -> bool:
        d = self._daemon
        if d.pose_every_frames > 0 and self._since_pose >= d.pose_every_frames:
            return True
        if (
            not self._known
            and not self._tracker.confirmed
            and (d.pose_every_frames > 0 or d.pose_every_s > 0)
        ):
            return True  # nothing is known until the floor is found: look on every frame
        return d.pose_every_s > 0 and (
            self._last_pose_t is None or frame.timestamp_s - self._last_pose_t >= d.pose_every_s
        )

    def _read_tilt_source(self, frame: Frame) -> None:
        try:
            _update_tilt_prior(
                self._tracker, frame, self._daemon.tilt_source, self._tilt_source, self._tilt_roll
            )
        except DriverError as exc:
            # the IMU only refines the mount: losing it must not blind the robot, so say so
            # once and go on with the floor estimate and the last mount
            log.error("%s; going on without the serial tilt source", exc)
            self._tilt_source = None

    def _tilt_roll(self, accel: tuple[float, float, float]) -> tuple[float, float]:
        """tilt_roll_from_accel, reused while the reading repeats (a device may update its
        accelerometer less often than it sends frames; the conversion cost 5-7 % of the loop)."""
        last = self._accel_tilt
        if last is not None and isinstance(accel, tuple) and last[0] == accel:
            return last[1]
        tilt_roll = tilt_roll_from_accel(accel)
        self._accel_tilt = (accel, tilt_roll) if isinstance(accel, tuple) else None
        return tilt_roll


def _pending(trust: MountTrust, used: Mount, wanted: Mount) -> MountTrust:
    """``trust`` for a frame processed with ``used`` while ``wanted``'s tables are being built:
    beyond a small change (the tracker's deadband), its drop-offs rest on the old mount and are
    not trusted."""
    if used is wanted or used == wanted or _SMALL.holds(used, wanted):
        return trust
    note = (
        f"mount change to {wanted.height_m:.2f} m / tilt {wanted.tilt_deg:.1f} deg pending (its "
        f"tables are being built): this frame used {used.height_m:.2f} m / "
        f"{used.tilt_deg:.1f} deg, drop-offs not trusted"
    )
    return dataclasses.replace(trust, dropoffs_trusted=False, note=note)


_SMALL = SmallChange()


def _unknown(scan: LaserScan) -> LaserScan:
    return dataclasses.replace(scan, ranges=np.full_like(scan.ranges, np.nan), far=None)


def unknown_ranges(result: Result, note: str | None = None) -> Result:
    """``result`` with every range unknown (NaN): the scan, the cliff scan, and their level-frame
    copies. For a mount that is not known (``MountTrust.trusted`` False): the floor may be where
    the scan says a wall is, and +inf ("seen free") would be a claim nobody checked. The cliff's
    floor points stay, flagged untrusted like any drop-off of an untrusted mount. ``note`` (why)
    joins the frame's own warning ("no valid depth ...") when it has one."""
    cliff, sensor_cliff = result.cliff, result.sensor_cliff
    warning = result.warning
    if note and warning != note:
        warning = note if warning is None else f"{warning}; {note}"
    return dataclasses.replace(
        result,
        warning=warning,
        scan=_unknown(result.scan),
        sensor_scan=None if result.sensor_scan is None else _unknown(result.sensor_scan),
        cliff=None if cliff is None else dataclasses.replace(cliff, scan=_unknown(cliff.scan)),
        sensor_cliff=None
        if sensor_cliff is None
        else dataclasses.replace(sensor_cliff, scan=_unknown(sensor_cliff.scan)),
    )


def pose_prior(params: PoseParams, tracker: MountTracker) -> PoseParams:
    """The floor search's window for this frame.

    - While the mount is not known (nobody configured it, the floor has not given it yet): every
      plausible mount, as ``depthnav calibrate`` searches (``pose.wide_prior``: a prior set in
      [pose] wins; a tilt sensor's reading narrows the tilt and roll to +-10 deg).
    - While a tilt sensor gives the mount: the configured window's tilt, narrowed to its reading
      +-10 deg.
    - A mount outside the configured window (calibrated on a mast, say: ``depthnav calibrate``
      searches every plausible mount): a narrow window around it, +-0.3 m and +-10 deg, so live
      tracking follows it instead of finding no floor.
    - Else the configured window.

    Rounded (0.1 m, whole degrees) so the pose stage's per-prior tables are reused frame after
    frame.
    """
    m = tracker.mount
    sensor = tracker.source in ("accel", "serial")
    if not tracker.confirmed:
        return wide_prior(params, (m.tilt_deg, m.roll_deg) if sensor else None)
    if sensor:
        t = round(m.tilt_deg)
        lo = max(params.tilt_min_deg, t - PRIOR_HALF_WIDTH_DEG)
        hi = min(params.tilt_max_deg, t + PRIOR_HALF_WIDTH_DEG)
        if lo < hi:  # else the sensor disagrees with the configured window: trust the window
            return dataclasses.replace(params, tilt_min_deg=lo, tilt_max_deg=hi)
        return params
    inside = (
        params.height_min_m <= m.height_m <= params.height_max_m
        and params.tilt_min_deg <= m.tilt_deg <= params.tilt_max_deg
        and abs(m.roll_deg) <= params.roll_max_deg
    )
    if inside:
        return params
    h, t = round(m.height_m, 1), round(m.tilt_deg)
    return dataclasses.replace(
        params,
        height_min_m=max(MIN_PRIOR_HEIGHT_M, h - PRIOR_HALF_HEIGHT_M),
        height_max_m=min(MAX_MOUNT_HEIGHT_M, h + PRIOR_HALF_HEIGHT_M),
        tilt_min_deg=max(-MAX_TILT_DEG, t - PRIOR_HALF_WIDTH_DEG),
        tilt_max_deg=min(MAX_TILT_DEG, t + PRIOR_HALF_WIDTH_DEG),
        roll_max_deg=min(MAX_ROLL_DEG, max(params.roll_max_deg, abs(round(m.roll_deg)) + 10.0)),
    )


def _update_tilt_prior(
    tracker: MountTracker,
    frame: Frame,
    tilt_source: str,
    serial_tilt: TiltSource | None,
    tilt_roll: Callable[[tuple[float, float, float]], tuple[float, float]] = tilt_roll_from_accel,
) -> None:
    if tilt_source in ("auto", "accel") and frame.accel_mps2 is not None:
        try:
            tilt, roll = tilt_roll(frame.accel_mps2)
        except ValueError as exc:
            log.debug("accelerometer reading ignored: %s", exc)
            return
        tracker.from_tilt_sensor(tilt, roll, "accel")
    elif tilt_source in ("auto", "serial") and serial_tilt is not None:
        reading = serial_tilt.latest(max_age_s=2.0)
        if reading is not None:
            tracker.from_tilt_sensor(reading.tilt_deg, reading.roll_deg, "serial")


def _apply_pose(tracker: MountTracker, est: PoseEstimate, tilt_source: str) -> None:
    if not est.ok:
        log.debug("floor pose not confident: %s", est.reason)
        return
    if tilt_source != "config":  # else the user pinned the mount: the floor only checks it
        note = tracker.from_floor(est.height_m, est.tilt_deg, est.roll_deg)
        if note:
            (log.warning if "not applied" in note else log.info)("%s", note)
    tracker.check_floor(est.height_m, est.tilt_deg, est.roll_deg)
