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
    stopped_code,
)
from depthnav_daemon.errors import ConfigError
from drivers.errors import DeviceSpecError

log = logging.getLogger(__name__)


def _run(args: argparse.Namespace, device: str | None) -> int:
    stop = threading.Event()
    got = install_stop_handlers(stop)  # before the heavy imports: see install_stop_handlers
    from depthnav_daemon.daemon.kernel_cache import cache_dir, check_writable, warm_kernels

    check_writable(cache_dir())  # else every kernel's import fails ("no locator available")
    from depthnav_daemon.daemon.loop import run
    from depthnav_daemon.daemon.notify import ServiceNotifier

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
    notifier = ServiceNotifier()
    # a cold cache is filled by a child process, stopped at once by a signal (kernel_cache.py)
    if not warm_kernels(stop, notifier):
        notifier.give_up("stopped while compiling the kernels")
        return stopped_code(got)
    serial = None
    if cfg.daemon.serial_tilt:
        from drivers.tilt import create_tilt_source

        serial = create_tilt_source(cfg.daemon.serial_tilt)
        serial.start()
    try:
        report = run(cfg, stop, args.max_frames, serial_tilt=serial, notifier=notifier)
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


def replay_spec(path: str, rate: str | None, loop: bool) -> str:
    """The device spec of ``depthnav replay PATH [--rate R] [--loop]``: PATH's own ``?options``
    kept, the flags merged into them (rate max unless either gives one).

    Raises:
        DeviceSpecError: a flag and the same option in PATH disagree (exit 2).
    """
    from drivers.spec import format_spec, parse_spec

    spec = parse_spec(f"replay:{path}")
    options = dict(spec.options)
    flags = {"rate": rate} if rate is not None else {}
    if loop:
        flags["loop"] = "1"
    for key, value in flags.items():
        if key in options:
            # the same setting twice: compared as the driver reads them (loop=yes is loop=1)
            if _replay_option(spec.text, key, options[key]) != _replay_option(
                spec.text, key, value
            ):
                flag = "--loop" if key == "loop" else f"--{key} {value}"
                raise DeviceSpecError(
                    f"{flag} and {key}={options[key]} in {path!r} disagree",
                    hint=f"give {key} once: as the flag or in the path",
                )
        else:
            options[key] = value
    options.setdefault("rate", "max")  # the replay command's default: a recording as fast as read
    return format_spec("replay", spec.target, options)


def _replay_option(text: str, key: str, value: str) -> object:
    """A ``rate`` or ``loop`` value as the replay driver reads it (``text``: the spec, for the
    error of a bad value)."""
    from drivers.spec import Spec, bool_option, choice_option

    probe = Spec(text, "replay", "", {key: value})
    if key == "rate":
        return choice_option(probe, key, ("realtime", "max"), "max")
    return bool_option(probe, key, False)


def cmd_replay(args: argparse.Namespace) -> int:
    return _run(args, replay_spec(args.path, args.rate, args.loop))
