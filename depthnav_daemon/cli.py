"""The ``depthnav`` command line: run, replay, calibrate, record, mount, devices, info, bench.

The only module that prints to stderr or chooses exit codes: 0 ok (or stopped by SIGTERM), 1 runtime
failure, 2 bad usage or config, 130 interrupted (Ctrl-C).
"""

from __future__ import annotations

import argparse
import logging
import os
import signal
import sys
import threading
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

from depthnav_daemon import __version__
from depthnav_daemon.errors import ConfigError, DepthnavError
from drivers.errors import DeviceSpecError, DriverError

if TYPE_CHECKING:
    from depthnav_daemon.pipeline.geometry import Mount

log = logging.getLogger("depthnav_daemon.cli")

EXIT_OK, EXIT_FAIL, EXIT_USAGE, EXIT_INTERRUPTED = 0, 1, 2, 130


class _Parser(argparse.ArgumentParser):
    """argparse that reports usage errors as one line plus a hint, with exit code 2."""

    def error(self, message: str) -> None:  # type: ignore[override]
        self.exit(
            EXIT_USAGE,
            f"depthnav: error: {message}\ndepthnav: hint: {self.prog} --help shows the options\n",
        )


def _add_config_args(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "-c",
        "--config",
        action="append",
        default=[],
        metavar="FILE",
        type=Path,
        help="config file (TOML, or a depth_nav_tools ROS .yaml); repeat, later files win",
    )
    p.add_argument(
        "--set",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="override one config key, e.g. --set scan.range_max_m=4 (wins over files)",
    )
    p.add_argument("--height-m", type=float, help="sensor height above the floor, metres")
    p.add_argument("--tilt-deg", type=float, help="sensor tilt, degrees, positive = pitched down")
    p.add_argument("--roll-deg", type=float, help="sensor roll, degrees, positive = left side up")
    p.add_argument("--method", choices=("exact", "paper"), help="scan method (default exact)")


