"""The second fault campaign's classes (docs/hardening.md, "Hostile inputs"), one test each.

Each bad input ends in one ``error:`` line with the documented exit code; where the failure was
memory, the child's peak (VmHWM) is compared with a clean run's; where it was a hang, the case
simply has to end (a FIFO is refused before anything blocks on it). Most cases run the CLI in
this process (``kit.run_cli``: the same ``cli.main``, without a second of imports per case); the
memory cases run it in a child.
"""

from __future__ import annotations

import shutil
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest

from drivers.formats.fakenect import write_fakenect
from drivers.formats.recording import read_recording
from drivers.formats.recording_writer import write_recording

from . import hostile
from .kit import FIXTURE, depthnav_measured, one_error_line, run_cli

FAST = f"replay:{FIXTURE}?rate=max"
MARGIN_MB = 64  # a bomb here decodes to 512 MiB: decoding one shows as 8 margins and more


# --- memory: bombs, duplicate members, endless devices, hostile YAML, huge frames --------------
@pytest.fixture(scope="module")
def baseline_mb(tmp_path_factory: pytest.TempPathFactory) -> float:
    """Peak memory of ``depthnav replay`` of a small valid .npz to its end (imports, tables)."""
    path = hostile.npz(tmp_path_factory.mktemp("base") / "ok.npz", hostile.valid_arrays())
    run = depthnav_measured("replay", str(path), "--sink", "null")
    assert run.returncode == 0, run.stderr
    return run.peak_mb


def _bomb_npz(folder: Path, name: str, member: hostile.Deflated) -> Path:
    """A valid small .npz with array ``name`` replaced by (or, for a new name such as the bare
    ``depth_mm``, added as) ``member``."""
    arrays: list = [(k, v) for k, v in hostile.valid_arrays().items() if k != name]
    arrays.append((name, member))
    return hostile.npz(folder / "x.npz", arrays)


def _dev_zero_recording(folder: Path, role: str, device: str = "/dev/zero") -> Path:
    rec = folder / "rec"
    shutil.copytree(FIXTURE, rec)
    (rec / role).unlink()
    (rec / role).symlink_to(device)
    return rec


def _fakenect_dev_zero(folder: Path) -> Path:
    fk = folder / "fk"
    write_fakenect(fk, read_recording(FIXTURE).frames()[:1])
    (fk / "INDEX.txt").unlink()
    (fk / "INDEX.txt").symlink_to("/dev/urandom")
    return fk


MiB512_F8 = (64 << 20,)  # float64 elements in 512 MiB

