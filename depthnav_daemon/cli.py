"""The ``depthnav`` command line: run, replay, calibrate, record, mount, snapshot, devices, info,
bench, warmup.

The only module that prints to stderr or chooses exit codes: 0 ok (or stopped by SIGTERM), 1 runtime
failure, 2 bad usage or config, 130 interrupted (Ctrl-C).
"""

from __future__ import annotations

import argparse
import importlib
import logging
import os
import signal
import sys
from collections.abc import Callable, Sequence
from pathlib import Path
from types import FrameType
from typing import Any

from depthnav_daemon import __version__
from depthnav_daemon.commands.common import (
    EXIT_FAIL,
    EXIT_INTERRUPTED,
    EXIT_OK,
    EXIT_USAGE,
    STOP_SIGNALS,
    bound_message,
    note_stop_signal,
    stop_signal_received,
    stopped_code,
)
from depthnav_daemon.errors import DepthnavError
from depthnav_daemon.stdio import configure_logging, guard_standard_fds, say

# Light on purpose: this module is what the ``depthnav`` console script imports before
# entry_point() can install the start-up stop handlers, so it imports nothing of drivers (whose
# package imports numpy: 0.1-0.25 s in which SIGTERM killed the process by the signal). drivers
# is imported in build_parser() and main(), after the handlers.

DEVICE_HELP = (
    "device spec: kinect, openni://, replay:PATH, ... (options below; see depthnav devices)"
)


def _with_spec_help() -> dict[str, Any]:
    """The device spec options, from the table the drivers check them against, below a
    command's help."""
    from drivers.spec_options import help_text

    return {"epilog": help_text(), "formatter_class": argparse.RawDescriptionHelpFormatter}


TRACEBACK_VERBOSITY = 2  # -vv shows tracebacks
log = logging.getLogger("depthnav_daemon.cli")


