"""Bad input at every entry point, fuzzed with hypothesis: one clean error, never anything else.

Every reader and loader gets mutated and random input. It must either accept it (with a defined
result) or raise its own error type whose message is one line naming the input; any other
exception (a traceback for the user), a hang (pytest-timeout) or a native crash fails the test.
Case counts are ``max_examples`` per test; docs/hardening.md lists them.
"""

from __future__ import annotations

import io
import math
import os
import re
import shutil
import string
import tempfile
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import tomli_w
import yaml
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from PIL import Image

from depthnav_daemon.config.loader import build_config, parse_set, valid_keys
from depthnav_daemon.config.ros_params import load_ros_params
from depthnav_daemon.errors import ConfigError
from depthnav_daemon.sinks import create_sink
from drivers import create_driver
from drivers.base import Frame, Intrinsics
from drivers.errors import DriverError, RecordingError
from drivers.formats.fakenect import ACCEL_DUMP, write_fakenect
from drivers.formats.oni import check_oni, write_oni
from drivers.formats.recording_writer import write_recording
from drivers.kinect.driver import check_fakenect_recording
from drivers.limits import image_size_problem, max_image_pixels
from drivers.replay import CACHE_MAX_BYTES, ReplayDriver
from drivers.tilt.serialtilt import SerialTiltSource, parse_line

from . import hostile

BASE = settings(
    deadline=None, suppress_health_check=list(HealthCheck), derandomize=True, database=None
)


LONG = os.environ.get("DEPTHNAV_SOAK") == "1"  # --soak (tests/faults/conftest.py) or the env
LONG_FACTOR = 5


def fuzz(cases: int) -> settings:
    """Deterministic (derandomized) hypothesis settings: ``cases`` examples, 5x with --soak."""
    return settings(BASE, max_examples=cases * LONG_FACTOR if LONG else cases)


# a depthnav recording replays decoded in memory up to the cache's cap and streamed above it
REPLAY_PATHS = pytest.mark.parametrize("cap", [CACHE_MAX_BYTES, 0], ids=["cached", "streamed"])


SMALL = Intrinsics(64, 48, 61.5, 57.25, 30.25, 22.75)  # asymmetric on purpose
MAX_FRAMES = 50  # a fuzzed recording is read to its end, or this many frames


def one_line(exc: BaseException, *names: str) -> str:
    """The error's message: one non-empty line that names one of ``names`` (the input)."""
    msg = str(exc)
    assert msg and "\n" not in msg and "\r" not in msg, repr(msg)
    if names:
        assert any(n in msg for n in names), f"{msg!r} names none of {names}"
    return msg


def clean(
    call: Callable[[], object], errors: tuple[type[BaseException], ...], *names: str
) -> object:
    """Run ``call``; it returns, or raises one of ``errors`` with a one-line message naming the
    input."""
    try:
        return call()
    except errors as exc:
        one_line(exc, *names)
        return None


def frames(n: int = 3, intr: Intrinsics = SMALL) -> list[Frame]:
    rng = np.random.default_rng(3)
    return [
        Frame(
            i,
            i / 30,
            rng.integers(300, 6000, (intr.height, intr.width), dtype=np.uint16),
            intr,
            (0.0, -9.5, -2.5),
        )
        for i in range(n)
    ]


def mutate(data: bytes, edits: list[tuple[int, int]], cut: int | None) -> bytes:
    """``data`` with bytes replaced at (position, value) pairs, then cut to ``cut`` bytes."""
    buf = bytearray(data)
    for pos, value in edits:
        if buf:
            buf[pos % len(buf)] = value
    return bytes(buf[:cut] if cut is not None else buf)


EDITS = st.lists(st.tuples(st.integers(0, 1 << 24), st.integers(0, 255)), max_size=12)
CUTS = st.one_of(st.none(), st.integers(0, 4000))


def replay_all(spec: str, *names: str) -> None:
    """Open a replay spec and read it to the end: clean or one DriverError line."""

    def go() -> None:
        driver = create_driver(spec)
        try:
            driver.open()
            for _ in range(MAX_FRAMES):
                if driver.read_frame(0.5) is None:
                    break
        finally:
            driver.close()

    clean(go, (DriverError,), *names)
    assert ReplayDriver.open_count == 0


# --- recordings -------------------------------------------------------------------------------
def _npz_bytes() -> bytes:
    with tempfile.TemporaryDirectory() as d:
        write_recording(Path(d) / "r", frames())
        return (Path(d) / "r" / "frames.npz").read_bytes()


NPZ = _npz_bytes()


@REPLAY_PATHS
@fuzz(200)
@given(edits=EDITS, cut=CUTS)
def test_fuzz_npz_bytes(
    tmp_path_factory: pytest.TempPathFactory, monkeypatch: pytest.MonkeyPatch, cap, edits, cut
) -> None:
    monkeypatch.setattr("drivers.replay.CACHE_MAX_BYTES", cap)
    path = tmp_path_factory.mktemp("npz") / "x.npz"
    path.write_bytes(mutate(NPZ, edits, cut))
    replay_all(f"replay:{path}?rate=max", str(path))