MEMORY_CASES: dict[str, tuple[Callable[[Path], list[str]], int, str]] = {
    # name: (argv from a temp folder, exit code, what the one line says)
    "bomb in timestamp_s": (
        lambda d: [
            "replay",
            str(_bomb_npz(d, "timestamp_s", hostile.bomb("<f8", MiB512_F8))),
        ],
        1,
        "'timestamp_s' must be 3 numbers, got float64 (67108864,)",
    ),
    "bomb in intrinsics": (
        lambda d: ["replay", str(_bomb_npz(d, "intrinsics", hostile.bomb("<f8", MiB512_F8)))],
        1,
        "'intrinsics' must be 4 numbers",
    ),
    "bomb in accel_mps2": (
        lambda d: ["replay", str(_bomb_npz(d, "accel_mps2", hostile.bomb("<f8", (22369621, 3))))],
        1,
        "'accel_mps2' must be (3, 3) numbers",
    ),
    "bomb in an unused member": (
        lambda d: ["replay", str(_bomb_npz(d, "other", hostile.bomb("<f8", MiB512_F8)))],
        0,
        "",
    ),
    "duplicate depth member": (
        lambda d: ["replay", str(_bomb_npz(d, "depth_mm", hostile.bomb("<u2", (4096, 256, 256))))],
        1,
        "holds 'depth_mm' twice (depth_mm.npy and depth_mm)",
    ),
    "recording.toml -> /dev/zero": (
        lambda d: ["replay", str(_dev_zero_recording(d, "recording.toml"))],
        1,
        "recording.toml: is a character device (through a symlink), not a regular file",
    ),
    "frames.npz -> /dev/urandom": (
        lambda d: ["replay", str(_dev_zero_recording(d, "frames.npz", "/dev/urandom"))],
        1,
        "frames.npz: is a character device (through a symlink), not a regular file",
    ),
    "fakenect INDEX.txt -> /dev/urandom": (
        lambda d: ["replay", str(_fakenect_dev_zero(d))],
        1,
        "INDEX.txt: is a character device (through a symlink), not a regular file",
    ),
    "billion laughs as a config": (
        lambda d: [
            "run",
            "--device",
            FAST,
            "-c",
            str(_write(d / "p.yaml", hostile.billion_laughs(9, 9))),
        ],
        2,
        "not accepted as YAML: alias *l0 repeats a list or mapping",
    ),
    "PNG of 12000x12000": (
        lambda d: ["replay", str(_png_folder(d, 12000, 12000)), "--sink", "null"],
        1,
        "a 12000x12000 image is outside 1..8192 pixels each way",
    ),
    "PNG header claiming 20000x20000": (
        lambda d: ["replay", str(_png_folder(d, 20000, 20000, header_only=True))],
        1,
        "a 20000x20000 image is outside 1..8192 pixels each way",
    ),
}


def _write(path: Path, text: str) -> Path:
    path.write_text(text)
    return path


def _png_folder(folder: Path, width: int, height: int, header_only: bool = False) -> Path:
    out = folder / "png"
    out.mkdir()
    if header_only:
        hostile.png_header_only(out / "000.png", width, height, b"\0" * 64)
    else:
        hostile.png_of_zeros(out / "000.png", width, height)
    (out / "camera.toml").write_text(
        "depth_scale = 1000\n[intrinsics]\nfx = 500.0\nfy = 500.0\ncx = 10.0\ncy = 10.0\n"
    )
    return out


@pytest.mark.parametrize("case", list(MEMORY_CASES))
def test_memory_stays_bounded(tmp_path: Path, baseline_mb: float, case: str) -> None:
    """Before: 2.4 GB (bombs), 4.7 GB (duplicate member), read to the end (/dev/zero), 8.4 GB
    and 160 s (billion laughs), 3.2 GB (12000x12000 PNG), DecompressionBombError (20000x20000)."""
    make, code, says = MEMORY_CASES[case]
    run = depthnav_measured(*make(tmp_path), "--sink", "null")
    assert run.returncode == code, run.stderr
    if code:
        assert says in one_error_line(run.stderr)
    else:
        assert "Traceback" not in run.stderr
    assert run.peak_mb < baseline_mb + MARGIN_MB, (run.peak_mb, baseline_mb)


# --- one line, the right exit code ------------------------------------------------------------
def _recording_with(folder: Path, name: str, text: str | bytes) -> Path:
    rec = folder / "rec"
    shutil.copytree(FIXTURE, rec)
    data = text.encode() if isinstance(text, str) else text
    (rec / name).write_bytes(data)
    return rec


def _with_meta(data: str | bytes) -> Callable[[Path], list[str]]:
    """A case: ``replay`` of a copy of the fixture with this recording.toml."""
    return lambda folder: ["replay", str(_recording_with(folder, "recording.toml", data))]


def _png_with(folder: Path, name: str, text: str | bytes) -> Path:
    out = folder / "png"
    out.mkdir()
    hostile.png_of_zeros(out / "000.png", 64, 48)
    hostile.png_of_zeros(out / "001.png", 64, 48)
    (out / "camera.toml").write_text(
        "depth_scale = 1000\n[intrinsics]\nfx = 60.0\nfy = 60.0\ncx = 31.5\ncy = 23.5\n"
    )
    (out / name).write_bytes(text.encode() if isinstance(text, str) else text)
    return out


