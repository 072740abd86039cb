"""``depthnav record``: a device's frames into a depthnav recording (a fixture)."""

from __future__ import annotations

import argparse
import logging
import signal
import sys
import threading

from depthnav_daemon.commands.common import (
    EXIT_OK,
    STOP_SIGNALS,
    install_stop_handlers,
    mib,
    note_stop_signal,
    progress_bar,
    stopped_code,
)
from depthnav_daemon.errors import ConfigError

log = logging.getLogger(__name__)


def _utf8(text: str) -> bool:
    """True if ``text`` can be written as UTF-8 (command-line bytes that were not UTF-8 come in
    as lone surrogates, which cannot)."""
    try:
        text.encode("utf-8")
    except UnicodeEncodeError:
        return False
    return True


def cmd_record(args: argparse.Namespace) -> int:
    if args.frames < 1:
        raise ConfigError(f"--frames={args.frames} is out of range (accepted: 1 or more)")
    # checked before a frame is read: the metadata is written last, after every frame
    if not _utf8(args.description):
        raise ConfigError(
            "--description is not UTF-8 text", hint="write it in a UTF-8 terminal or locale"
        )
    # a device path that is not UTF-8 still records; recording.toml names it with U+FFFD
    device_text = args.device.encode("utf-8", "surrogateescape").decode("utf-8", "replace")
    stop = threading.Event()
    got = install_stop_handlers(stop)  # before the heavy imports: see install_stop_handlers
    from drivers import create_driver, iter_frames, opened
    from drivers.errors import RecordingError
    from drivers.formats.recording_writer import write_recording

    driver = create_driver(args.device)
    recording = progress_bar("recording")
    compressing = progress_bar("compressing", unit="MiB")
    taken = [0]

    def took(k: int) -> None:
        taken[0] = k
        recording(k, args.frames)

    def compressed(done: int, total: int) -> None:
        if taken[0] < args.frames and sys.stderr.isatty():
            sys.stderr.write("\n")  # a stop left the recording bar's line open
        taken[0] = args.frames
        compressing(mib(done), mib(total))

    def while_compressing(signum: int, _frame: object) -> None:
        note_stop_signal(signum)
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
        for sig in STOP_SIGNALS:
            signal.signal(sig, while_compressing)

    try:
        with opened(driver):
            n = write_recording(
                args.out,
                frames(),
                description=args.description,
                device=device_text,
                progress=took,
                progress_compress=compressed,
            )
    except RecordingError:
        if "signal" not in got or taken[0]:
            raise
        # a stop before the first frame is a clean stop, not a failed recording
        log.warning("stopped before the first frame: nothing was recorded into %s", args.out)
        return stopped_code(got)
    if n < args.frames and "signal" not in got:
        log.warning(
            "%s ended after %d of the %d frames asked for; recorded %d into %s",
            args.device,
            n,
            args.frames,
            n,
            args.out,
        )
    else:
        log.info("recorded %d frames into %s", n, args.out)
    return stopped_code(got) if "signal" in got else EXIT_OK