def _add_run_args(p: argparse.ArgumentParser, device_required: bool) -> None:
    if device_required:
        p.add_argument(
            "--device",
            help="device spec: kinect, openni://, replay:PATH, ... (see: depthnav devices)",
        )
    p.add_argument(
        "--sink",
        action="append",
        default=None,
        metavar="SPEC",
        help="output: stdout, udp://HOST:PORT, rerun, rerun:FILE.rrd, rerun+grpc://HOST:PORT, "
        "mavlink:PORT?baud=N, mavlink+udp://HOST:PORT, null; repeat for several",
    )
    p.add_argument("--max-frames", type=int, metavar="N", help="stop after N frames")
    _add_config_args(p)


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(
        prog="depthnav", description="Depth sensor to laser scan, cliffs and mount pose for robots."
    )
    parser.add_argument("--version", action="version", version=f"depthnav {__version__}")
    parser.add_argument(
        "-v", "--verbose", action="count", default=0, help="-v debug logs, -vv with tracebacks"
    )
    parser.add_argument(
        "-q", "--quiet", action="store_true", default=False, help="warnings and errors only"
    )
    # the same flags after the subcommand; SUPPRESS keeps the values given before it
    common = argparse.ArgumentParser(add_help=False)
    common.add_argument(
        "-v", "--verbose", action="count", default=argparse.SUPPRESS, help=argparse.SUPPRESS
    )
    common.add_argument(
        "-q", "--quiet", action="store_true", default=argparse.SUPPRESS, help=argparse.SUPPRESS
    )
    sub = parser.add_subparsers(dest="command", required=True, parser_class=_Parser)
    _add = sub.add_parser
    sub.add_parser = lambda *a, **k: _add(*a, parents=[common], **k)  # type: ignore[method-assign]

    p = sub.add_parser("run", help="process a device and stream the results")
    _add_run_args(p, device_required=True)
    p.set_defaults(handler=cmd_run)

    p = sub.add_parser("replay", help="process a recording (alias of run --device replay:PATH)")
    p.add_argument("path", help="recording folder, .npz, PNG folder, fakenect folder or .oni file")
    p.add_argument(
        "--rate", choices=("realtime", "max"), default="max", help="pacing (default max)"
    )
    p.add_argument("--loop", action="store_true", help="start again at the end")
    _add_run_args(p, device_required=False)
    p.set_defaults(handler=cmd_replay)

    p = sub.add_parser("calibrate", help="estimate the sensor height, tilt and roll from the floor")
    p.add_argument("--device", required=True, help="device spec")
    p.add_argument("--frames", type=int, default=30, metavar="N", help="frames to use (default 30)")
    p.add_argument("--json", action="store_true", help="print one JSON object instead of text")
    p.add_argument(
        "--write", type=Path, metavar="FILE", help="write the [mount] section into this TOML file"
    )
    _add_config_args(p)
    p.set_defaults(handler=cmd_calibrate)

    p = sub.add_parser(
        "record", help="record a device's frames as a depthnav recording (a fixture)"
    )
    p.add_argument("--device", required=True, help="device spec")
    p.add_argument(
        "--frames", type=int, default=30, metavar="N", help="frames to record (default 30)"
    )
    p.add_argument("--description", default="", help="one line about the scene")
    p.add_argument("out", type=Path, help="new folder to write")
    p.set_defaults(handler=cmd_record)

    p = sub.add_parser(
        "mount", help="dead zones and highest visible obstacle for a mount (eq. 15-16)"
    )
    p.add_argument("--height-m", type=float, required=True, help="sensor height, metres")
    p.add_argument("--tilt-deg", type=float, required=True, help="tilt, degrees, positive = down")
    p.add_argument(
        "--sensor", default="kinect", help="kinect, xtion, kinect2, realsense-d435 (field of view)"
    )
    p.add_argument("--vfov-deg", type=float, help="vertical field of view, overrides --sensor")
    p.add_argument("--distances-m", default="0.5,1,1.5,2,3,4,5", help="comma-separated distances")
    p.add_argument("--plot", type=Path, metavar="PNG", help="also draw the side view to this PNG")
    p.set_defaults(handler=cmd_mount)

    p = sub.add_parser("devices", help="list the devices that can be opened here")
    p.set_defaults(handler=cmd_devices)
    p = sub.add_parser("info", help="versions, drivers and native libraries found")
    p.set_defaults(handler=cmd_info)

    p = sub.add_parser("bench", help="time every stage and the whole pipeline")
    p.add_argument(
        "--device",
        help="recording or device to time on (default: the bundled fixtures/corridor_step)",
    )
    p.add_argument("--json", action="store_true", help="print JSON")
    p.add_argument(
        "--rounds", type=int, default=7, metavar="N", help="interleaved timing rounds (default 7)"
    )
    p.add_argument(
        "--resolutions",
        action="store_true",
        help="also time synthetic frames at 640x480, 512x424, 848x480 and 1280x720",
    )
    p.add_argument(
        "--cpu-30fps",
        type=float,
        default=0.0,
        metavar="SECONDS",
        nargs="?",
        const=20.0,
        help="also run depthnav run at 30 frames/s to UDP and report its CPU share (default 20 s)",
    )
    p.add_argument(
        "--startup",
        action="store_true",
        help="also time depthnav run to its first output (5 runs, warm kernel cache)",
    )
    p.add_argument(
        "--mount",
        metavar="H,TILT,ROLL",
        help="also time synthetic frames seen from this mount (metres, degrees down, degrees "
        "left side up): the exact scan's cost grows with tilt and roll",
    )
    p.add_argument(
        "--quick", action="store_true", help="one short round (a smoke test, not a measurement)"
    )
    p.set_defaults(handler=cmd_bench)
    return parser