ARRAYS = st.dictionaries(
    st.sampled_from(["depth_mm", "intrinsics", "timestamp_s", "accel_mps2", "other"]),
    st.tuples(
        st.sampled_from(["u2", "i2", "f4", "f8", "u1", "i8", "b1", "U3"]),
        st.lists(st.integers(0, 5), min_size=0, max_size=4),
        st.sampled_from([0.0, -1.0, 65535.0, math.nan, math.inf, -math.inf, 1e30, 7.0]),
    ),
    max_size=5,
)


@REPLAY_PATHS
@fuzz(200)
@given(arrays=ARRAYS)
def test_fuzz_npz_arrays(
    tmp_path_factory: pytest.TempPathFactory, monkeypatch: pytest.MonkeyPatch, cap, arrays
) -> None:
    """Wrong dtypes, shapes and values (NaN, inf, negative, saturated) in every array."""
    monkeypatch.setattr("drivers.replay.CACHE_MAX_BYTES", cap)
    path = tmp_path_factory.mktemp("npz") / "x.npz"
    made = {}
    for name, (dtype, shape, fill) in arrays.items():
        with np.errstate(invalid="ignore", over="ignore"):
            made[name] = (
                np.full(shape, fill).astype(dtype) if dtype != "U3" else np.full(shape, "ab")
            )
    np.savez(path, **made)
    replay_all(f"replay:{path}?rate=max", str(path))


META_VALUES = st.one_of(
    st.integers(-5, 5000),
    st.floats(allow_nan=True, allow_infinity=True),
    st.text(max_size=5),
    st.booleans(),
    st.lists(st.integers(), max_size=3),
)


@fuzz(200)
@given(
    text=st.one_of(
        st.text(max_size=200),
        st.dictionaries(
            st.sampled_from(["format_version", "description", "device", "intrinsics", "truth"]),
            st.one_of(
                META_VALUES,
                st.dictionaries(
                    st.sampled_from(["width", "height", "fx", "fy", "cx", "cy"]),
                    META_VALUES,
                    max_size=6,
                ),
            ),
            max_size=5,
        ),
    )
)
def test_fuzz_recording_toml(tmp_path_factory: pytest.TempPathFactory, text) -> None:
    folder = tmp_path_factory.mktemp("rec")
    (folder / "frames.npz").write_bytes(NPZ)
    if isinstance(text, dict):
        try:
            text = tomli_w.dumps(text)
        except (TypeError, ValueError):  # NaN, inf or mixed lists: a TOML writer refuses them
            text = "format_version = nan\n"
    (folder / "recording.toml").write_text(text, encoding="utf-8", errors="surrogatepass")
    replay_all(f"replay:{folder}?rate=max", str(folder))


def _png(depth: np.ndarray) -> bytes:
    out = io.BytesIO()
    Image.fromarray(depth).save(out, format="PNG")
    return out.getvalue()


PNG = _png(frames(1)[0].depth_mm)


@fuzz(200)
@given(
    edits=EDITS,
    cut=CUTS,
    index=st.one_of(st.none(), st.text(max_size=80)),
    sidecar=st.one_of(
        st.none(),
        st.text(max_size=80),
        st.dictionaries(
            st.sampled_from(["depth_scale", "intrinsics"]),
            st.one_of(
                META_VALUES,
                st.dictionaries(st.sampled_from(["fx", "fy", "cx", "cy"]), META_VALUES, max_size=4),
            ),
            max_size=2,
        ),
    ),
)
def test_fuzz_png_folder(
    tmp_path_factory: pytest.TempPathFactory, edits, cut, index, sidecar
) -> None:
    """Corrupt PNGs, a random depth.txt and a random camera.toml sidecar."""
    folder = tmp_path_factory.mktemp("png")
    (folder / "000.png").write_bytes(PNG)
    (folder / "001.png").write_bytes(mutate(PNG, edits, cut))
    if index is not None:
        (folder / "depth.txt").write_text(index, encoding="utf-8", errors="surrogatepass")
    if isinstance(sidecar, dict):
        try:
            sidecar = tomli_w.dumps(sidecar)
        except (TypeError, ValueError):
            sidecar = "depth_scale = inf\n"
    if sidecar is not None:
        (folder / "camera.toml").write_text(sidecar, encoding="utf-8", errors="surrogatepass")
    replay_all(f"replay:{folder}?rate=max&fx=60&fy=58&cx=31&cy=23", str(folder))


FAKENECT_DIR = Path(tempfile.mkdtemp(prefix="fuzz-fakenect-"))
write_fakenect(
    FAKENECT_DIR / "base",
    [
        Frame(
            i,
            i / 30,
            np.full((480, 640), 1500 + 100 * i, np.uint16),
            Intrinsics(640, 480, 580, 580, 319.5, 239.5),
            (0.0, -9.7, -1.4),
        )
        for i in range(2)
    ],
)
BASE_NAMES = (FAKENECT_DIR / "base" / "INDEX.txt").read_text().split()


