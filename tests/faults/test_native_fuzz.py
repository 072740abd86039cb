""".oni files mutated until they pass depthnav's checker, then played by the real libOniFile.

The checker (drivers/formats/oni.check_oni) is what stands between a damaged file and native code:
every file it accepts must play, or end in one DriverError line, without crashing the process.
The player runs in a child process, so a native crash fails this test, not the run.
"""

from __future__ import annotations

import json
import random
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from drivers.base import Frame, Intrinsics
from drivers.errors import RecordingError
from drivers.formats.oni import check_oni, write_oni
from drivers.openni.native import find_library
from tests.drivers.driverkit import skip_without

from .kit import ROOT, depthnav, one_error_line

SMALL = Intrinsics(64, 48, 61.5, 57.25, 30.25, 22.75)
CASES, CASES_LONG = 40, 200  # accepted mutants played natively, CI / --soak (docs/hardening.md)

PLAYER = """
import json, sys
import drivers
from drivers.errors import DriverError
for path in sys.argv[1:]:
    print(json.dumps({"start": path}), flush=True)   # the last line names the file if we crash
    driver = drivers.create_driver(f"replay:{path}?rate=max")
    try:
        driver.open()
        n = 0
        while n < 10 and driver.read_frame(2.0) is not None:
            n += 1
        result = {"frames": n}
    except DriverError as exc:
        result = {"error": str(exc), "type": type(exc).__name__}
    finally:
        driver.close()
    print(json.dumps({"end": path, **result}), flush=True)
"""


@pytest.fixture(scope="module")
def base_oni(tmp_path_factory: pytest.TempPathFactory) -> Path:
    skip_without(find_library() is None, "libopenni2-0")
    rng = np.random.default_rng(3)
    frames = [
        Frame(i, i / 30, rng.integers(300, 6000, (48, 64), dtype=np.uint16), SMALL)
        for i in range(3)
    ]
    path = tmp_path_factory.mktemp("oni") / "base.oni"
    write_oni(path, frames)
    return path


def accepted_mutants(base: Path, out: Path, count: int, seed: int) -> list[Path]:
    """``count`` mutants of ``base`` (1-4 bytes changed, mostly in the headers) that check_oni
    accepts."""
    data = base.read_bytes()
    r = random.Random(seed)
    found: list[Path] = []
    for attempt in range(count * 50):
        buf = bytearray(data)
        for _ in range(r.randint(1, 4)):
            pos = r.randrange(24, 800) if r.random() < 0.8 else r.randrange(len(buf))
            buf[pos] = r.randrange(256)
        path = out / f"m{attempt:05d}.oni"
        path.write_bytes(bytes(buf))
        try:
            check_oni(path)
        except RecordingError:
            path.unlink()
            continue
        found.append(path)
        if len(found) == count:
            break
    return found


def test_mutated_oni_files_never_crash_the_native_player(
    base_oni: Path, tmp_path: Path, soak_long: bool
) -> None:
    cases = CASES_LONG if soak_long else CASES
    files = accepted_mutants(base_oni, tmp_path, cases, seed=20261122)
    assert len(files) == cases
    proc = subprocess.run(
        [sys.executable, "-c", PLAYER, *map(str, files)],
        capture_output=True,
        text=True,
        timeout=600,
        cwd=ROOT,
    )
    events = [json.loads(line) for line in proc.stdout.splitlines() if line.startswith("{")]
    crashed = events[-1].get("start") if events and "start" in events[-1] else None
    assert proc.returncode == 0, (
        f"native crash ({proc.returncode}) on {crashed}: {proc.stderr[-1500:]}"
    )
    ends = [e for e in events if "end" in e]
    assert len(ends) == cases
    for e in ends:
        if "error" in e:
            assert "\n" not in e["error"] and e["end"] in e["error"], e


def test_non_ascii_property_name_is_rejected_before_libonifile(
    base_oni: Path, tmp_path: Path
) -> None:
    """Found by the mutation test: one byte of a property name set to 0x8b made libOniFile
    SIGSEGV."""
    data = bytearray(base_oni.read_bytes())
    data[data.index(b"xnIsGenerating") + 4] = 0x8B
    bad = tmp_path / "bad_name.oni"
    bad.write_bytes(bytes(data))
    p = depthnav("run", "--device", f"replay:{bad}?rate=max", "--sink", "null", timeout=120)
    assert p.returncode == 1, p.stderr
    line = one_error_line(p.stderr)
    assert str(bad) in line and "bad name" in line


@pytest.mark.parametrize(
    ("mode", "needle"),
    [((128, 96), "needs 24576"), ((0, 0), "out of range"), ((65535, 48), "out of range")],
)
def test_resolution_that_does_not_match_the_frames(
    base_oni: Path, tmp_path: Path, mode: tuple[int, int], needle: str
) -> None:
    """Intrinsics (the stream's resolution) that do not match the image: one line, exit 1."""
    import struct

    data = bytearray(base_oni.read_bytes())
    at = data.index(b"xnMapOutputMode") + len(b"xnMapOutputMode\0") + 4
    struct.pack_into("<II", data, at, *mode)
    bad = tmp_path / "mode.oni"
    bad.write_bytes(bytes(data))
    p = depthnav("run", "--device", f"replay:{bad}?rate=max", "--sink", "null", timeout=120)
    assert p.returncode == 1, p.stderr
    assert needle in one_error_line(p.stderr)


