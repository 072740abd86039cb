"""Calibration for ``depthnav calibrate``: the sensor's height, tilt and roll from the floor over N
frames."""

from __future__ import annotations

import logging
import math
import os
import tempfile
import threading
import tomllib
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import tomlkit
import tomlkit.exceptions

from depthnav_daemon.config.loader import Config
from depthnav_daemon.errors import ConfigError, DepthnavError
from depthnav_daemon.pipeline.pose import (
    TILT_SENSOR_WINDOW_DEG,
    WHOLE_RANGE,
    PoseParams,
    estimate_pose,
    tilt_roll_from_accel,
    wide_prior,
)
from drivers import create_driver, iter_frames, opened
from drivers.files import read_text
from drivers.values import short_text

log = logging.getLogger(__name__)

# calibrate searches every plausible mount (pose.WHOLE_RANGE; the daemon searches the same while
# an unconfigured mount's floor is not found yet)
ACCEL_WINDOW_DEG = TILT_SENSOR_WINDOW_DEG  # the search around the accelerometer's tilt and roll


def calibration_prior(pose: PoseParams, accel_mps2: Sequence[float] | None = None) -> PoseParams:
    """The floor search's prior for calibrate: a prior the user's config gives (any prior field
    changed from its default) wins; else the accelerometer's tilt and roll +-10 deg at any
    height; else the whole plausible range (:func:`pose.wide_prior`)."""
    if accel_mps2 is None:
        return wide_prior(pose)
    try:
        tilt_roll = tilt_roll_from_accel(accel_mps2)
    except ConfigError:  # moving, or not an accelerometer reading: search the whole range
        return wide_prior(pose)
    return wide_prior(pose, tilt_roll)


class NoFramesError(DepthnavError):
    """The device gave no frame before the calibration ended."""


@dataclass(frozen=True, slots=True)
class Calibration:
    """The mount estimated over several frames: medians, spreads (standard deviations) and
    quality."""

    height_m: float
    tilt_deg: float
    roll_deg: float
    height_std_m: float
    tilt_std_deg: float
    roll_std_deg: float
    inlier_ratio: float
    frames_used: int
    frames_read: int

    def as_dict(self) -> dict[str, Any]:
        return {
            k: (round(v, 6) if isinstance(v, float) else v)
            for k, v in ((f, getattr(self, f)) for f in self.__slots__)
        }  # type: ignore[attr-defined]


def calibrate(
    cfg: Config,
    n_frames: int,
    stop: threading.Event,
    progress: Callable[[int, int], None] | None = None,
    enough: int = 0,
) -> Calibration:
    """Estimate the mount from the floor on up to ``n_frames`` frames of ``cfg.device``; with
    ``enough``, say once when that many frames gave a floor estimate (enough to write it).

    Raises:
        DepthnavError: too little floor in too many frames (with a hint to point at open floor).
    """
    rng = np.random.default_rng(cfg.daemon.seed)
    prior: PoseParams | None = None
    good: list[tuple[float, float, float, float]] = []
    reasons: list[str] = []
    read = 0
    driver = create_driver(cfg.device)
    with opened(driver):
        for frame in iter_frames(driver, stop):
            if prior is None:  # from the first frame: its accelerometer narrows the search
                prior = calibration_prior(cfg.pose, frame.accel_mps2)
            est = estimate_pose(frame.depth_mm, frame.intrinsics, prior, rng)
            read += 1
            if read == 1:  # the device works: the wait from here is the calibration itself
                log.info("calibrating %s over up to %d frames", cfg.device, n_frames)
            if est.ok:
                good.append((est.height_m, est.tilt_deg, est.roll_deg, est.inlier_ratio))
                if len(good) == enough:
                    log.info("%d frames gave a floor estimate: enough to write the config", enough)
            else:
                reasons.append(est.reason)
            if progress:
                progress(read, n_frames)
            if read >= n_frames:
                break
    need = max(1, math.ceil(read / 3))
    if read == 0:
        raise NoFramesError(
            f"{cfg.device} gave no frames", hint="check the device with depthnav devices"
        )
    if len(good) < need:
        why = reasons[-1] if reasons else "no confident floor estimate"
        raise DepthnavError(
            f"too little floor: {len(good)} of {read} frames gave a confident floor estimate "
            f"({why})",
            hint="point the sensor at open floor, or widen the [pose] prior "
            "(height_min_m.. tilt_max_deg)",
        )
    a = np.array(good)
    med = np.median(a, axis=0)
    std = a.std(axis=0)
    return Calibration(
        float(med[0]),
        float(med[1]),
        float(med[2]),
        float(std[0]),
        float(std[1]),
        float(std[2]),
        float(med[3]),
        len(good),
        read,
    )