def _with_config(name: str, data: str | bytes) -> Callable[[Path], list[str]]:
    """A case: ``run`` on the fixture with one config file holding ``data``."""

    def make(folder: Path) -> list[str]:
        path = folder / name
        path.write_bytes(data.encode() if isinstance(data, str) else data)
        return ["run", "--device", FAST, "-c", str(path)]

    return make


def _bytes(path: Path, data: bytes) -> Path:
    path.write_bytes(data)
    return path


def _special(path: Path, kind: str) -> Path:
    hostile.make_special(path, kind)
    return path


def _special_in_recording(folder: Path, name: str, kind: str) -> Path:
    rec = folder / "rec"
    shutil.copytree(FIXTURE, rec)
    hostile.make_special(rec / name, kind)
    return rec


def _fakenect_with(folder: Path, kind: str) -> Path:
    fk = folder / "fk"
    write_fakenect(fk, read_recording(FIXTURE).frames()[:1])
    hostile.make_special(fk / "INDEX.txt", kind)
    return fk


def _one_pixel_wide(folder: Path) -> Path:
    from drivers.base import Frame, Intrinsics

    intr = Intrinsics(1, 48, 50.0, 50.0, 0.0, 23.5)
    depth = np.full((48, 1), 1500, np.uint16)
    write_recording(folder / "thin", [Frame(i, i / 30, depth, intr) for i in range(3)])
    return folder / "thin"


BIG = "9" * 400
HUGE = "9" * 5000
META = (FIXTURE / "recording.toml").read_text()

