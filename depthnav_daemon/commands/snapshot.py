"""``depthnav snapshot``: one frame of any device or recording drawn as the paper's figs. 9 and 13.

The frames up to the one asked for go through the daemon's own frame loop (``daemon.loop.run``:
mount tracking, the floor estimate on its schedule, the stages with the obstacle mask, the obstacle
memory with the frames' or the configured odometry), so the picture shows exactly what
``depthnav run`` computes for that frame, memory included.
"""

from __future__ import annotations

import argparse
import dataclasses
import logging
import signal
import threading
from typing import TYPE_CHECKING

from depthnav_daemon.commands.common import (
    EXIT_INTERRUPTED,
    EXIT_OK,
    figure_output,
    install_stop_handlers,
    load_config,
    save_figure,
)
from depthnav_daemon.errors import ConfigError, DepthnavError

if TYPE_CHECKING:
    from depthnav_daemon.config.loader import Config
    from depthnav_daemon.pipeline import Result
    from drivers.base import Frame

log = logging.getLogger(__name__)

MAX_FRAME = 100_000
FOOTPRINT_LIMITS_M = (0.05, 5.0)
TITLE_CHARS = 40


def footprint(text: str) -> tuple[float, float]:
    """``LENGTH,WIDTH`` in metres.

    Raises:
        ConfigError: not two numbers in 0.05..5 m.
    """
    try:
        length, width = (float(t) for t in text.split(","))
    except ValueError:
        raise ConfigError(
            f"--footprint-m={text!r} is not LENGTH,WIDTH in metres",
            hint="e.g. --footprint-m 0.5,0.4",
        ) from None
    lo, hi = FOOTPRINT_LIMITS_M
    if not (lo <= length <= hi and lo <= width <= hi):
        raise ConfigError(f"--footprint-m={text!r} is out of range (accepted: 0.05..5 m each)")
    return length, width


class FrameCapture:
    """The snapshot's sink: keeps the frame and Result of the frame asked for (the loop's
    ``index``-th processed frame, counting from 0) and counts what it was given."""

    needs_obstacle_mask = True  # the snapshot draws the obstacle pixels

    def __init__(self, index: int) -> None:
        self.name = "snapshot"
        self.index = index
        self.seen = 0
        self.got: tuple[Frame, Result] | None = None

    def open(self, context: object) -> None:
        """Nothing to open."""

    def write(self, frame: Frame, result: Result) -> None:
        if self.seen == self.index:
            self.got = (frame, result)
        self.seen += 1

    def close(self) -> None:
        """Nothing to close."""


def grab(cfg: Config, index: int, stop: threading.Event) -> tuple[Frame, Result]:
    """Frames 0..index of ``cfg.device`` through the daemon's own frame loop (``daemon.loop.run``:
    mount tracking, the floor estimate on its schedule, the obstacle memory with the frames'
    odometry or the configured source, several sensors merged); the last one's frame and Result,
    as ``depthnav run`` would have sent it.

    Raises:
        DepthnavError: the device ended before frame ``index`` or was stopped.
        DriverError: the device failed.
    """
    from depthnav_daemon.daemon.loop import run
    from depthnav_daemon.daemon.notify import ServiceNotifier

    capture = FrameCapture(index)
    quiet = ServiceNotifier(environ={})  # a snapshot is no service: nothing to tell systemd
    run(
        dataclasses.replace(cfg, sinks=(capture.name,)),
        stop,
        max_frames=index + 1,
        sink_factory=lambda _spec: capture,
        notifier=quiet,
    )
    if capture.got is not None:
        return capture.got
    if stop.is_set():
        raise DepthnavError("stopped before the frame was reached")
    seen = capture.seen
    raise DepthnavError(
        f"{cfg.device} ended after {seen} frames: there is no frame {index}",
        hint=f"give --frame between 0 and {max(seen - 1, 0)}",
    )


def cmd_snapshot(args: argparse.Namespace) -> int:
    out, _ = figure_output(args.out, "the output file")
    if not (0 <= args.frame <= MAX_FRAME):
        raise ConfigError(f"--frame={args.frame} is out of range (accepted: 0..{MAX_FRAME})")
    size = footprint(args.footprint_m)
    stop = threading.Event()
    got = install_stop_handlers(stop)  # before the heavy imports: see install_stop_handlers
    cfg = load_config(args, args.device)
    frame, result = grab(cfg, args.frame, stop)
    if got.get("signal") == signal.SIGINT:
        return EXIT_INTERRUPTED
    from depthnav_daemon.plots.snapshot import draw_snapshot

    fig = draw_snapshot(
        frame, result, cfg.scan.range_max_m, _short(cfg.device), size, scan_params=cfg.scan,
        body_m=cfg.robot.footprint_m,
    )  # fmt: skip
    save_figure(fig, out, "the output file")
    print(f"frame {result.seq} of {cfg.device} drawn to {out}")  # noqa: T201
    return EXIT_OK


def _short(spec: str) -> str:
    """The device spec without options, shortened to its last path parts."""
    base = spec.split("?", maxsplit=1)[0].rstrip("/")
    return base if len(base) <= TITLE_CHARS else "..." + base[3 - TITLE_CHARS :]
