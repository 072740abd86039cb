"""``depthnav record``: a device's frames into a depthnav recording (a fixture), or exported as a
folder of 16-bit PNGs, an ``.oni`` file or a fakenect folder for other tools (``--format``)."""

from __future__ import annotations

import argparse
import logging
import signal
import sys
import threading
from collections.abc import Callable, Iterator
from typing import Any

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


def _device_text(args: argparse.Namespace) -> str:
    """The device as recording.toml names it, after checking the text given for the metadata.

    Checked before a frame is read: the metadata is written last, after every frame, and failing
    then lost them all. Command-line bytes that are not UTF-8 come in as lone surrogates: a
    ``--description`` of them is refused; a device path of them still records, named with U+FFFD.
    """
    try:
        args.description.encode("utf-8")
    except UnicodeEncodeError:
        raise ConfigError(
            "--description is not UTF-8 text", hint="write it in a UTF-8 terminal or locale"
        ) from None
    return str(args.device.encode("utf-8", "surrogateescape").decode("utf-8", "replace"))


# what each format keeps of a frame; said once when recording starts
FORMATS = {
    "depthnav": "depth, timestamps, intrinsics, accelerometer, odometry and description",
    "png": "depth (mm), timestamps and intrinsics (camera.toml); no accelerometer or odometry",
    "oni": "depth (mm), timestamps and the camera (fx, fy in the file as a field of view; a "
    "principal point off the centre or a lens in NAME.camera.toml beside it, which depthnav's "
    "replay reads); no accelerometer or odometry",
    "fakenect": "640x480 depth as 11-bit Kinect disparity (quantised) with the accelerometer; "
    "the camera, when not a Kinect v1's, in camera.toml beside INDEX.txt (depthnav's replay reads "
    "it; libfreenect's assumes a Kinect v1)",
}


def _check_out(args: argparse.Namespace) -> None:
    """Refuse a target that cannot be written, before the device is opened."""
    out, fmt = args.out, getattr(args, "format", "depthnav")
    if fmt == "oni":
        if out.suffix.lower() != ".oni":
            raise ConfigError(f"{out}: an .oni recording is a file named *.oni", hint="e.g. x.oni")
        # its camera.toml too (drivers.formats.oni.sidecar_path, not imported: numpy would load
        # before the stop handlers): an old one beside the new file would be read as its camera
        for target in (out, out.with_suffix(".camera.toml")):
            if target.exists() or target.is_symlink():
                raise ConfigError(
                    f"{target}: exists; refusing to overwrite", hint="choose a new name"
                )
    elif fmt != "depthnav" and out.exists() and (not out.is_dir() or any(out.iterdir())):
        # (write_recording checks its own target, before the first frame)
        raise ConfigError(
            f"{out}: exists and is not an empty folder; refusing to overwrite",
            hint="choose a new folder",
        )
    if fmt != "depthnav" and args.odometry:
        raise ConfigError(
            f"--odometry is stored by --format depthnav only, not {fmt}",
            hint="record with --format depthnav",
        )
    if args.odometry is not None:  # a bad spec is a usage error, as in run (a source that
        # cannot open is not: the recording is then made without it, said in one line)
        from drivers.odometry import create_odometry  # light: no I/O, no compiled stages

        if not args.odometry.strip():
            raise ConfigError("--odometry needs a spec", hint="e.g. odom+udp://127.0.0.1:5700")
        create_odometry(args.odometry)  # DeviceSpecError: exit 2


def _export(args: argparse.Namespace, frames: Iterator[Any], took: Callable[[int], None]) -> int:
    """Write ``frames`` in ``args.format`` (not depthnav's own), reporting each frame taken."""
    from drivers.errors import RecordingError
    from drivers.formats.fakenect import write_fakenect
    from drivers.formats.oni import write_oni
    from drivers.formats.png_folder import write_png_folder

    def counted() -> Iterator[Any]:
        for k, frame in enumerate(frames, 1):
            yield frame
            took(k)

    if args.format == "png":
        return write_png_folder(args.out, counted(), scale=1000.0)  # millimetres: lossless
    if args.format == "oni":
        return write_oni(args.out, counted())
    n = write_fakenect(args.out, counted())
    if n == 0:
        raise RecordingError(f"{args.out}: no frames to write")
    return n