class _Parser(argparse.ArgumentParser):
    """argparse that reports usage errors as one line plus a hint, with exit code 2."""

    def error(self, message: str) -> None:  # type: ignore[override]
        self.exit(
            EXIT_USAGE,
            f"depthnav: error: {bound_message(message)}\n"
            f"depthnav: hint: {self.prog} --help shows the options\n",
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
        p.add_argument("--device", help=DEVICE_HELP)
    p.add_argument(
        "--sink",
        action="append",
        default=None,
        metavar="SPEC",
        help="output: stdout, text, udp://HOST:PORT, rerun, rerun:FILE.rrd, "
        "rerun+grpc://HOST:PORT, mavlink:PORT?baud=N, mavlink+udp://HOST:PORT, "
        "rosbag:FILE.mcap|.bag, ros2[?domain=N], foxglove://HOST:PORT, foxglove:FILE.mcap, null; "
        "repeat for several",
    )
    p.add_argument("--max-frames", type=int, metavar="N", help="stop after N frames")
    p.add_argument(
        "--odometry",
        metavar="SPEC",
        help="the robot's odometry, for the obstacle memory: odom+udp://127.0.0.1:PORT, "
        "mavlink+udp://HOST:PORT, mavlink:SERIALPORT (sets [odometry] source)",
    )
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

    _add_run_commands(sub)
    _add_setup_commands(sub)
    _add_tool_commands(sub)
    return parser


def _add_run_commands(sub: Any) -> None:
    """``run`` and ``replay``."""
    spec_help = _with_spec_help()
    p = sub.add_parser("run", help="process a device and stream the results", **spec_help)
    _add_run_args(p, device_required=True)
    p.set_defaults(handler="run:cmd_run")

    p = sub.add_parser(
        "replay", help="process a recording (alias of run --device replay:PATH)", **spec_help
    )
    p.add_argument(
        "path",
        help="recording folder, .npz, .npy, PNG/PGM folder, fakenect folder, .oni file or ROS bag",
    )
    p.add_argument(
        "--rate",
        choices=("realtime", "max"),
        default=None,
        help="pacing (default max; PATH?rate=.. works too)",
    )
    p.add_argument(
        "--loop", action="store_true", help="start again at the end (PATH?loop=1 works too)"
    )
    _add_run_args(p, device_required=False)
    p.set_defaults(handler="run:cmd_replay")


def _add_setup_commands(sub: Any) -> None:
    """``calibrate``, ``record`` and ``mount``: setting a sensor up."""
    spec_help = _with_spec_help()
    p = sub.add_parser(
        "calibrate",
        help="estimate the sensor height, tilt and roll from the floor",
        **spec_help,
    )
    p.add_argument("--device", required=True, help=DEVICE_HELP)
    p.add_argument("--frames", type=int, default=30, metavar="N", help="frames to use (default 30)")
    p.add_argument("--json", action="store_true", help="print one JSON object instead of text")
    p.add_argument(
        "--write", type=Path, metavar="FILE", help="write the [mount] section into this TOML file"
    )
    _add_config_args(p)
    p.set_defaults(handler="calibrate:cmd_calibrate")

    p = sub.add_parser(
        "record",
        help="record a device's frames as a depthnav recording (a fixture), or export them",
        **spec_help,
    )
    p.add_argument("--device", required=True, help=DEVICE_HELP)
    p.add_argument(
        "--frames", type=int, default=30, metavar="N", help="frames to record (default 30)"
    )
    p.add_argument("--description", default="", help="one line about the scene")
    p.add_argument(
        "--odometry",
        metavar="SPEC",
        help="also store the robot's odometry with every frame (odom+udp://127.0.0.1:PORT, "
        "mavlink+udp://HOST:PORT, mavlink:SERIALPORT)",
    )
    p.add_argument(
        "--format",
        choices=("depthnav", "png", "oni", "fakenect"),
        default="depthnav",
        help="depthnav (default: everything, compressed), png (folder of 16-bit millimetre PNGs "
        "with depth.txt and camera.toml, TUM style), oni (OpenNI2 file, OUT ends in .oni), "
        "fakenect (libfreenect's folder, 640x480 only)",
    )
    p.add_argument("out", type=Path, help="new folder to write (a new file for --format oni)")
    p.set_defaults(handler="record:cmd_record")

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
    p.add_argument(
        "--robot-height-m",
        type=float,
        metavar="M",
        help="the robot's height: from where obstacles that high are seen (eq. 16)",
    )
    p.add_argument(
        "--plot", type=Path, metavar="FILE", help="draw the side view to scale (.png or .svg)"
    )
    p.add_argument(
        "--sweep",
        type=Path,
        metavar="FILE",
        help="draw dead zone and highest obstacle seen against tilt (fig. 6; .png or .svg)",
    )
    p.set_defaults(handler="mount:cmd_mount")


def _add_tool_commands(sub: Any) -> None:
    """``devices``, ``info``, ``snapshot``, ``bench`` and ``warmup``."""
    spec_help = _with_spec_help()
    p = sub.add_parser("devices", help="list the devices that can be opened here")
    p.set_defaults(handler="info:cmd_devices")
    p = sub.add_parser("info", help="versions, drivers and native libraries found")
    p.set_defaults(handler="info:cmd_info")

    p = sub.add_parser(
        "snapshot",
        help="draw one frame: depth with obstacles and drop-offs, and a top-down view",
        **spec_help,
    )
    p.add_argument("--device", required=True, help=DEVICE_HELP)
    p.add_argument(
        "--frame", type=int, default=0, metavar="N", help="the frame to draw, from 0 (default 0)"
    )
    p.add_argument(
        "--footprint-m",
        default="0.45,0.40",
        metavar="LENGTH,WIDTH",
        help="the robot drawn behind the sensor, metres (default 0.45,0.40)",
    )
    p.add_argument("out", type=Path, help="the picture to write (.png or .svg)")
    _add_config_args(p)
    p.set_defaults(handler="snapshot:cmd_snapshot")

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
    p.set_defaults(handler="bench.command:cmd_bench")

    p = sub.add_parser(
        "warmup",
        help="compile every kernel now, into the cache the daemon (or the service) uses",
        description="Compile every numeric kernel the daemon can use into a cache, so that its "
        "first start compiles nothing. scripts/install.sh runs it for the service.",
    )
    p.add_argument(
        "--cache-dir",
        type=Path,
        metavar="DIR",
        help="the cache (default: $NUMBA_CACHE_DIR, else ~/.cache/depthnav/numba); the service "
        "uses /var/cache/depthnav/numba",
    )
    p.add_argument(
        "--owner",
        metavar="USER",
        help="give the cache to this user (as root: the service's user, depthnav)",
    )
    p.set_defaults(handler="warmup:cmd_warmup")


def _handler(name: str) -> Callable[[argparse.Namespace], int]:
    """The command function ``module:function`` of depthnav_daemon.commands, imported now: each
    command imports only what it needs, after installing its stop handlers."""
    module, function = name.split(":")
    return getattr(importlib.import_module(f"depthnav_daemon.commands.{module}"), function)


# commands whose result is what they print: with stdout closed it would be lost without a word
_PRINTING = {"info:cmd_info", "info:cmd_devices", "mount:cmd_mount", "calibrate:cmd_calibrate"}


def main(argv: Sequence[str] | None = None) -> int:
    """Run the CLI; returns the exit code (never raises for bad input)."""
    from drivers.errors import DriverError

    parser = build_parser()
    args = parser.parse_args(argv)
    configure_logging(args.verbose, args.quiet)
    if sys.stdout is None and args.handler in _PRINTING:
        log.warning("stdout is closed: what this command prints is lost")
    try:
        command = _handler(args.handler)
        if _early["installed"]:
            _stop_ends_bag_reads()
            if stop_signal_received() is not None:
                raise _EarlyStop(stop_signal_received())  # noted while the command was imported
        return int(command(args))
    except (DepthnavError, DriverError) as exc:
        return _error_code(exc, args)
    except KeyboardInterrupt:
        return EXIT_INTERRUPTED
    except BrokenPipeError:
        return EXIT_OK  # the reader went away (e.g. `| head`); nothing left to say
    except Exception as exc:
        log.debug("traceback", exc_info=True)
        say(
            f"depthnav: internal error: {type(exc).__name__}: {exc}\n"
            "depthnav: hint: run again with -vv for the traceback and report it\n"
        )
        return EXIT_FAIL


def _error_code(exc: Exception, args: argparse.Namespace) -> int:
    """Say a DepthnavError or DriverError in one line (and its hint); its exit code."""
    from drivers.errors import DeviceSpecError
    from drivers.formats.bag_limits import StoppedError

    if isinstance(exc, StoppedError) and stop_signal_received() is not None:
        # a bag's probing ended for the stop signal (bag_limits): a stop, not a failure
        log.warning("stopped while opening %s: nothing done", getattr(args, "device", None))
        return stopped_code({"signal": stop_signal_received()})
    log.debug("traceback", exc_info=args.verbose >= TRACEBACK_VERBOSITY)
    say(f"depthnav: error: {str(exc).splitlines()[0] if str(exc) else type(exc).__name__}\n")
    if getattr(exc, "hint", None):
        say(f"depthnav: hint: {exc.hint}\n")  # type: ignore[attr-defined]
    if isinstance(exc, DeviceSpecError):
        return EXIT_USAGE
    return int(getattr(exc, "exit_code", EXIT_FAIL))


def _stop_ends_bag_reads() -> None:
    """A stop signal ends a ROS bag's reading between two pieces of a chunk (its probing at
    start-up can inflate a 256 MiB chunk), in a process run by entry_point."""
    from drivers.formats import bag_limits

    bag_limits.set_stop_check(lambda: stop_signal_received() is not None)


_early = {"installed": False}  # entry_point's start-up handlers are in place (not in-process use)


class _EarlyStop(BaseException):
    """A stop signal before the command installed its graceful stop (start-up, config)."""


def _importing(frame: FrameType | None) -> bool:
    """True if ``frame`` runs inside the import machinery (any frame up the stack)."""
    while frame is not None:
        if frame.f_code.co_filename.startswith("<frozen importlib"):
            return True
        frame = frame.f_back
    return False


def _stop_early(signum: int, frame: FrameType | None) -> None:
    """A stop signal during start-up: noted, then raised where raising is safe.

    Inside the import machinery an exception may be swallowed (importlib's module-lock weakref
    callback printed 'Exception ignored in ... _get_module_lock ... KeyboardInterrupt' and the
    command ran on, in 2 of 200 runs); there the signal is only noted, and acted on when the
    import is done (main()) or the command installs its handlers (install_stop_handlers).
    """
    note_stop_signal(signum)
    if not _importing(frame):
        raise _EarlyStop(signum)


def _note_only(signum: int, _frame: FrameType | None) -> None:
    note_stop_signal(signum)


def entry_point() -> None:
    """Console-script entry: exit with main()'s code.

    Until a command installs its own handlers (which finish the current frame and close every
    sink), SIGTERM and SIGHUP end start-up with exit code 0 and SIGINT with 130, never with a
    traceback: nothing has been opened or written yet at that point. A run stopped by a signal
    ends without the interpreter's teardown (about a second of freeing the kernels' objects)
    once every sink is closed and every stream flushed, so a stop takes well under a second.
    """
    for sig in STOP_SIGNALS:
        signal.signal(sig, _stop_early)
    _early["installed"] = True
    guard_standard_fds()
    code: int | None = None
    while True:  # a stop signal may land anywhere, even while main() returns: each lap takes one
        try:
            if code is None:
                code = main()
            for sig in STOP_SIGNALS:  # everything is closed: a late signal changes nothing
                signal.signal(sig, _note_only)
            break
        except _EarlyStop as stop:
            code = stopped_code({"signal": stop.args[0]}) if code is None else code
        except KeyboardInterrupt:
            code = EXIT_INTERRUPTED if code is None else code
    received = stop_signal_received()
    if received is not None and code == EXIT_OK:
        code = stopped_code({"signal": received})  # noted during an import, never raised
    _exit_now_if_a_viewer_is_stuck(code, force=received is not None)
    sys.exit(code)


def _exit_now_if_a_viewer_is_stuck(code: int, force: bool = False) -> None:
    """End the process at once when a rerun viewer thread is stuck (see abandoned_viewers()), or
    when ``force`` (a stop signal ended the command).

    Every sink is closed by now; only the interpreter's teardown is skipped, which would wait 5 s
    for the gone viewer and could abort (SIGABRT, 'terminate called without an active exception').
    """
    rerun_sink = sys.modules.get("depthnav_daemon.sinks.rerun.rerun")
    stuck = rerun_sink is not None and rerun_sink.abandoned_viewers()
    if not (stuck or force):
        return
    logging.shutdown()
    for stream in (sys.stdout, sys.stderr):
        try:
            stream.flush()
        except (OSError, ValueError, AttributeError):  # AttributeError: a closed stdout (None)
            pass
    os._exit(code)
