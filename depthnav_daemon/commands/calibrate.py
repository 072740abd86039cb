"""``depthnav calibrate``: estimate the sensor's height, tilt and roll from the floor (the work is
in ``calibration``, imported after the stop handlers)."""

from __future__ import annotations

import argparse
import json
import logging
import signal
import threading

from depthnav_daemon.commands.common import (
    EXIT_INTERRUPTED,
    EXIT_OK,
    announce_compiles,
    install_stop_handlers,
    load_config,
    progress_bar,
    stopped_code,
)
from depthnav_daemon.errors import ConfigError

log = logging.getLogger(__name__)


def cmd_calibrate(args: argparse.Namespace) -> int:
    if args.frames < 1:
        raise ConfigError(f"--frames={args.frames} is out of range (accepted: 1 or more)")
    stop = threading.Event()
    got = install_stop_handlers(stop)  # before the heavy imports: see install_stop_handlers
    from depthnav_daemon.commands.calibration import (
        NoFramesError,
        calibrate,
        format_text,
        write_mount,
    )

    announce_compiles()

    cfg = load_config(args, args.device)
    try:
        result = calibrate(
            cfg, args.frames, stop, progress=progress_bar("calibrating") if not args.json else None
        )
    except NoFramesError:
        if "signal" not in got:
            raise
        # a stop before the first frame is a clean stop, not a failed calibration
        log.warning("stopped before the first frame: nothing was calibrated")
        return stopped_code(got)
    interrupted = got.get("signal") == signal.SIGINT
    partial = "signal" in got and result.frames_read < args.frames
    if args.json:
        print(json.dumps({**result.as_dict(), "partial": partial}, allow_nan=False))  # noqa: T201
    else:
        print(format_text(result))  # noqa: T201
    if partial:
        # what was collected is reported, marked partial; Ctrl-C writes nothing, SIGTERM (a
        # service manager stopping it) writes what the frames read so far give
        log.warning(
            "partial calibration: stopped after %d of %d frames%s",
            result.frames_read,
            args.frames,
            "; nothing written" if interrupted and args.write else "",
        )
    if interrupted:
        return EXIT_INTERRUPTED
    if args.write:
        write_mount(args.write, result)
        log.info("wrote [mount] to %s", args.write)
    return EXIT_OK
