"""Security: no listening socket unless asked, loopback defaults, no pickle or eval of input, and
recordings that neither write nor read outside the folder they name."""

from __future__ import annotations

import os
import re
import socket
from pathlib import Path

import numpy as np
import pytest

from depthnav_daemon.config.loader import build_config
from depthnav_daemon.errors import ConfigError
from depthnav_daemon.sinks import create_sink
from drivers import create_driver
from drivers.base import Frame, Intrinsics
from drivers.errors import RecordingError
from drivers.formats.recording_writer import write_recording

from .kit import ENDLESS, ROOT, depthnav, finish, free_udp_port, one_error_line, read_lines, start

A = Intrinsics(64, 48, 61.5, 57.25, 30.25, 22.75)


def frames(n: int = 2) -> list[Frame]:
    return [Frame(i, i / 30, np.full((48, 64), 1500, np.uint16), A) for i in range(n)]


def sockets_of(pid: int) -> list[tuple[str, str, str, str]]:
    """(protocol, local address, remote address, state) of every socket process ``pid`` holds."""
    inodes = set()
    for fd in Path(f"/proc/{pid}/fd").iterdir():
        try:
            m = re.fullmatch(r"socket:\[(\d+)\]", os.readlink(fd))
        except OSError:
            continue
        if m:
            inodes.add(m.group(1))
    found = []
    for proto in ("tcp", "tcp6", "udp", "udp6"):
        for line in Path(f"/proc/{pid}/net/{proto}").read_text().splitlines()[1:]:
            cols = line.split()
            if cols[9] in inodes:
                found.append((proto, cols[1], cols[2], cols[3]))
    return found


def test_no_listening_socket_with_every_client_sink(tmp_path: Path) -> None:
    """TCP LISTEN (state 0A) or an unconnected UDP socket (remote 0:0) would accept input."""
    rx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    rx.bind(("127.0.0.1", 0))
    mav = free_udp_port()
    proc = start(
        "run",
        "--device",
        ENDLESS,
        "--sink",
        "stdout",
        "--sink",
        "null",
        "--sink",
        f"udp://127.0.0.1:{rx.getsockname()[1]}",
        "--sink",
        f"mavlink+udp://127.0.0.1:{mav}",
        "--sink",
        f"rerun:{tmp_path / 'x.rrd'}?image=0",
    )
    try:
        read_lines(proc, 3)
        found = sockets_of(proc.pid)
    finally:
        code, _, err = finish(proc)
        rx.close()
    assert code == 0, err
    assert len(found) >= 2  # the two UDP sinks' sockets were seen
    for proto, local, remote, state in found:
        assert not (proto.startswith("tcp") and state == "0A"), (proto, local, state)
        assert not (proto.startswith("udp") and set(remote.split(":")[1]) == {"0"}), (
            proto,
            local,
            remote,
        )


def test_defaults_are_loopback() -> None:
    assert create_sink("udp://:5600").host == "127.0.0.1"
    assert create_sink("udp:5600").host == "127.0.0.1"
    assert create_sink("mavlink+udp://").udp == ("127.0.0.1", 14550)
    assert create_sink("rerun+grpc://").target == "rerun+http://127.0.0.1:9876/proxy"


def test_a_pickled_object_in_an_npz_is_never_loaded(tmp_path: Path) -> None:
    marker = tmp_path / "pwned"

    class Exploit:
        def __reduce__(self) -> tuple:
            return (open, (str(marker), "w"))

    depth = np.empty(1, dtype=object)
    depth[0] = Exploit()
    with open(tmp_path / "evil.npz", "wb") as fh:
        np.savez(fh, depth_mm=depth, intrinsics=np.array([61.5, 57.25, 30.25, 22.75]))
    assert b"pwned" in (tmp_path / "evil.npz").read_bytes()  # the payload is in the file
    p = depthnav("run", "--device", f"replay:{tmp_path / 'evil.npz'}?rate=max", timeout=60)
    assert p.returncode == 1, p.stderr
    assert "evil.npz" in one_error_line(p.stderr)
    assert not marker.exists()


def test_yaml_tags_are_not_executed(tmp_path: Path) -> None:
    marker = tmp_path / "pwned"
    cfg = tmp_path / "params.yaml"
    cfg.write_text(f"range_min: !!python/object/apply:os.system ['touch {marker}']\n")
    with pytest.raises(ConfigError, match=r"params\.yaml"):
        build_config([cfg])
    assert not marker.exists()


def test_the_code_never_unpickles_evals_or_uses_a_shell() -> None:
    banned = re.compile(
        r"\bpickle\b|\beval\(|\bexec\(|yaml\.load\(|allow_pickle=True|shell=True|"
        r"yaml\.unsafe_load|marshal\.loads"
    )
    hits = [
        f"{path.relative_to(ROOT)}:{n}: {line.strip()}"
        for folder in ("depthnav_daemon", "drivers")
        for path in (ROOT / folder).rglob("*.py")
        for n, line in enumerate(path.read_text().splitlines(), 1)
        if banned.search(line)
    ]
    assert hits == []


def test_a_recording_write_never_follows_a_planted_link(tmp_path: Path) -> None:
    """Between the 'folder is empty' check and the write, someone plants frames.npz.partial as a
    symlink to a file outside: O_EXCL makes the write fail instead of overwriting that file."""
    outside = tmp_path / "precious.txt"
    outside.write_text("do not touch")
    folder = tmp_path / "rec"
    folder.mkdir()

    def frames_then_plant():
        yield from frames()
        (folder / "frames.npz.partial").symlink_to(outside)

    with pytest.raises(RecordingError, match="writing the recording failed"):
        write_recording(folder, frames_then_plant())
    assert outside.read_text() == "do not touch"
    assert not (folder / "recording.toml").exists()


def test_record_writes_only_inside_the_folder_it_names(tmp_path: Path) -> None:
    parent = tmp_path / "space"
    parent.mkdir()
    p = depthnav(
        "record",
        "--device",
        f"replay:{ROOT / 'fixtures' / 'corridor_step'}?rate=max",
        "--frames",
        "2",
        str(parent / "a" / ".." / "rec"),
        timeout=120,
    )
    assert p.returncode == 0, p.stderr
    assert sorted(str(x.relative_to(parent)) for x in parent.rglob("*")) == [
        "a",
        "rec",
        "rec/frames.npz",
        "rec/recording.toml",
    ]


@pytest.mark.parametrize("name", ["../outside.png", "/etc/hostname", "link/x.png"])
def test_a_png_index_cannot_read_outside_its_folder(tmp_path: Path, name: str) -> None:
    from PIL import Image

    folder = tmp_path / "png"
    folder.mkdir()
    Image.fromarray(np.full((48, 64), 5000, np.uint16)).save(tmp_path / "outside.png")
    (folder / "link").symlink_to(tmp_path)
    (tmp_path / "x.png").write_bytes((tmp_path / "outside.png").read_bytes())
    (folder / "depth.txt").write_text(f"0.0 {name}\n")
    driver = create_driver(f"replay:{folder}?rate=max&fx=60&fy=58&cx=31&cy=23&scale=5000")
    with pytest.raises(RecordingError, match="outside the recording folder"):
        driver.open()
    driver.close()


def test_a_fakenect_index_cannot_name_files_outside(tmp_path: Path) -> None:
    folder = tmp_path / "fk"
    folder.mkdir()
    (folder / "INDEX.txt").write_text("../d-1.000000-0.pgm\n")
    with pytest.raises(RecordingError, match="not a fakenect file name"):
        create_driver(f"replay:{folder}?rate=max").open()