def configure_logging(verbose: int, quiet: bool) -> None:
    level = logging.WARNING if quiet else (logging.DEBUG if verbose else logging.INFO)
    handler = logging.StreamHandler(sys.stderr)
    handler.setFormatter(logging.Formatter("depthnav: %(levelname)s: %(message)s"))
    root = logging.getLogger()
    root.handlers[:] = [handler]
    root.setLevel(logging.WARNING)
    for name in ("depthnav_daemon", "drivers"):
        logging.getLogger(name).setLevel(level)


def _overrides(args: argparse.Namespace, device: str | None = None) -> dict[str, Any]:
    out: dict[str, Any] = {}
    mount = {
        k: v
        for k, v in (
            ("height_m", args.height_m),
            ("tilt_deg", args.tilt_deg),
            ("roll_deg", args.roll_deg),
        )
        if v is not None
    }
    if mount:
        out["mount"] = mount
    if args.method:
        out["scan"] = {"method": args.method}
    if device:
        out["device"] = device
    if getattr(args, "sink", None):
        out["sinks"] = args.sink
    return out


def load_config(args: argparse.Namespace, device: str | None):
    from depthnav_daemon.config import build_config

    return build_config(args.config, args.set, _overrides(args, device))


def _install_stop_handlers(stop: threading.Event) -> dict[str, int]:
    """SIGINT and SIGTERM set ``stop``; returns a dict that records which signal came.

    Commands install these before their heavy imports (numpy, numba, the kernels): a
    KeyboardInterrupt raised inside an import ended the process with -SIGINT instead of 130 in
    ~1 of 30 runs signalled 0.1-0.3 s into start-up; a stop flag set during the imports is seen
    by the command as soon as they finish.
    """
    got: dict[str, int] = {}

    def handler(signum: int, _frame: object) -> None:
        got["signal"] = signum
        stop.set()

    signal.signal(signal.SIGINT, handler)
    signal.signal(signal.SIGTERM, handler)
    return got


def _run(args: argparse.Namespace, device: str | None) -> int:
    stop = threading.Event()
    got = _install_stop_handlers(stop)  # before the imports: see _install_stop_handlers
    from depthnav_daemon.daemon import run

    cfg = load_config(args, device)
    if not cfg.device:
        raise ConfigError(
            "no device given", hint="use --device SPEC or set device in a config file"
        )
    if args.max_frames is not None and args.max_frames < 1:
        raise ConfigError(f"--max-frames={args.max_frames} is out of range (accepted: 1 or more)")
    serial = None
    if cfg.daemon.serial_tilt:
        from drivers.serial_tilt import SerialTiltSource

        serial = SerialTiltSource.from_spec(cfg.daemon.serial_tilt)
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


def cmd_calibrate(args: argparse.Namespace) -> int:
    if args.frames < 1:
        raise ConfigError(f"--frames={args.frames} is out of range (accepted: 1 or more)")
    stop = threading.Event()
    got = _install_stop_handlers(stop)  # before the imports: see _install_stop_handlers
    from depthnav_daemon.calibrate import calibrate, format_text, write_mount

    cfg = load_config(args, args.device)
    result = calibrate(
        cfg, args.frames, stop, progress=_progress_bar("calibrating") if not args.json else None
    )
    if got.get("signal") == signal.SIGINT:
        return EXIT_INTERRUPTED
    if args.json:
        import json

        print(json.dumps(result.as_dict(), allow_nan=False))  # noqa: T201
    else:
        print(format_text(result))  # noqa: T201
    if args.write:
        write_mount(args.write, result)
        log.info("wrote [mount] to %s", args.write)
    return EXIT_OK