def format_text(c: Calibration) -> str:
    return "\n".join(
        [
            f"height  {c.height_m:.3f} m    (spread {c.height_std_m * 1000:.1f} mm)",
            f"tilt    {c.tilt_deg:.2f} deg   "
            f"(spread {c.tilt_std_deg:.2f} deg, positive = pitched down)",
            f"roll    {c.roll_deg:.2f} deg   "
            f"(spread {c.roll_std_deg:.2f} deg, positive = left side up)",
            f"floor   {c.inlier_ratio:.0%} inliers, {c.frames_used} of {c.frames_read} frames used",
            "",
            "[mount]",
            f"height_m = {c.height_m:.3f}",
            f"tilt_deg = {c.tilt_deg:.2f}",
            f"roll_deg = {c.roll_deg:.2f}",
        ]
    )


def write_mount(path: Path, c: Calibration) -> None:
    """Set the [mount] section of a TOML config file (created if missing), atomically.

    The file is edited with tomlkit, which keeps the user's comments, key order and formatting
    (only the three mount keys change). A symlink is written through: its target is replaced (in
    the target's folder, keeping its permissions) and the link stays a link.

    Raises:
        ConfigError: the file is not TOML, not UTF-8, not a regular file, or [mount] is not a
            table.
        DepthnavError: the file cannot be written (the old one is left as it was).
    """
    target = Path(os.path.realpath(path))  # through every symlink to the file itself
    doc = _read_document(path, target)
    mount = doc.get("mount")
    if mount is None:
        mount = tomlkit.table()
        doc["mount"] = mount
    elif not isinstance(mount, dict):
        raise ConfigError(
            f"{path}: 'mount' is not a table, cannot set [mount] in it",
            hint="name a new file or fix this one",
        )
    mount["height_m"] = round(c.height_m, 4)
    mount["tilt_deg"] = round(c.tilt_deg, 3)
    mount["roll_deg"] = round(c.roll_deg, 3)
    _replace(path, target, tomlkit.dumps(doc).encode("utf-8"))


def _read_document(path: Path, target: Path) -> tomlkit.TOMLDocument:
    """The config to update as a tomlkit document (an empty one when the file does not exist)."""
    if not os.path.lexists(target):
        return tomlkit.document()
    text = read_text(target, what="config file", error=_not_updatable(path))
    try:
        tomllib.loads(text)  # the reader's verdict first: tomlkit accepts a few things it refuses
        return tomlkit.parse(text)
    except (tomllib.TOMLDecodeError, tomlkit.exceptions.TOMLKitError) as exc:
        raise _not_updatable(path)(f"{path}: {short_text(str(exc))}") from None
    except (RecursionError, ValueError):
        raise _not_updatable(path)(f"{path}: nested too deeply or a number too long") from None


def _not_updatable(path: Path) -> Callable[..., ConfigError]:
    def error(message: str, hint: str | None = None) -> ConfigError:
        return ConfigError(
            f"{message.rstrip('.')}; not a TOML file I can update",
            hint=hint or "name a new file or fix this one",
        )

    return error


def _replace(path: Path, target: Path, data: bytes) -> None:
    """Write ``data`` to ``target`` through a temporary file in its folder, renamed over it."""
    try:
        # the new file keeps the old one's permissions (mkstemp makes 0600), or the umask's
        mode = target.stat().st_mode & 0o7777 if target.exists() else 0o666 & ~_umask()
        fd, tmp = tempfile.mkstemp(prefix=f".{target.name}.", dir=target.parent)
    except OSError as exc:
        raise DepthnavError(
            f"cannot write {path}: {exc.strerror or exc}",
            hint="check the folder exists and is writable",
        ) from None
    try:
        with os.fdopen(fd, "wb") as fh:
            fh.write(data)
            fh.flush()
            os.fsync(fh.fileno())
        os.chmod(tmp, mode)
        os.replace(tmp, target)
    except OSError as exc:  # a full disk: the old file stays as it was
        Path(tmp).unlink(missing_ok=True)
        raise DepthnavError(
            f"writing {path} failed: {exc.strerror or exc}; the file was not changed",
            hint="free some disk space and calibrate again",
        ) from None
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def _umask() -> int:
    """The process umask (reading it means setting it; set it straight back)."""
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


__all__ = [  # WHOLE_RANGE lives in pose; importable from here as before
    "ACCEL_WINDOW_DEG",
    "WHOLE_RANGE",
    "Calibration",
    "NoFramesError",
    "calibrate",
    "calibration_prior",
    "format_text",
    "write_mount",
]