@fuzz(150)
@given(
    lines=st.lists(
        st.one_of(st.sampled_from(BASE_NAMES), st.text(string.printable, max_size=30)), max_size=6
    ),
    pgm_edits=EDITS,
    pgm_cut=st.one_of(st.none(), st.integers(0, 614417)),
    dump=st.binary(max_size=20),
)
def test_fuzz_fakenect(
    tmp_path_factory: pytest.TempPathFactory, lines, pgm_edits, pgm_cut, dump
) -> None:
    """INDEX.txt lines, depth .pgm bytes and accelerometer dumps; the pure-Python reader and the
    guard that keeps bad files away from the native fakenect library."""
    folder = tmp_path_factory.mktemp("fk")
    for name in BASE_NAMES:
        data = (FAKENECT_DIR / "base" / name).read_bytes()
        if name.startswith("d-") and name == BASE_NAMES[0]:
            data = mutate(data, pgm_edits, pgm_cut)
        if name.startswith("a-"):
            data = dump if len(dump) != ACCEL_DUMP.size or dump else data
        (folder / name).write_bytes(data)
    (folder / "INDEX.txt").write_text("\n".join(lines) + "\n", encoding="ascii", errors="replace")
    replay_all(f"replay:{folder}?rate=max", str(folder))
    clean(lambda: check_fakenect_recording(folder), (RecordingError,), str(folder))


def _oni_bytes() -> bytes:
    with tempfile.TemporaryDirectory() as d:
        write_oni(Path(d) / "x.oni", frames(2))
        return (Path(d) / "x.oni").read_bytes()


ONI = _oni_bytes()


@fuzz(300)
@given(edits=EDITS, cut=st.one_of(st.none(), st.integers(0, len(ONI))))
def test_fuzz_oni_structure(tmp_path_factory: pytest.TempPathFactory, edits, cut) -> None:
    """The .oni checker that runs before libOniFile: headers, record headers, truncation.

    (Mutated files that pass it are played by the real libOniFile in test_native_fuzz.py.)
    """
    path = tmp_path_factory.mktemp("oni") / "x.oni"
    path.write_bytes(mutate(ONI, edits, cut))
    clean(lambda: check_oni(path), (RecordingError,), str(path))


# --- configuration ----------------------------------------------------------------------------
CONFIG_KEYS = ["device", "sinks", "mount", "scan", "cliff", "pose", "daemon", "bogus"]
SECTION_KEYS = [
    "height_m",
    "tilt_deg",
    "roll_deg",
    "range_min_m",
    "range_max_m",
    "row_start",
    "row_stop",
    "block_size",
    "method",
    "pose_every_frames",
    "reconnect_backoff_s",
    "tilt_source",
    "serial_tilt",
    "seed",
    "used_depth_height",
    "nonsense",
]
CONFIG_VALUES = st.one_of(
    st.integers(-(2**70), 2**70),
    st.floats(),
    st.text(max_size=8),
    st.booleans(),
    st.lists(st.text(max_size=5), max_size=3),
)


@fuzz(250)
@given(
    doc=st.one_of(
        st.text(max_size=300),
        st.dictionaries(
            st.sampled_from(CONFIG_KEYS),
            st.one_of(
                CONFIG_VALUES,
                st.dictionaries(st.sampled_from(SECTION_KEYS), CONFIG_VALUES, max_size=4),
            ),
            max_size=5,
        ),
    ),
    sets=st.lists(st.text(max_size=30), max_size=3),
)
def test_fuzz_config_files_and_set(tmp_path_factory: pytest.TempPathFactory, doc, sets) -> None:
    path = tmp_path_factory.mktemp("cfg") / "robot.toml"
    if isinstance(doc, dict):
        try:
            doc = tomli_w.dumps(doc)
        except (TypeError, ValueError):
            doc = "[mount]\nheight_m = nan\n"
    path.write_text(doc, encoding="utf-8", errors="surrogatepass")
    clean(lambda: build_config([path], sets), (ConfigError,))
    for item in sets:
        clean(lambda item=item: parse_set(item), (ConfigError,))


ROS_KEYS = [
    "range_min",
    "range_max",
    "sensor_mount_height",
    "sensor_tilt_angle",
    "scan_height",
    "block_size",
    "used_depth_height",
    "depth_img_step_row",
    "ransac_max_iter",
    "ground_remove_en",
    "tilt_angle_max",
    "mount_height_min",
    "output_frame_id",
    "weird",
]
ROS_VALUES = st.one_of(
    st.integers(-(2**40), 2**40),
    st.floats(),
    st.text(max_size=6),
    st.booleans(),
    st.none(),
    st.lists(st.integers(), max_size=2),
)


@fuzz(250)
@given(
    doc=st.one_of(
        st.text(max_size=200),
        st.dictionaries(st.sampled_from(ROS_KEYS), ROS_VALUES, max_size=6),
        st.dictionaries(
            st.sampled_from(
                ["laserscan_kinect", "/cliff_detector", "depth_sensor_pose", "/**", "x"]
            ),
            st.one_of(
                ROS_VALUES,
                st.fixed_dictionaries(
                    {
                        "ros__parameters": st.one_of(
                            ROS_VALUES,
                            st.dictionaries(st.sampled_from(ROS_KEYS), ROS_VALUES, max_size=5),
                        )
                    }
                ),
            ),
            max_size=3,
        ),
    )
)
def test_fuzz_ros_parameter_files(tmp_path_factory: pytest.TempPathFactory, doc) -> None:
    path = tmp_path_factory.mktemp("ros") / "params.yaml"
    text = doc if isinstance(doc, str) else yaml.safe_dump(doc)
    path.write_text(text, encoding="utf-8", errors="surrogatepass")
    clean(lambda: load_ros_params(path), (ConfigError,), str(path))
    clean(lambda: build_config([path]), (ConfigError,))


