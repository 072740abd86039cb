"""``depthnav run`` and ``depthnav replay``: the daemon's frame loop on a device or recording."""

from __future__ import annotations

import argparse
import logging
import signal
import threading

from depthnav_daemon.commands.common import (
    EXIT_INTERRUPTED,
    EXIT_OK,
    announce_compiles,
    install_stop_handlers,
    load_config,
    overrides,
)
from depthnav_daemon.errors import ConfigError

log = logging.getLogger(__name__)


def _run(args: argparse.Namespace, device: str | None) -> int:
    stop = threading.Event()
    got = install_stop_handlers(stop)  # before the heavy imports: see install_stop_handlers
    from depthnav_daemon.daemon.loop import run

    announce_compiles()

    cfg = load_config(args, device)
    if not cfg.device and not cfg.sensors:
        raise ConfigError(
            "no device given",
            hint="use --device SPEC, or set device (or [[sensor]] tables) in a config file",
        )
    if args.max_frames is not None and args.max_frames < 1:
        raise ConfigError(f"--max-frames={args.max_frames} is out of range (accepted: 1 or more)")
    if overrides(args).get("daemon", {}).get("tilt_source") == "config":
        m = cfg.mount
        log.info(
            "mount %.3f m, tilt %.1f deg, roll %.1f deg as given: the accelerometer and the floor "
            "estimates do not replace it (--set daemon.tilt_source=auto lets them)",
            m.height_m,
            m.tilt_deg,
            m.roll_deg,
        )
    serial = None
    if cfg.daemon.serial_tilt:
        from drivers.tilt import create_tilt_source

        serial = create_tilt_source(cfg.daemon.serial_tilt)
        serial.start()
    try:
        report = run(cfg, stop, args.max_frames, serial_tilt=serial)
    finally:
        if serial is not None:
            serial.stop()
    log.info(
        "%d frames processed%s",
        report.frames,
        f"; dropped sinks: {', '.join(report.dropped_sinks)}" if report.dropped_sinks else "",
    )
    if got.get("signal") == signal.SIGINT:
        return EXIT_INTERRUPTED
    return EXIT_OK


def cmd_run(args: argparse.Namespace) -> int:
    if not args.device and not args.config:
        raise ConfigError(
            "no device given", hint="depthnav run --device kinect (or replay:PATH, openni://)"
        )
    return _run(args, args.device)


def cmd_replay(args: argparse.Namespace) -> int:
    query = f"?rate={args.rate}" + ("&loop=1" if args.loop else "")
    return _run(args, f"replay:{args.path}{query}")