ONE_LINE_CASES: dict[str, tuple[Callable[[Path], list[str]], int, str]] = {
    # numbers
    "--set a 400-digit float field": (
        lambda d: ["run", "--device", FAST, "--set", f"scan.range_max_m={BIG}"],
        2,
        "scan.range_max_m=<integer of 400 digits> is too large",
    ),
    "--set a 5000-digit integer": (
        lambda d: ["run", "--device", FAST, "--set", f"daemon.seed={HUGE}"],
        2,
        "--set 'daemon.seed': the value has too many digits",
    ),
    "config: inf in an integer field": (
        _with_config("c.toml", "[cliff]\nblock_size = inf\n"),
        2,
        "cliff.block_size=inf has the wrong type (accepted: int)",
    ),
    "config: 5000-digit integer": (
        _with_config("c.toml", f"[daemon]\nseed = {HUGE}\n"),
        2,
        "is not valid TOML (a number with too many digits)",
    ),
    "ROS params: a 400-digit float": (
        _with_config("p.yaml", f"range_max: {BIG}\nscan_height: 3\n"),
        2,
        "range_max=<integer of 400 digits> is too large",
    ),
    "recording.toml: inf width": (
        _with_meta(META.replace("width = 640", "width = inf")),
        1,
        "[intrinsics] width = inf is not a finite number",
    ),
    "recording.toml: 400-digit fx": (
        _with_meta(META.replace("fx = ", f"fx = {BIG} #")),
        1,
        "[intrinsics] fx = <integer of 400 digits> is too large",
    ),
    "camera.toml: 400-digit depth_scale": (
        lambda d: ["replay", str(_png_with(d, "camera.toml", f"depth_scale = {BIG}\n"))],
        1,
        "depth_scale = <integer of 400 digits> is not a number in 1..1000000",
    ),
    "replay option fps of 400 digits": (
        lambda d: ["run", "--device", f"{FAST}&fps={BIG}"],
        2,
        "option fps=",
    ),
    "text sink every= of 400 digits": (
        lambda d: ["run", "--device", FAST, "--sink", f"text?every={BIG}"],
        2,
        "is too long to be an integer (more than 100 characters)",
    ),
    "mavlink baud= superscript digit": (
        lambda d: ["run", "--device", FAST, "--sink", "mavlink:/dev/null?baud=5²"],
        2,
        "is not an integer",
    ),
    "depth.txt timestamps nan": (
        lambda d: ["replay", str(_png_with(d, "depth.txt", "nan 000.png\n1 001.png\n"))],
        1,
        "depth.txt:1: timestamp 'nan' is not a finite number",
    ),
    "depth.txt timestamps 1e400": (
        lambda d: ["replay", str(_png_with(d, "depth.txt", "0 000.png\n1e400 001.png\n"))],
        1,
        "depth.txt:2: timestamp '1e400' is not a finite number",
    ),
    # nesting
    "config nested 3000 deep": (
        _with_config("c.toml", f"[mount]\nheight_m = {hostile.nested(3000)}\n"),
        2,
        "is not valid TOML (nested too deeply)",
    ),
    "--set nested 3000 deep": (
        lambda d: ["run", "--device", FAST, "--set", f"mount.height_m={hostile.nested(3000, '{')}"],
        2,
        "the value is nested too deeply",
    ),
    "YAML nested 3000 deep": (
        _with_config("p.yaml", f"range_min: {hostile.nested(3000)}\n"),
        2,
        "nested deeper than 64 levels",
    ),
    "recording.toml nested 3000 deep": (
        _with_meta(META + f"x = {hostile.nested(3000)}\n"),
        1,
        "recording.toml: is not valid TOML (nested too deeply)",
    ),
    "camera.toml nested 3000 deep": (
        lambda d: [
            "replay",
            str(_png_with(d, "camera.toml", f"x = {hostile.nested(3000, '{')}\n")),
        ],
        1,
        "camera.toml: is not valid TOML (nested too deeply)",
    ),
    # text that is not UTF-8
    "config in UTF-16": (
        _with_config("c.toml", "[mount]\nheight_m = 0.5\n".encode("utf-16")),
        2,
        "is UTF-16 text; depthnav reads UTF-8",
    ),
    "config in Latin-1": (
        _with_config("c.toml", '# caf\xe9\ndevice = "x"\n'.encode("latin-1")),
        2,
        "is not UTF-8 text (byte 0xe9 at offset 5)",
    ),
    "YAML in UTF-16": (
        _with_config("p.yaml", b"\xff\xfe" + "range_min: 0.5\n".encode("utf-16-le")),
        2,
        "is UTF-16 text",
    ),
    "recording.toml in Latin-1": (
        _with_meta(META.replace("Synthetic", "Synth\xe9tic").encode("latin-1")),
        1,
        "recording.toml: is not UTF-8 text",
    ),
    "camera.toml in UTF-16": (
        lambda d: [
            "replay",
            str(_png_with(d, "camera.toml", "depth_scale = 5\n".encode("utf-16"))),
        ],
        1,
        "camera.toml: is UTF-16 text",
    ),
    # special files, long names, folders where files belong
    "a FIFO as x.npz": (
        lambda d: ["replay", str(_special(d / "x.npz", "fifo"))],
        1,
        "x.npz: is a FIFO (named pipe), not a regular file",
    ),
    "a FIFO as recording.toml": (
        lambda d: ["replay", str(_special_in_recording(d, "recording.toml", "fifo"))],
        1,
        "recording.toml: is a FIFO (named pipe), not a regular file",
    ),
    "a FIFO as frames.npz": (
        lambda d: ["replay", str(_special_in_recording(d, "frames.npz", "fifo"))],
        1,
        "frames.npz: is a FIFO (named pipe), not a regular file",
    ),
    "a FIFO as openni:x.oni": (
        lambda d: ["run", "--device", f"openni:{_special(d / 'x.oni', 'fifo')}"],
        1,
        "x.oni: is a FIFO (named pipe), not a regular file",
    ),
    "a FIFO as the config": (
        lambda d: ["run", "--device", FAST, "-c", str(_special(d / "c.toml", "fifo"))],
        2,
        "c.toml: is a FIFO (named pipe), not a regular file",
    ),
    "a folder as recording.toml": (
        lambda d: ["replay", str(_special_in_recording(d, "recording.toml", "folder"))],
        1,
        "recording.toml: is a folder, not a regular file",
    ),
    "a folder as fakenect INDEX.txt": (
        lambda d: ["replay", str(_fakenect_with(d, "folder"))],
        1,
        "INDEX.txt: is a folder, not a regular file",
    ),
    "a FIFO as fakenect INDEX.txt": (
        lambda d: ["run", "--device", f"kinect?fakenect={_fakenect_with(d, 'fifo')}"],
        1,
        "INDEX.txt: is a FIFO (named pipe), not a regular file",
    ),
    "kinect?fakenect=/dev/zero": (
        lambda d: ["run", "--device", "kinect?fakenect=/dev/zero"],
        1,
        "/dev/zero: is a character device, not a folder",
    ),
    "a recording name of 300 bytes": (
        lambda d: ["replay", str(d / ("x" * 300))],
        1,
        "xxxxxxxxxx...: a name of 300 bytes, longer than the 255 a file name may have",
    ),
    "a config name of 300 bytes": (
        lambda d: ["run", "--device", FAST, "-c", str(d / ("c" * 300 + ".toml"))],
        2,
        "a name of 305 bytes, longer than the 255 a file name may have",
    ),
    # sink hosts and ports
    "udp://a..b:5": (
        lambda d: ["run", "--device", FAST, "--sink", "udp://a..b:5"],
        2,
        "host 'a..b' in sink spec 'udp://a..b:5' is not a valid host name or IP address",
    ),
    "udp host with a 64-character label": (
        lambda d: ["run", "--device", FAST, "--sink", f"udp://{'a' * 64}.local:5600"],
        2,
        "is not a valid host name or IP address",
    ),
    "udp://:٥٦٠٠ (Arabic-Indic digits)": (
        lambda d: ["run", "--device", FAST, "--sink", "udp://:٥٦٠٠"],
        2,
        "port '٥٦٠٠' in sink spec 'udp://:٥٦٠٠' is not 1..65535",
    ),
    "udp port with a superscript digit": (
        lambda d: ["run", "--device", FAST, "--sink", "udp://127.0.0.1:5²"],
        2,
        "port '5²'",
    ),
    # what divided by zero after the run had started
    "angle_increment_deg=5e-324": (
        lambda d: ["run", "--device", FAST, "--set", "scan.angle_increment_deg=5e-324"],
        2,
        "scan.angle_increment_deg=5e-324 is out of range",
    ),
    "paper scan of a 1-pixel-wide image": (
        lambda d: [
            "run",
            "--device",
            f"replay:{_one_pixel_wide(d)}?rate=max",
            "--method",
            "paper",
            "--set",
            "scan.scan_height=8",
            "--set",
            "daemon.cliff=false",
        ],
        2,
        "scan.method='paper' needs an image at least 2 pixels wide, this one is 1",
    ),
}


@pytest.mark.parametrize("case", list(ONE_LINE_CASES))
def test_one_line_error(tmp_path: Path, case: str) -> None:
    """Before: 'internal error' (OverflowError, RecursionError, UnicodeDecodeError, OSError errno
    36, IsADirectoryError, NotADirectoryError, UnicodeError from idna, ZeroDivisionError), or a
    hang (a FIFO), or a wrong value taken quietly (udp://:٥٦٠٠ as port 5600)."""
    make, code, says = ONE_LINE_CASES[case]
    got, out, err = run_cli(*make(tmp_path))  # the stdout sink, unless the case names one
    assert got == code, err
    line = one_error_line(err)
    assert says in line, line
    assert "internal error" not in err
    assert out == ""  # not one frame was output before the error