# --- specs ------------------------------------------------------------------------------------
SPEC_TEXT = st.text(
    st.sampled_from(list(string.ascii_letters + string.digits + ":/?&=%.-+_[] \n\t\x00é")),
    max_size=40,
)
DEVICE_PREFIX = st.sampled_from(
    [
        "",
        "kinect",
        "kinect://",
        "openni://",
        "openni:",
        "replay:",
        "xtion",
        "replay:fixtures/corridor_step?",
        "kinect?",
        "openni://Dummy?",
    ]
)
SINK_PREFIX = st.sampled_from(
    [
        "",
        "stdout",
        "text?",
        "udp://",
        "udp:",
        "null",
        "rerun",
        "rerun:",
        "rerun+grpc://",
        "mavlink:",
        "mavlink+udp://",
        "udp://127.0.0.1:",
    ]
)


@fuzz(400)
@given(prefix=DEVICE_PREFIX, rest=SPEC_TEXT)
def test_fuzz_device_specs(prefix: str, rest: str) -> None:
    """Building a driver from a spec does no I/O and fails with one DriverError line."""
    clean(lambda: create_driver(prefix + rest), (DriverError,))


@fuzz(400)
@given(prefix=SINK_PREFIX, rest=SPEC_TEXT)
def test_fuzz_sink_specs(prefix: str, rest: str) -> None:
    clean(lambda: create_sink(prefix + rest), (ConfigError,))


@fuzz(200)
@given(rest=SPEC_TEXT)
def test_fuzz_serial_tilt_specs(rest: str) -> None:
    clean(lambda: SerialTiltSource.from_spec("serialtilt:" + rest), (DriverError,))


# --- the serial line protocol and MAVLink input -----------------------------------------------
LINE_BYTES = st.one_of(
    st.binary(max_size=80),
    st.builds(
        lambda t, r, ck: f"$TILT,{t},{r}*{ck}".encode(),
        st.one_of(st.floats(), st.text("0123456789.-+e", max_size=8)),
        st.one_of(st.floats(), st.text("0123456789.-+e", max_size=8)),
        st.text("0123456789ABCDEFabcdefXYZ", min_size=0, max_size=3),
    ),
)


@fuzz(600)
@given(
    chunks=st.lists(LINE_BYTES, max_size=8), newline=st.sampled_from([b"\n", b"\r\n", b"", b"\r"])
)
def test_fuzz_serial_line_protocol(chunks: list[bytes], newline: bytes) -> None:
    """Noise, split and malformed ``$TILT`` lines: never raises, only plausible readings
    published."""
    src = SerialTiltSource("loop://")
    feed = src._line_feeder()
    for chunk in chunks:
        feed(chunk + newline)
        parsed = parse_line(chunk)
        if parsed is not None:
            assert abs(parsed[0]) <= 90 and abs(parsed[1]) <= 180
    reading = src.latest()
    if reading is not None:
        assert math.isfinite(reading.tilt_deg) and abs(reading.tilt_deg) <= 90
        assert math.isfinite(reading.roll_deg) and abs(reading.roll_deg) <= 180


@fuzz(400)
@given(
    pitch=st.floats(width=32),
    roll=st.floats(width=32),
    noise=st.binary(max_size=60),
    edits=EDITS,
    split=st.integers(0, 80),
)
def test_fuzz_mavlink_input(pitch: float, roll: float, noise: bytes, edits, split: int) -> None:
    """ATTITUDE with any float (NaN, inf, huge), corrupted bytes and noise: never raises, and only
    an attitude within +-90 deg pitch, +-180 deg roll is published."""
    from pymavlink.dialects.v20 import common as mavlink2

    mav = mavlink2.MAVLink(None)
    msg = mav.attitude_encode(1000, roll, pitch, 0.0, 0.0, 0.0, 0.0).pack(mav)
    data = noise + mutate(msg, edits if edits and len(edits) % 2 else [], None) + msg
    src = SerialTiltSource("loop://", protocol="mavlink")
    feed = src._mavlink_feeder()
    feed(data[:split])
    feed(data[split:])
    reading = src.latest()
    if reading is not None:
        assert abs(reading.tilt_deg) <= 90.0 + 1e-3 and abs(reading.roll_deg) <= 180.0 + 1e-3


def test_mavlink_attitude_out_of_range_is_not_published() -> None:
    """Before the fix, pitch = 10 rad was published as a tilt of -573 degrees."""
    from pymavlink.dialects.v20 import common as mavlink2

    mav = mavlink2.MAVLink(None)
    src = SerialTiltSource("loop://", protocol="mavlink")
    src._mavlink_feeder()(mav.attitude_encode(0, 0.0, 10.0, 0.0, 0.0, 0.0, 0.0).pack(mav))
    assert src.latest() is None and src.bad_messages == 1


# --- the command line itself ------------------------------------------------------------------
ARG_WORDS = st.sampled_from(
    [
        "run",
        "replay",
        "calibrate",
        "mount",
        "info",
        "devices",
        "frobnicate",
        "--device",
        "--sink",
        "--max-frames",
        "--set",
        "-c",
        "--height-m",
        "--tilt-deg",
        "--roll-deg",
        "--frames",
        "--vfov-deg",
        "--distances-m",
        "--sensor",
        "--rate",
        "--loop",
        "--method",
        "-v",
        "-q",
        "--json",
        "nan",
        "inf",
        "-1",
        "0",
        "1e309",
        "replay:/nonexistent",
        "stdout",
        "null",
        "udp://",
        "kinect?bogus=1",
        "mount.height_m=-1",
        "daemon.seed=x",
        "/nonexistent.toml",
        "exact",
        "",
        "=",
        "\x00",
    ]
)