def _checked(args: argparse.Namespace) -> tuple[str, str]:
    """(format, device text), after checking the arguments before the device is opened."""
    if args.frames < 1:
        raise ConfigError(f"--frames={args.frames} is out of range (accepted: 1 or more)")
    fmt = getattr(args, "format", "depthnav")
    _check_out(args)
    device_text = _device_text(args)
    log.info("recording %s as %s: %s", args.out, fmt, FORMATS[fmt])
    return fmt, device_text


def cmd_record(args: argparse.Namespace) -> int:
    fmt, device_text = _checked(args)
    stop = threading.Event()
    got = install_stop_handlers(stop)  # before the heavy imports: see install_stop_handlers
    from drivers import create_driver, iter_frames, opened
    from drivers.errors import RecordingError
    from drivers.formats.recording_writer import write_recording

    driver = create_driver(args.device)
    odometry = _start_odometry(args.odometry, stop) if args.odometry else None
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
            yield frame if odometry is None else _with_odometry(frame, odometry)
        driver.close()  # the device is not needed while the frames are compressed
        for sig in STOP_SIGNALS:
            signal.signal(sig, while_compressing)

    try:
        with opened(driver):
            if fmt == "depthnav":
                n = write_recording(
                    args.out,
                    frames(),
                    description=args.description,
                    device=device_text,
                    progress=took,
                    progress_compress=compressed,
                )
            else:
                n = _export(args, frames(), took)
    except RecordingError:
        if "signal" not in got or taken[0]:
            raise
        # a stop before the first frame is a clean stop, not a failed recording
        log.warning("stopped before the first frame: nothing was recorded into %s", args.out)
        return stopped_code(got)
    finally:
        if odometry is not None:
            odometry.stop()
    return _reported(args, n, got)


def _reported(args: argparse.Namespace, n: int, got: dict[str, Any]) -> int:
    """Say how many frames were recorded; the exit code."""
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


ODOMETRY_WAIT_S = 2.0  # for the source's first sample before the first frame
ODOMETRY_MAX_AGE_S = 0.5  # a frame whose newest odometry is older gets none


def _start_odometry(spec: str, stop: threading.Event):
    """The started odometry source, once it has spoken; None (said in one line) when it cannot
    start or says nothing within ODOMETRY_WAIT_S: the recording is then made without it."""
    from drivers.errors import DriverError
    from drivers.odometry import create_odometry

    try:
        source = create_odometry(spec)
        source.start()
    except DriverError as exc:
        log.warning("odometry %s cannot start: %s; recording without it", spec, exc)
        return None
    log.info("waiting for odometry from %s", spec)
    if stop.wait(0) or not _spoke(source, stop):
        log.warning(
            "odometry %s has sent nothing in %g s; recording without it", spec, ODOMETRY_WAIT_S
        )
        source.stop()
        return None
    return source


def _spoke(source, stop: threading.Event) -> bool:
    for _ in range(int(ODOMETRY_WAIT_S / 0.05)):
        if source.buffer.count:
            return True
        if stop.wait(0.05):
            return False
    return bool(source.buffer.count)


def _with_odometry(frame, source):
    """The frame with the odometry pose at its arrival (or its timestamp, for a source that sends
    the frames' clock); without one when the newest is older than ODOMETRY_MAX_AGE_S (the writer
    then stores no odometry, and says so)."""
    import dataclasses
    import time

    t = time.monotonic() if source.uses_arrival_clock else frame.timestamp_s
    at = source.buffer.pose_at(t)
    if at is None or at[1] > ODOMETRY_MAX_AGE_S:
        return frame
    return dataclasses.replace(frame, odom=tuple(float(v) for v in at[0]))
