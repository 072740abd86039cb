"""What depthnav writes stays whole, and what it wrote before a failure stays intact.

stdout on a disk that fills, ``calibrate --write`` onto a commented config (through a symlink),
``record`` with text that is not UTF-8, and a fakenect recording losing a file mid-replay.
"""

from __future__ import annotations

import os
import subprocess
from pathlib import Path

import pytest

from drivers import create_driver
from drivers.errors import RecordingError
from drivers.formats.fakenect import write_fakenect
from drivers.formats.recording import read_recording
from drivers.formats.recording_writer import write_recording

from .kit import FIXTURE, ROOT, json_lines, one_error_line, run_cli, small_disk

FAST = f"replay:{FIXTURE}?rate=max"


def test_stdout_on_a_disk_that_fills_ends_with_a_whole_line(tmp_path: Path) -> None:
    """Before: the last line was cut where the disk filled (half a JSON object). Now the part of
    the line that was written is cut off again; the null sink goes on to the end."""
    with small_disk(tmp_path, "1m") as (disk, preexec):
        out = disk / "scan.jsonl"
        with open(out, "w") as fh:
            run = subprocess.run(
                [
                    os.sys.executable,
                    "-m",
                    "depthnav_daemon",
                    "run",
                    "--device",
                    f"{FAST}&loop=1",
                    "--max-frames",
                    "300",
                    "--sink",
                    "stdout",
                    "--sink",
                    "null",
                ],
                stdout=fh,
                stderr=subprocess.PIPE,
                text=True,
                timeout=120,
                cwd=ROOT,
                preexec_fn=preexec,
            )
        assert run.returncode == 0, run.stderr
        assert "sink stdout failed: writing to stdout failed" in run.stderr
        assert "300 frames processed; dropped sinks: stdout" in run.stderr
        data = out.read_bytes()
    assert data.endswith(b"\n")
    lines = json_lines(data.decode())  # every line whole
    assert 10 < len(lines) < 300
    assert [m["seq"] for m in lines] == list(range(len(lines)))


COMMENTED = """\
# the robot's depth sensor
device = "kinect"  # front, under the bumper

[mount]  # measured by hand in May
height_m = 0.3  # to the optical centre
tilt_deg = 1.0

[scan]
# the room is small
range_max_m = 4.0
"""


def test_calibrate_write_keeps_comments_and_writes_through_a_symlink(tmp_path: Path) -> None:
    """Before: every comment was dropped, and a symlink was replaced by a regular file (the
    target never updated)."""
    real = tmp_path / "configs" / "robot.toml"
    real.parent.mkdir()
    real.write_text(COMMENTED)
    real.chmod(0o640)
    link = tmp_path / "robot.toml"
    link.symlink_to(real)
    run = subprocess.run(
        [
            os.sys.executable,
            "-m",
            "depthnav_daemon",
            "calibrate",
            "--device",
            FAST,
            "--frames",
            "4",
            "--write",
            str(link),
        ],
        capture_output=True,
        text=True,
        timeout=120,
        cwd=ROOT,
    )
    assert run.returncode == 0, run.stderr
    assert link.is_symlink() and link.resolve() == real
    text = real.read_text()
    for comment in (
        "# the robot's depth sensor",
        "# front, under the bumper",
        "# measured by hand in May",
        "# to the optical centre",
        "# the room is small",
    ):
        assert comment in text
    assert "height_m = 0.3 " not in text and "tilt_deg = 1.0\n" not in text  # updated
    assert 'device = "kinect"' in text and "range_max_m = 4.0" in text
    assert text.index("[mount]") < text.index("roll_deg") < text.index("[scan]")
    assert real.stat().st_mode & 0o777 == 0o640
    assert sorted(p.name for p in real.parent.iterdir()) == ["robot.toml"]  # no temporary left


def test_record_refuses_a_description_that_is_not_utf8_before_recording(tmp_path: Path) -> None:
    """Before: every frame was recorded and compressed, then writing recording.toml failed and the
    folder was left without it (unreplayable, and blocking the next record there)."""
    out = tmp_path / "rec"
    # bytes that are not UTF-8 on the command line reach Python as lone surrogates
    code, _, err = run_cli("record", "--device", FAST, "--description", "caf\udce9", str(out))
    assert code == 2
    assert "--description is not UTF-8 text" in one_error_line(err)
    assert not out.exists()
    with pytest.raises(RecordingError, match="description is not UTF-8 text"):
        write_recording(out, iter(()), description="caf\udce9")  # refused before any frame
    assert not out.exists()


def test_record_from_a_path_that_is_not_utf8_keeps_every_frame(tmp_path: Path) -> None:
    folder = Path(os.fsdecode(bytes(tmp_path) + b"/caf\xe9"))  # a folder name in Latin-1
    os.symlink(FIXTURE, folder)
    out = tmp_path / "rec"
    code, _, err = run_cli(
        "record", "--device", f"replay:{folder}?rate=max", "--frames", "5", str(out)
    )
    assert code == 0, err
    rec = read_recording(out)
    assert len(rec.depth_mm) == 5
    assert rec.device.endswith("caf\ufffd?rate=max")  # the byte that is not UTF-8, replaced


def test_a_fakenect_file_deleted_during_the_replay_is_one_line(tmp_path: Path) -> None:
    """Before: FileNotFoundError (an internal error) at the frame whose file had gone."""
    folder = tmp_path / "fk"
    write_fakenect(folder, read_recording(FIXTURE).frames()[:3])
    driver = create_driver(f"replay:{folder}?rate=max")
    driver.open()
    try:
        first = driver.read_frame(1.0)
        assert first is not None and first.seq == 0  # what came before is intact
        pgms = sorted(folder.glob("d-*.pgm"))
        pgms[2].unlink()  # frames are read one at a time: frame 2's file goes after frame 0
        assert driver.read_frame(1.0) is not None
        with pytest.raises(RecordingError) as info:
            driver.read_frame(1.0)
    finally:
        driver.close()
    msg = str(info.value)
    assert "\n" not in msg and pgms[2].name in msg and "no such file" in msg


def test_stdout_writer_serves_its_own_queue_after_a_close_at_once(tmp_path: Path) -> None:
    """A stop signal right after start-up closed the stdout sink before its writer thread ran a
    line: the thread then read the cleared attributes ('Exception in thread sink stdout:
    Traceback ... AssertionError', seen once in a full suite run). The thread now gets its queue
    and fd when it is made; here it runs after the sink has let go of both."""
    import queue

    from depthnav_daemon.sinks.json.stdout import StdoutSink, _lock_of

    sink = StdoutSink()
    lines: queue.Queue[bytes | None] = queue.Queue()
    out = tmp_path / "out.jsonl"
    with open(out, "wb") as fh:
        lines.put(b'{"seq":0}\n')
        lines.put(None)
        sink._queue = None  # what close() leaves
        sink._fd = None
        sink._writer(lines, fh.fileno(), _lock_of(fh.fileno()))
    assert out.read_bytes() == b'{"seq":0}\n' and sink._error is None