@fuzz(200)
@given(argv=st.lists(st.one_of(ARG_WORDS, st.text(max_size=12)), max_size=7))
def test_fuzz_command_line(argv: list[str]) -> None:
    """Random argument lists through cli.main(): exit 0, 1, 2 or 130, never an internal error.

    In process (300 subprocesses would take minutes); logging and signal handlers are restored.
    """
    import contextlib
    import io
    import logging
    import signal

    from depthnav_daemon import cli

    if any(w in ("--write", "--plot", "record", "bench") for w in argv):
        return  # commands that write files or run long are covered in their own tests
    root = logging.getLogger()
    stops = (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)
    saved = (root.handlers[:], root.level, {s: signal.getsignal(s) for s in stops})
    err = io.StringIO()
    try:
        with contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()):
            try:
                code = cli.main(argv)
            except SystemExit as exc:  # argparse: --help, --version, usage errors
                code = exc.code if isinstance(exc.code, int) else 2
    finally:
        root.handlers[:], root.level = saved[0], saved[1]
        for sig, handler in saved[2].items():
            signal.signal(sig, handler)
        for name in ("depthnav_daemon", "drivers"):
            logging.getLogger(name).setLevel(logging.NOTSET)
    text = err.getvalue()
    assert code in (0, 1, 2, 130), (argv, code, text)
    assert "internal error" not in text and "Traceback" not in text, (argv, text)


# --- hostile inputs, generated for every reader (docs/hardening.md, "Hostile inputs") ----------
# Each reader registers how to make a valid input, the files it reads and which of them are
# text; every generator below then runs against every reader: special files and symlinks in
# place of each file, each text file in another encoding, every number in it replaced by a
# hostile one, deep nesting in each TOML/YAML file. A new reader added to READERS inherits them.
@dataclass(frozen=True)
class Reader:
    """An entry point that reads files.

    Attributes:
        name: for the test ids.
        make: writes a valid input into a folder; returns its root (what the user names).
        files: the files it reads, relative to the root ("" is the root itself; a glob picks
            the first match).
        text: those of ``files`` that are text.
        read: reads the whole input: returns, or raises its own error in one line.
    """

    name: str
    make: Callable[[Path], Path]
    files: tuple[str, ...]
    text: tuple[str, ...]
    read: Callable[[Path], None]


def _replay(root: Path) -> None:
    replay_all(f"replay:{root}?rate=max&fx=60&fy=58&cx=31&cy=23", str(root.parent))


def _replay_recording(root: Path) -> None:
    replay_all(f"replay:{root}?rate=max", str(root.parent))


def _make_recording(folder: Path) -> Path:
    write_recording(folder / "rec", frames())
    return folder / "rec"


def _make_npz(folder: Path) -> Path:
    (folder / "x.npz").write_bytes(NPZ)
    return folder / "x.npz"


def _make_png_folder(folder: Path) -> Path:
    root = folder / "png"
    root.mkdir()
    (root / "000.png").write_bytes(PNG)
    (root / "001.png").write_bytes(PNG)
    (root / "depth.txt").write_text("# t file\n0.0 000.png\n0.033 001.png\n")
    (root / "camera.toml").write_text(
        "depth_scale = 1000.0\n[intrinsics]\nfx = 60.0\nfy = 58.0\ncx = 31.0\ncy = 23.0\n"
    )
    return root


def _make_npy(folder: Path) -> Path:
    np.save(folder / "x.npy", np.stack([f.depth_mm for f in frames()]))
    return folder / "x.npy"


def _make_image_folder(folder: Path) -> Path:
    """TUM/slambook style without an index: colour beside 16-bit PGM depth, picked by header."""
    root = folder / "img"
    root.mkdir()
    for i, frame in enumerate(frames()[:2]):
        depth = frame.depth_mm
        head = f"P5\n{depth.shape[1]} {depth.shape[0]}\n65535\n".encode()
        (root / f"{i}_depth.pgm").write_bytes(head + depth.astype(">u2").tobytes())
        (root / f"{i}.ppm").write_bytes(f"P6 {depth.shape[1]} {depth.shape[0]} 255\n".encode())
    (root / "camera.toml").write_text("depth_scale = 1000.0\n")
    return root


def _make_fakenect(folder: Path) -> Path:
    shutil.copytree(FAKENECT_DIR / "base", folder / "fk")
    return folder / "fk"


def _make_oni(folder: Path) -> Path:
    (folder / "x.oni").write_bytes(ONI)
    return folder / "x.oni"


def _make_config(folder: Path) -> Path:
    (folder / "robot.toml").write_text(
        'device = "kinect"\n[mount]\nheight_m = 0.55\ntilt_deg = 15.0\n'
        "[scan]\nrange_max_m = 4.0\nrow_step = 2\n[daemon]\nseed = 7\npose_every_frames = 30\n"
    )
    return folder / "robot.toml"