# --- fakenect through Debian's real fakenect library ------------------------------------------
FAKENECT_CASES, FAKENECT_CASES_LONG = 4, 20  # one child process each (fakenect is process-global)


@pytest.fixture(scope="module")
def fakenect_base(tmp_path_factory: pytest.TempPathFactory) -> Path:
    from drivers.formats.fakenect import write_fakenect
    from drivers.kinect.freenect import find_library as find_freenect

    skip_without(find_freenect(fakenect=True) is None, "libfreenect0.5")
    vga = Intrinsics(640, 480, 580.0, 580.0, 319.5, 239.5)
    rng = np.random.default_rng(5)
    frames = [
        Frame(
            i, i / 30, rng.integers(500, 4000, (480, 640), dtype=np.uint16), vga, (0.0, -9.7, -1.4)
        )
        for i in range(3)
    ]
    folder = tmp_path_factory.mktemp("fk") / "base"
    write_fakenect(folder, frames)
    return folder


def fakenect_mutant(base: Path, out: Path, r: random.Random) -> Path:
    """A copy of ``base`` with shuffled/duplicated index lines, random accelerometer bytes,
    disparities beyond 11 bits and a colour file with a random header."""
    import shutil

    shutil.copytree(base, out)
    names = (out / "INDEX.txt").read_text().split()
    for path in out.glob("a-*.dump"):
        path.write_bytes(r.randbytes(12))
    pgm = next(out.glob("d-*.pgm"))
    data = bytearray(pgm.read_bytes())
    for _ in range(r.randint(1, 50)):
        data[r.randrange(17, len(data))] = r.randrange(256)
    pgm.write_bytes(bytes(data))
    rgb = "r-1000000.010000-1.ppm"
    (out / rgb).write_bytes(
        r.choice([b"P6 640 480 255\n", b"P6 1 1 255\n", b"P6 99999 99999 255\n", b"garbage\n"])
        + r.randbytes(r.randrange(0, 64))
    )
    names.insert(r.randrange(len(names) + 1), rgb)
    if r.random() < 0.5:
        names.append(r.choice(names))
    if r.random() < 0.3:
        r.shuffle(names)
    (out / "INDEX.txt").write_text("".join(n + "\n" for n in names))
    return out


def test_fakenect_mutants_never_crash_or_write_into_stdout(
    fakenect_base: Path, tmp_path: Path, soak_long: bool
) -> None:
    from drivers.kinect.driver import check_fakenect_recording

    r = random.Random(7)
    wanted = FAKENECT_CASES_LONG if soak_long else FAKENECT_CASES
    played = 0
    for i in range(wanted * 20):
        if played == wanted:
            break
        folder = fakenect_mutant(fakenect_base, tmp_path / f"m{i}", r)
        try:
            check_fakenect_recording(folder)  # only mutants the guard lets through reach fakenect
        except RecordingError:
            continue
        played += 1
        p = depthnav(
            "run", "--device", f"kinect?fakenect={folder}", "--sink", "stdout", timeout=120
        )
        assert p.returncode in (0, 1), (folder, p.returncode, p.stderr[-1500:])
        if p.returncode == 1:
            assert str(folder) in one_error_line(p.stderr)
        for line in p.stdout.splitlines():  # only our JSON: nothing the C library printed
            json.loads(line)
    assert played == wanted


def test_short_accelerometer_dump_is_rejected_before_fakenect(
    fakenect_base: Path, tmp_path: Path
) -> None:
    """Found here: fakenect printf()s 'Warning: Accelerometer data has an unexpected size' onto
    stdout, into the JSON stream. The guard now refuses such a dump with one line."""
    import shutil

    folder = tmp_path / "short"
    shutil.copytree(fakenect_base, folder)
    dump = next(folder.glob("a-*.dump"))
    dump.write_bytes(dump.read_bytes()[:10])
    p = depthnav("run", "--device", f"kinect?fakenect={folder}", "--sink", "stdout", timeout=120)
    assert p.returncode == 1, p.stderr
    assert p.stdout == ""
    assert f"{dump}: 10 bytes, an accelerometer dump has 12" in one_error_line(p.stderr)


def test_openni_stream_error_mid_run_ends_a_file_replay_once(
    base_oni: Path, tmp_path: Path
) -> None:
    """A stream that starts, then delivers frames that are not depth (the pixel format property
    says RGB888). Before the fix: 'internal error: ValueError: cannot reshape array' (and a format
    error was DeviceLost, which the daemon retries forever on a file). Now: one line, exit 1, no
    reconnect."""
    import struct

    data = bytearray(base_oni.read_bytes())
    at = data.index(b"oniPixelFormat") + len(b"oniPixelFormat\0") + 4
    struct.pack_into("<Q", data, at, 200)  # ONI_PIXEL_FORMAT_RGB888
    bad = tmp_path / "rgb.oni"
    bad.write_bytes(bytes(data))
    p = depthnav(
        "run",
        "--device",
        f"replay:{bad}?rate=max",
        "--sink",
        "stdout",
        "--set",
        "daemon.reconnect_backoff_s=0.01",
        timeout=120,
    )
    assert p.returncode == 1, p.stderr
    line = one_error_line(p.stderr)
    assert str(bad) in line and "is not depth" in line
    assert "reconnect" not in p.stderr and p.stdout == ""