def _progress_bar(label: str, unit: str = "frames"):
    """A one-line progress bar on stderr when it is a terminal; log lines otherwise.

    The log lines come at every quarter of ``total`` crossed and at the end, also for callers
    that skip values (compression reports every few MiB).
    """
    tty = sys.stderr.isatty()
    last = [0]

    def show(done: int, total: int) -> None:
        step = max(total // 4, 1)
        if tty:
            width = 30
            filled = int(width * done / max(total, 1))
            end = "\n" if done >= total else ""
            sys.stderr.write(
                f"\r{label} [{'#' * filled}{'.' * (width - filled)}] {done}/{total} {unit}{end}"
            )
            sys.stderr.flush()
        elif done == total or done // step > last[0] // step:
            log.info("%s: %d/%d %s", label, done, total, unit)
        last[0] = done

    return show


def _mib(n_bytes: int) -> int:
    """Bytes in whole MiB, rounded up (so a finished count equals its total)."""
    return -(-n_bytes // (1 << 20))


def cmd_record(args: argparse.Namespace) -> int:
    if args.frames < 1:
        raise ConfigError(f"--frames={args.frames} is out of range (accepted: 1 or more)")
    stop = threading.Event()
    got = _install_stop_handlers(stop)  # before the imports: see _install_stop_handlers
    from drivers import create_driver, iter_frames, opened
    from drivers.recording_writer import write_recording

    driver = create_driver(args.device)
    recording = _progress_bar("recording")
    compressing = _progress_bar("compressing", unit="MiB")
    taken = [0]

    def took(k: int) -> None:
        taken[0] = k
        recording(k, args.frames)

    def compressed(done: int, total: int) -> None:
        if taken[0] < args.frames and sys.stderr.isatty():
            sys.stderr.write("\n")  # a stop left the recording bar's line open
        taken[0] = args.frames
        compressing(_mib(done), _mib(total))

    def while_compressing(signum: int, _frame: object) -> None:
        if got.get("abandon"):
            log.warning("recording abandoned: nothing is written to %s", args.out)
            raise KeyboardInterrupt  # write_recording removes its partial files
        got["abandon"] = signum
        got.setdefault("signal", signum)
        log.warning(
            "finishing %s with the frames recorded; stop again to abandon the recording", args.out
        )

    def frames():
        for i, frame in enumerate(iter_frames(driver, stop)):
            if i >= args.frames:
                break
            yield frame
        driver.close()  # the device is not needed while the frames are compressed
        signal.signal(signal.SIGINT, while_compressing)
        signal.signal(signal.SIGTERM, while_compressing)

    with opened(driver):
        n = write_recording(
            args.out,
            frames(),
            description=args.description,
            device=args.device,
            progress=took,
            progress_compress=compressed,
        )
    log.info("recorded %d frames into %s", n, args.out)
    return EXIT_INTERRUPTED if got.get("signal") == signal.SIGINT else EXIT_OK


def cmd_mount(args: argparse.Namespace) -> int:
    from depthnav_daemon.mount_cli import mount_report

    text = mount_report(
        args.height_m, args.tilt_deg, args.sensor, args.vfov_deg, args.distances_m, args.plot
    )
    print(text)  # noqa: T201
    return EXIT_OK


def cmd_devices(_args: argparse.Namespace) -> int:
    from drivers import detect_devices

    found = detect_devices()
    if not found:
        print("no devices found (a recording plays with --device replay:PATH)")  # noqa: T201
    for spec, description in found:
        print(f"{spec:<28} {description}")  # noqa: T201
    return EXIT_OK


def cmd_info(_args: argparse.Namespace) -> int:
    import platform

    import numpy as np

    from drivers import describe_backends

    lines = [
        f"depthnav {__version__}",
        f"python {platform.python_version()} ({sys.executable})",
        f"numpy {np.__version__}",
    ]
    for mod in ("numba", "rerun", "pymavlink", "serial", "usb", "openni", "PIL"):
        try:
            m = __import__(mod)
            lines.append(f"{mod} {getattr(m, '__version__', getattr(m, 'VERSION', 'present'))}")
        except ImportError:
            lines.append(f"{mod} missing")
    lines += [f"driver {name}: {status}" for name, status in describe_backends()]
    print("\n".join(lines))  # noqa: T201
    return EXIT_OK


def cmd_bench(args: argparse.Namespace) -> int:
    from depthnav_daemon.bench import main as bench_main

    if args.rounds < 1:
        raise ConfigError(f"--rounds={args.rounds} is out of range (accepted: 1 or more)")
    if args.cpu_30fps < 0:
        raise ConfigError(f"--cpu-30fps={args.cpu_30fps} is out of range (accepted: seconds > 0)")
    mount = _parse_mount(args.mount) if args.mount is not None else None
    return bench_main(
        device=args.device,
        as_json=args.json,
        resolutions=args.resolutions,
        cpu_seconds=args.cpu_30fps,
        startup=args.startup,
        rounds=args.rounds,
        quick=args.quick,
        mount=mount,
    )


def _parse_mount(text: str) -> Mount:
    """``H,TILT,ROLL`` (metres, degrees, degrees) as a Mount; a bad value is a ConfigError."""
    from depthnav_daemon.pipeline.geometry import Mount

    parts = text.split(",")
    try:
        if len(parts) != 3:
            raise ValueError
        height_m, tilt_deg, roll_deg = (float(x) for x in parts)
    except ValueError:
        raise ConfigError(
            f"--mount={text!r} is not H,TILT,ROLL", hint="e.g. --mount 0.55,30,5"
        ) from None
    return Mount(height_m, tilt_deg, roll_deg)


def main(argv: Sequence[str] | None = None) -> int:
    """Run the CLI; returns the exit code (never raises for bad input)."""
    parser = build_parser()
    args = parser.parse_args(argv)
    configure_logging(args.verbose, args.quiet)
    try:
        return int(args.handler(args))
    except (DepthnavError, DriverError) as exc:
        log.debug("traceback", exc_info=args.verbose >= 2)
        sys.stderr.write(
            f"depthnav: error: {str(exc).splitlines()[0] if str(exc) else type(exc).__name__}\n"
        )
        if getattr(exc, "hint", None):
            sys.stderr.write(f"depthnav: hint: {exc.hint}\n")
        if isinstance(exc, DeviceSpecError):
            return EXIT_USAGE
        return int(getattr(exc, "exit_code", EXIT_FAIL))
    except KeyboardInterrupt:
        return EXIT_INTERRUPTED
    except BrokenPipeError:
        return EXIT_OK  # the reader went away (e.g. `| head`); nothing left to say
    except Exception as exc:
        log.debug("traceback", exc_info=True)
        sys.stderr.write(
            f"depthnav: internal error: {type(exc).__name__}: {exc}\n"
            "depthnav: hint: run again with -vv for the traceback and report it\n"
        )
        return EXIT_FAIL


class _EarlyStop(BaseException):
    """SIGTERM before the command installed its graceful stop (start-up, imports, config)."""


def _stop_early(signum: int, _frame: object) -> None:
    raise _EarlyStop(signum)


def entry_point() -> None:
    """Console-script entry: exit with main()'s code.

    Until a command installs its own handlers (which finish the current frame and close every
    sink), SIGTERM ends start-up at once with exit code 0 and SIGINT with 130, never with a
    traceback: nothing has been opened or written yet at that point.
    """
    signal.signal(signal.SIGTERM, _stop_early)
    signal.signal(signal.SIGINT, signal.default_int_handler)  # KeyboardInterrupt from here on
    try:
        code = main()
    except _EarlyStop:
        code = EXIT_OK
    except KeyboardInterrupt:
        code = EXIT_INTERRUPTED
    _exit_now_if_a_viewer_is_stuck(code)
    sys.exit(code)


def _exit_now_if_a_viewer_is_stuck(code: int) -> None:
    """End the process at once when a rerun viewer thread is stuck (see abandoned_viewers()).

    Every sink is closed by now; only the interpreter's teardown is skipped, which would wait 5 s
    for the gone viewer and could abort (SIGABRT, 'terminate called without an active exception').
    """
    rerun_sink = sys.modules.get("depthnav_daemon.sinks.rerun")
    if rerun_sink is None or not rerun_sink.abandoned_viewers():
        return
    logging.shutdown()
    for stream in (sys.stdout, sys.stderr):
        try:
            stream.flush()
        except (OSError, ValueError):
            pass
    os._exit(code)