def _make_ros_params(folder: Path) -> Path:
    (folder / "params.yaml").write_text(
        "laserscan_kinect:\n  ros__parameters:\n    range_min: 0.45\n    range_max: 4.0\n"
        "    scan_height: 3\n    sensor_mount_height: 0.4\n    sensor_tilt_angle: -10.0\n"
    )
    return folder / "params.yaml"


def _read_config(root: Path) -> None:
    # a value's error names its key (mount.height_m), not the file: values from several files
    # and --set are merged before they are checked
    clean(lambda: build_config([root]), (ConfigError,))


def _make_ros2_bag(folder: Path) -> Path:
    from tests.drivers.bagkit import BagSpec, write_bag
    from tests.drivers.driverkit import ramp_frames

    return write_bag(folder / "bag", ramp_frames(2), BagSpec("mcap"))


READERS = [
    Reader(
        "recording",
        _make_recording,
        ("", "recording.toml", "frames.npz"),
        ("recording.toml",),
        _replay_recording,
    ),
    Reader("bare npz", _make_npz, ("",), (), _replay_recording),
    Reader("bare npy", _make_npy, ("",), (), _replay),
    Reader(
        "image folder",
        _make_image_folder,
        ("", "camera.toml", "0_depth.pgm", "1_depth.pgm"),
        ("camera.toml",),
        _replay,
    ),
    Reader(
        "png folder",
        _make_png_folder,
        ("", "depth.txt", "camera.toml", "000.png", "001.png"),
        ("depth.txt", "camera.toml"),
        _replay,
    ),
    Reader(
        "fakenect",
        _make_fakenect,
        ("", "INDEX.txt", "d-*.pgm", "a-*.dump"),
        ("INDEX.txt",),
        _replay_recording,
    ),
    Reader(
        "fakenect guard",
        _make_fakenect,
        ("", "INDEX.txt", "d-*.pgm", "a-*.dump"),
        ("INDEX.txt",),
        lambda root: clean(
            lambda: check_fakenect_recording(root), (RecordingError,), str(root.parent)
        ),
    ),
    Reader(
        "oni",
        _make_oni,
        ("",),
        (),
        lambda root: clean(lambda: check_oni(root), (RecordingError,), str(root.parent)),
    ),
    Reader("config", _make_config, ("",), ("",), _read_config),
    Reader("ros params", _make_ros_params, ("",), ("",), _read_config),
    Reader("ros bag", lambda folder: _touch(folder / "x.bag"), ("",), (), _replay_recording),
    # a ROS 2 bag folder: its metadata.yaml (text) and its storage file, each in every role
    Reader(
        "ros 2 bag",
        _make_ros2_bag,
        ("", "metadata.yaml", "*.mcap"),
        ("metadata.yaml",),
        _replay_recording,
    ),
]

READER = st.sampled_from(READERS)


def _touch(path: Path) -> Path:
    path.write_bytes(b"")
    return path


def _role(root: Path, name: str) -> Path:
    if not name:
        return root
    return next(iter(sorted(root.glob(name))), root / name)


def _guarded(read: Callable[[Path], None], root: Path) -> None:
    """``read(root)`` under a watchdog (20 s, +4 GiB of address space): a reader that blocks on a
    FIFO or reads /dev/zero to the end fails its case, not the machine."""
    with hostile.Watchdog():
        read(root)


@fuzz(150)
@given(
    reader=READER,
    pick=st.integers(0, 10),
    kind=st.sampled_from([*hostile.SPECIAL_KINDS, "long name"]),
)
def test_fuzz_special_files_in_place_of_every_input(
    tmp_path_factory: pytest.TempPathFactory, reader: Reader, pick: int, kind: str
) -> None:
    """A FIFO, a folder, a symlink to /dev/zero or /dev/urandom, a dangling symlink, a symlink
    loop or a 300-byte name where each file of each reader belongs: one line, never a hang
    (before: open() blocked and SIGTERM was ignored) or a read to the end."""
    folder = tmp_path_factory.mktemp("special")
    root = reader.make(folder)
    if kind == "long name":
        root = root.with_name("n" * 300 + root.suffix)
    else:
        hostile.make_special(_role(root, reader.files[pick % len(reader.files)]), kind)
    with hostile.PeakMemory() as peak:
        _guarded(reader.read, root)
    assert peak.growth_mb is None or peak.growth_mb < 200, peak.growth_mb


TEXT_READERS = st.sampled_from([r for r in READERS if r.text])


@fuzz(120)
@given(
    reader=TEXT_READERS,
    pick=st.integers(0, 10),
    encoding=st.sampled_from(["utf-16", "utf-16-le", "utf-16-be", "utf-32", "latin-1", "cp1252"]),
    noise=st.one_of(st.none(), st.binary(min_size=1, max_size=8)),
    at=st.integers(0, 1 << 16),
)
def test_fuzz_text_that_is_not_utf8(
    tmp_path_factory: pytest.TempPathFactory,
    reader: Reader,
    pick: int,
    encoding: str,
    noise: bytes | None,
    at: int,
) -> None:
    """Every text file of every reader in another encoding (a non-ASCII character added so
    Latin-1 differs from UTF-8), or with random bytes inserted: one line (before: a
    UnicodeDecodeError traceback), or read as before when the bytes happen to be valid UTF-8."""
    root = reader.make(tmp_path_factory.mktemp("enc"))
    path = _role(root, reader.text[pick % len(reader.text)])
    text = path.read_text()
    if noise is None:
        data = ("# café\n" + text if not path.name.endswith(".txt") else text).encode(
            encoding, errors="replace"
        )
    else:
        raw = text.encode()
        data = raw[: at % (len(raw) + 1)] + noise + raw[at % (len(raw) + 1) :]
    path.write_bytes(data)
    _guarded(reader.read, root)


