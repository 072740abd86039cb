"""Round 3, part 2 (issue 35 items 6 and 8): the figure outputs of ``snapshot``, ``mount --plot``
and ``--sweep`` go through one guarded path (commands.common.figure_output / save_figure over
drivers.files.open_output): a long name, a FIFO, a device or a folder is one line, never a hang;
the same file for --plot and --sweep is refused. Through the CLI in a child process."""

from __future__ import annotations

import os
import threading
import time
from pathlib import Path

import pytest

from drivers.errors import RecordingError
from drivers.files import open_output
from tests.faults import hostile
from tests.faults.kit import FAST, depthnav_measured, one_error_line

MOUNT = ("mount", "--height-m", "0.5", "--tilt-deg", "15")
BOUND_S = 60.0  # a FIFO used to block for ever: a generous bound for a loaded machine
EXPECT = {  # kind -> what the one line says
    "fifo": "is a FIFO (named pipe), not a regular file",
    "folder": "is a directory",
    "dev_null": "is a character device (through a symlink), not a regular file",
    "dev_full": "is a character device (through a symlink), not a regular file",
    "dev_zero": "is a character device (through a symlink), not a regular file",
    "long name": "a name of 304 bytes, longer than the 255",
    "long path": "longer than the 4095 the system allows",
}


def _command(kind: str, where: str, out: Path) -> list[str]:
    if where == "snapshot":
        return ["snapshot", "--device", FAST, "--frame", "1", str(out)]
    return [*MOUNT, where, str(out)]


@pytest.mark.parametrize("where", ["snapshot", "--plot", "--sweep"])
@pytest.mark.parametrize("kind", hostile.OUTPUT_KINDS)
def test_a_figure_output_that_is_not_a_file_is_one_line(
    tmp_path: Path, kind: str, where: str
) -> None:
    """Before: 'internal error: OSError [Errno 36]' for a 300-byte name; a FIFO blocked
    ``snapshot`` for ever (SIGTERM ignored) and ``mount --plot`` until SIGTERM."""
    out = hostile.make_output(tmp_path, kind)
    before = sorted(tmp_path.iterdir())
    t0 = time.monotonic()
    done = depthnav_measured(*_command(kind, where, out))
    assert time.monotonic() - t0 < BOUND_S
    assert done.returncode == 2, done.stderr
    line = one_error_line(done.stderr)
    assert EXPECT[kind] in line and len(line) < 300, line
    assert "internal error" not in done.stderr and "depthnav: hint:" in done.stderr
    assert done.peak_mb < 1024
    if kind == "fifo":
        assert out.is_fifo()  # nothing replaced it
    assert sorted(tmp_path.iterdir()) == before  # nothing was written beside it


def test_the_same_file_for_plot_and_sweep_is_refused(tmp_path: Path) -> None:
    for plot, sweep in (("same.png", "same.png"), ("same.png", "./sub/../same.png")):
        (tmp_path / "sub").mkdir(exist_ok=True)
        done = depthnav_measured(
            *MOUNT, "--plot", str(tmp_path / plot), "--sweep", str(tmp_path / sweep)
        )
        assert done.returncode == 2, done.stderr
        assert "--plot and --sweep name the same file" in one_error_line(done.stderr)
        assert not (tmp_path / "same.png").exists() and done.stdout == ""


def test_a_symlink_to_the_other_figure_is_the_same_file(tmp_path: Path) -> None:
    (tmp_path / "side.png").write_bytes(b"old")
    (tmp_path / "link.png").symlink_to(tmp_path / "side.png")
    done = depthnav_measured(
        *MOUNT, "--plot", str(tmp_path / "side.png"), "--sweep", str(tmp_path / "link.png")
    )
    assert done.returncode == 2 and "the same file" in done.stderr, done.stderr
    assert (tmp_path / "side.png").read_bytes() == b"old"


def test_both_figures_are_written_through_the_guarded_path(tmp_path: Path) -> None:
    (tmp_path / "old.png").write_bytes(b"x" * 100_000)  # an existing file is replaced whole
    done = depthnav_measured(
        *MOUNT, "--plot", str(tmp_path / "old.png"), "--sweep", str(tmp_path / "sweep.svg")
    )
    assert done.returncode == 0, done.stderr
    assert (tmp_path / "old.png").read_bytes().startswith(b"\x89PNG")
    assert b"<svg" in (tmp_path / "sweep.svg").read_bytes()


def test_a_fifo_swapped_in_after_the_check_fails_instead_of_blocking(tmp_path: Path) -> None:
    """open_output on a FIFO with no reader (as if swapped in between the check and the save)
    fails at once with ENXIO's line; with a reader present it is refused after the open."""
    fifo = tmp_path / "f.png"
    os.mkfifo(fifo)
    result: list[BaseException] = []
    worker = threading.Thread(
        target=lambda: _catch(result, lambda: open_output(fifo, what="figure")), daemon=True
    )
    worker.start()
    worker.join(timeout=10)
    assert not worker.is_alive(), "open_output blocked on a FIFO"
    assert isinstance(result[0], RecordingError) and "FIFO" in str(result[0])
    reader = os.open(fifo, os.O_RDONLY | os.O_NONBLOCK)  # a reader: the open itself succeeds
    try:
        with pytest.raises(RecordingError, match="FIFO"):
            open_output(fifo, what="figure")
    finally:
        os.close(reader)


def _catch(out: list[BaseException], fn) -> None:  # type: ignore[no-untyped-def]
    try:
        fn()
    except BaseException as exc:  # handed to the test thread
        out.append(exc)
