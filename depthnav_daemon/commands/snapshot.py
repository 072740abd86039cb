"""``depthnav snapshot``: one frame of any device or recording drawn as the paper's figs. 9 and 13.

The frames up to the one asked for go through the daemon's own frame step (mount tracking, the
floor pose stage on its schedule, then the pipeline with the obstacle mask), so the picture shows
exactly what ``depthnav run`` computes for that frame.
"""

from __future__ import annotations

import argparse
import logging
import signal
import threading
import time
from typing import TYPE_CHECKING

from depthnav_daemon.commands.common import (
    EXIT_INTERRUPTED,
    EXIT_OK,
    install_stop_handlers,
    load_config,
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
FIRST_FRAME_WAIT_S = 10.0  # a live sensor may take seconds to start streaming


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


def grab(cfg: Config, index: int, stop: threading.Event) -> tuple[Frame, Result]:
    """Frames 0..index of ``cfg.device`` through the daemon's frame step; the last one's result.

    Raises:
        DepthnavError: the device ended before frame ``index`` or was stopped.
        DriverError: the device failed.
    """
    from depthnav_daemon.daemon.frame_step import FrameStep
    from depthnav_daemon.pipeline import StageParams
    from drivers import create_driver, opened
    from drivers.errors import FrameTimeout

    params = StageParams(
        scan=cfg.scan, cliff=cfg.cliff if cfg.daemon.cliff else None, obstacle_mask=True
    )
    step = FrameStep(cfg, params, None)
    seen = 0
    try:
        with opened(create_driver(cfg.device)) as driver:
            deadline = time.monotonic() + FIRST_FRAME_WAIT_S
            while not stop.is_set():
                try:
                    frame = driver.read_frame(timeout_s=0.25)
                except FrameTimeout:
                    if time.monotonic() > deadline:
                        raise
                    continue
                if frame is None:
                    break
                deadline = time.monotonic() + FIRST_FRAME_WAIT_S
                result = step.run(frame)
                if seen == index:
                    return frame, result
                seen += 1
    finally:
        step.close()
    if stop.is_set():
        raise DepthnavError("stopped before the frame was reached")
    raise DepthnavError(
        f"{cfg.device} ended after {seen} frames: there is no frame {index}",
        hint=f"give --frame between 0 and {max(seen - 1, 0)}",
    )


def cmd_snapshot(args: argparse.Namespace) -> int:
    from depthnav_daemon.plots import check_output

    out, _ = check_output(args.out, "the output file")
    if not (0 <= args.frame <= MAX_FRAME):
        raise ConfigError(f"--frame={args.frame} is out of range (accepted: 0..{MAX_FRAME})")
    size = footprint(args.footprint_m)
    stop = threading.Event()
    got = install_stop_handlers(stop)  # before the heavy imports: see install_stop_handlers
    cfg = load_config(args, args.device)
    frame, result = grab(cfg, args.frame, stop)
    if got.get("signal") == signal.SIGINT:
        return EXIT_INTERRUPTED
    from depthnav_daemon.plots import save
    from depthnav_daemon.plots.snapshot import draw_snapshot

    fig = draw_snapshot(frame, result, cfg.scan.range_max_m, _short(cfg.device), size)
    save(fig, out, "the output file")
    print(f"frame {result.seq} of {cfg.device} drawn to {out}")  # noqa: T201
    return EXIT_OK


def _short(spec: str) -> str:
    """The device spec without options, shortened to its last path parts."""
    base = spec.split("?", maxsplit=1)[0].rstrip("/")
    return base if len(base) <= TITLE_CHARS else "..." + base[3 - TITLE_CHARS :]