_NUMBER = re.compile(rb"(?<![\w.])[-+]?[0-9]+(?:\.[0-9]+)?(?:[eE][-+]?[0-9]+)?(?![\w])")
HOSTILE_NUMBER = st.one_of(
    st.sampled_from(hostile.HOSTILE_NUMBERS),
    st.sampled_from(hostile.NOT_ASCII_NUMBERS),
    st.integers(-(10**30), 10**30).map(str),
    st.floats().map(repr),
)


@fuzz(200)
@given(
    reader=TEXT_READERS, pick=st.integers(0, 10), which=st.integers(0, 100), number=HOSTILE_NUMBER
)
def test_fuzz_hostile_numbers_in_every_text_file(
    tmp_path_factory: pytest.TempPathFactory, reader: Reader, pick: int, which: int, number: str
) -> None:
    """Each number in each text file of each reader (TOML and YAML values, depth.txt timestamps,
    fakenect file names) replaced by a 400- or 5000-digit integer, 1e400, inf, nan, 5e-324,
    non-ASCII digits and random numbers: accepted as a number, or one line (before: OverflowError,
    ValueError over 4300 digits, OverflowError from int(inf): internal errors)."""
    root = reader.make(tmp_path_factory.mktemp("num"))
    path = _role(root, reader.text[pick % len(reader.text)])
    data = path.read_bytes()
    spots = list(_NUMBER.finditer(data))
    if spots:
        spot = spots[which % len(spots)]
        data = data[: spot.start()] + number.encode() + data[spot.end() :]
        path.write_bytes(data)
    _guarded(reader.read, root)


NUMERIC_OPTIONS = [
    (
        "replay:fixtures/corridor_step?",
        ("fps", "fx", "fy", "cx", "cy", "scale", "const_shift", "start"),
    ),
    ("kinect?", ("tilt_deg", "const_shift", "fx", "cy")),
    ("openni:x.oni?", ("fx", "cx")),
]
SINK_NUMERIC_OPTIONS = [
    ("text?", ("every",)),
    ("udp://127.0.0.1:5600?", ("max_bytes",)),
    ("mavlink:/dev/null?", ("baud", "rate", "stale", "sysid", "compid")),
    ("mavlink+udp://127.0.0.1:14550?", ("rate", "sysid")),
    ("rerun:x.rrd?", ("every",)),
    ("udp://127.0.0.1:", ("",)),
    ("udp://[::1]:", ("",)),
]


@fuzz(200)
@given(
    device=st.sampled_from(NUMERIC_OPTIONS),
    sink=st.sampled_from(SINK_NUMERIC_OPTIONS),
    key=st.sampled_from(valid_keys()),
    pick=st.integers(0, 10),
    number=HOSTILE_NUMBER,
)
def test_fuzz_hostile_numbers_in_specs_and_set(device, sink, key, pick, number: str) -> None:
    """The same numbers in every numeric spec option of the drivers and sinks, in sink ports, and
    in ``--set`` for every config key: a value, or one line."""
    prefix, options = device
    option = options[pick % len(options)]
    clean(lambda: create_driver(f"{prefix}{option}={number}"), (DriverError,))
    prefix, options = sink
    option = options[pick % len(options)]
    clean(lambda: create_sink(f"{prefix}{option}{'=' if option else ''}{number}"), (ConfigError,))
    clean(lambda: build_config([], [f"{key}={number}"]), (ConfigError,))


NESTING = st.tuples(st.integers(1, 4000), st.sampled_from(["[", "{"]))


@fuzz(80)
@given(reader=TEXT_READERS, pick=st.integers(0, 10), nesting=NESTING)
def test_fuzz_deep_nesting_in_every_toml_and_yaml(
    tmp_path_factory: pytest.TempPathFactory, reader: Reader, pick: int, nesting
) -> None:
    """A value nested up to 4000 deep added to each TOML/YAML file (and to ``--set``): one line
    (before: RecursionError), never a crash."""
    depth, kind = nesting
    root = reader.make(tmp_path_factory.mktemp("deep"))
    path = _role(root, reader.text[pick % len(reader.text)])
    if path.suffix in (".toml", ".yaml"):
        value = hostile.nested(depth, kind)
        if path.suffix == ".yaml":
            value = value.replace(" = ", ": ")
            line = f"zz_nested: {value}\n"
        else:
            line = f"zz_nested = {value}\n"
        path.write_text(line + path.read_text())  # before the first table: a top-level key
    _guarded(reader.read, root)
    clean(
        lambda: build_config([], [f"scan.range_max_m={hostile.nested(depth, kind)}"]),
        (ConfigError,),
    )


