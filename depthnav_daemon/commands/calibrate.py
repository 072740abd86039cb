"""``depthnav calibrate``: estimate the sensor's height, tilt and roll from the floor (the work is
in ``calibration``, imported after the stop handlers).

``--write`` changes the config only on a normal end or SIGTERM, and only from at least
MIN_WRITE_FRAMES frames with a floor estimate: SIGINT or SIGHUP (a closing terminal) writes
nothing, and a calibration from fewer frames is reported, not written."""

from __future__ import annotations

import argparse
import json
import logging
import signal
import threading
from typing import TYPE_CHECKING

from depthnav_daemon.commands.common import (
    EXIT_OK,
    announce_compiles,
    install_stop_handlers,
    load_config,
    progress_bar,
    stopped_code,
)
from depthnav_daemon.errors import ConfigError, DepthnavError

if TYPE_CHECKING:
    from depthnav_daemon.commands.calibration import Calibration

log = logging.getLogger(__name__)

# the fewest frames with a floor estimate a calibration is written from: the median of three
# holds against one wrong estimate (under load a hang-up wrote the config from a single frame)
MIN_WRITE_FRAMES = 3


def cmd_calibrate(args: argparse.Namespace) -> int:
    if args.frames < 1:
        raise ConfigError(f"--frames={args.frames} is out of range (accepted: 1 or more)")
    if args.write and args.frames < MIN_WRITE_FRAMES:
        raise ConfigError(
            f"--frames={args.frames} is too few to --write a calibration (accepted: "
            f"{MIN_WRITE_FRAMES} or more)",
            hint=f"the config is written from the median of at least {MIN_WRITE_FRAMES} frames "
            "with a floor estimate",
        )
    stop = threading.Event()
    got = install_stop_handlers(stop)  # before the heavy imports: see install_stop_handlers
    from depthnav_daemon.commands.calibration import NoFramesError, calibrate, format_text

    announce_compiles()

    cfg = load_config(args, args.device)
    try:
        result = calibrate(
            cfg,
            args.frames,
            stop,
            progress=progress_bar("calibrating") if not args.json else None,
            enough=MIN_WRITE_FRAMES if args.write else 0,
        )
    except NoFramesError:
        if "signal" not in got:
            raise
        # a stop before the first frame is a clean stop, not a failed calibration
        log.warning("stopped before the first frame: nothing was calibrated")
        return stopped_code(got)
    except DepthnavError as exc:
        if "signal" not in got:
            raise
        # stopped before enough floor was seen: a clean stop too, and nothing written
        log.warning("stopped: %s; nothing calibrated or written", exc)
        return stopped_code(got)
    sig = got.get("signal")
    partial = sig is not None and result.frames_read < args.frames
    if args.json:
        print(json.dumps({**result.as_dict(), "partial": partial}, allow_nan=False))  # noqa: T201
    else:
        print(format_text(result))  # noqa: T201
    if partial:
        log.warning(
            "partial calibration: stopped after %d of %d frames", result.frames_read, args.frames
        )
    if not args.write:
        return EXIT_OK if sig is None else stopped_code(got)
    return _write(args, result, got)


def _write(args: argparse.Namespace, result: Calibration, got: dict[str, int]) -> int:
    """``--write``, on a normal end or SIGTERM (a service manager stopping it) only: Ctrl-C or a
    closing terminal (SIGHUP) leaves the robot's config as it was; and from at least
    MIN_WRITE_FRAMES frames with a floor estimate."""
    from depthnav_daemon.commands.calibration import write_mount

    sig = got.get("signal")
    if sig is not None and sig != signal.SIGTERM:
        log.warning("stopped by %s: nothing written to %s", signal.Signals(sig).name, args.write)
        return stopped_code(got)
    if result.frames_used < MIN_WRITE_FRAMES:
        why = (
            f"nothing written to {args.write}: {result.frames_used} of {result.frames_read} "
            f"frames gave a floor estimate, a written calibration needs {MIN_WRITE_FRAMES}"
        )
        if sig is not None:
            log.warning("%s", why)
            return stopped_code(got)
        raise DepthnavError(why, hint="calibrate over more frames of open floor (--frames)")
    write_mount(args.write, result)
    log.info("wrote [mount] to %s", args.write)
    return EXIT_OK if sig is None else stopped_code(got)