@fuzz(60)
@given(levels=st.integers(2, 12), width=st.integers(2, 12), scalar_alias=st.booleans())
def test_fuzz_hostile_yaml(
    tmp_path_factory: pytest.TempPathFactory, levels, width, scalar_alias
) -> None:
    """Billion-laughs documents of any depth and width (and harmless aliases of single values):
    one line, bounded memory and time (before: 8.4 GB and 160 s for 9 levels of 9)."""
    path = tmp_path_factory.mktemp("yaml") / "params.yaml"
    text = hostile.billion_laughs(levels, width)
    if scalar_alias:
        text = "scan_height: &h 3\nblock_size: *h\n" + text
    path.write_text(text)
    with hostile.PeakMemory() as peak:
        with hostile.Watchdog():
            clean(lambda: build_config([path]), (ConfigError,), str(path))
    assert peak.growth_mb is None or peak.growth_mb < 100, peak.growth_mb


NPZ_NAMES = [
    "depth_mm.npy",
    "depth_mm",
    "timestamp_s.npy",
    "intrinsics.npy",
    "accel_mps2.npy",
    "other.npy",
]
MEMBER = st.one_of(
    st.just("valid"),
    st.tuples(
        st.sampled_from(["bomb", "lie"]),
        st.sampled_from(["<u2", "<f8", ">u2", "<i4", "|b1", "<c16", "|O"]),
        st.lists(st.integers(0, 40000), min_size=1, max_size=3),
    ),
)


def _member(name: str, spec: Any) -> hostile.Deflated:
    valid = hostile.valid_arrays()
    if spec == "valid":
        key = "depth_mm.npy" if name.startswith("depth_mm") else name.removesuffix(".npy")
        return hostile.deflate(hostile.npy_bytes(valid.get(key, np.zeros(3))))
    kind, dtype, shape = spec
    shape = tuple(shape)
    elements = int(np.prod(shape, dtype=object))
    if kind == "bomb" and dtype != "|O" and elements * np.dtype(dtype).itemsize <= 300 << 20:
        return hostile.bomb(dtype, shape)  # header and zeros agree: up to 300 MB decoded
    header = hostile.npy_header(dtype if dtype != "|O" else "<u2", shape)  # claims, holds little
    return hostile.deflate(header + bytes(64))


@REPLAY_PATHS
@fuzz(120)
@given(members=st.lists(st.tuples(st.sampled_from(NPZ_NAMES), MEMBER), min_size=1, max_size=6))
def test_fuzz_npz_members_bombs_and_duplicates(
    tmp_path_factory: pytest.TempPathFactory, monkeypatch: pytest.MonkeyPatch, cap, members
) -> None:
    """Archives built member by member: names repeated (depth_mm.npy beside depth_mm), zip bombs
    of up to 300 MB in any member, headers that claim up to 40000^3 elements of any dtype over a
    few bytes: one line, and the process's peak memory grows by less than 200 MB per case
    (before: every member decoded in full before its shape was checked, 2.4 GB from 2.8 MB)."""
    monkeypatch.setattr("drivers.replay.CACHE_MAX_BYTES", cap)
    path = tmp_path_factory.mktemp("npz") / "x.npz"
    hostile.write_zip(path, [(name, _member(name, spec)) for name, spec in members])
    with hostile.PeakMemory() as peak:
        _guarded(lambda p: replay_all(f"replay:{p}?rate=max", str(p)), path)
    assert peak.growth_mb is None or peak.growth_mb < 200, peak.growth_mb


@fuzz(80)
@given(
    width=st.integers(1, 40000),
    height=st.integers(1, 40000),
    tail=st.one_of(st.none(), st.binary(max_size=64)),
)
def test_fuzz_huge_frames(tmp_path_factory: pytest.TempPathFactory, width, height, tail) -> None:
    """PNGs claiming any size up to 40000x40000 (a real image of zeros when it is small, a bare
    header with garbage otherwise) and .npz depth claiming the same: refused from the header
    when too big (drivers.limits), one line, peak memory bounded (before: Pillow's
    DecompressionBombError at 20000x20000, 3.2 GB before refusing 12000x12000)."""
    folder = tmp_path_factory.mktemp("huge") / "png"
    folder.mkdir()
    if tail is None and width * height <= 4_000_000:
        hostile.png_of_zeros(folder / "000.png", width, height)
    else:
        hostile.png_header_only(folder / "000.png", width, height, tail or b"")
    npz = folder.parent / "x.npz"
    hostile.npz(npz, {"depth_mm.npy": hostile.Deflated(*_claim((1, height, width)))})
    with hostile.PeakMemory() as peak:
        _guarded(_replay, folder)
        _guarded(_replay_recording, npz)
    assert peak.growth_mb is None or peak.growth_mb < 300, peak.growth_mb
    problem = image_size_problem(width, height)
    assert (problem is None) == (
        max(width, height) <= 8192 and width * height <= max_image_pixels()
    )


def _claim(shape: tuple[int, ...]) -> tuple[bytes, int, int]:
    d = hostile.deflate(hostile.npy_header("<u2", shape) + bytes(16))
    return d.data, d.crc, d.size


def test_image_size_limit_follows_memory() -> None:
    """The largest image is set from memory: the tables take ~200 B a pixel, and may use half."""
    assert image_size_problem(640, 480, memory=1 << 30) is None  # a Kinect on a 1 GB board
    too_big = image_size_problem(4096, 4096, memory=4 << 30)  # 16.8 M pixels, 3.4 GB of tables
    assert too_big is not None and "4096x4096" in too_big and "allow 10737418 pixels" in too_big
    assert max_image_pixels(1 << 50) == 8192 * 8192  # never beyond 8192 each way
