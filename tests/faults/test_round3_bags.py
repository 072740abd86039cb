"""Hardening round 3 (issue 35 classes 1 and 5, issue 32 item 6): ROS bags behind ``replay:``.

Bombs and lying sizes in MCAP and ROS 1 chunks, hostile ``metadata.yaml``, a stop during a
bag's probing, a cut ``.mcap``, wrong topics, a CameraInfo on the depth topic. Every case runs
the CLI in a child process and checks the one line, the exit code and the child's peak memory
against a clean run of a small bag.
"""

from __future__ import annotations

import os
import shutil
import signal
import struct
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from tests.drivers import bagkit
from tests.drivers.bagkit import DEPTH_TOPIC, INFO_TOPIC, BagSpec, bare_storage, write_bag
from tests.drivers.driverkit import ramp_frames
from tests.faults import hostile
from tests.faults.kit import ROOT, WAIT_S, depthnav_measured, json_lines, one_error_line

MEMORY_MARGIN_MB = 100  # over a clean run (48 MB); a bomb let through is GBs
ISSUE_BOUND_MB = 1000  # "each ends in one line ... under 1 GB" (issue 35)
FRAMES = 4


@pytest.fixture(scope="module")
def bags(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """Small valid bags of FRAMES frames: ROS 1, ROS 2 MCAP folder, its bare .mcap, db3."""
    root = tmp_path_factory.mktemp("bags")
    frames = ramp_frames(FRAMES)
    out = {
        "ros1": write_bag(root / "ok.bag", frames, BagSpec("ros1")),
        "mcap": write_bag(root / "mcap", frames, BagSpec("mcap")),
        "db3": write_bag(root / "db3", frames, BagSpec("db3")),
    }
    out["bare.mcap"] = bare_storage(out["mcap"], root / "bare.mcap")
    return out


@pytest.fixture(scope="module")
def clean_peak_mb(bags: dict[str, Path], tmp_path_factory: pytest.TempPathFactory) -> float:
    """The peak memory of recording a small bag's frames (``record`` reads the bag as ``run``
    does, without the numeric kernels, whose compiling would blur the figure)."""
    out = tmp_path_factory.mktemp("clean") / "rec"
    done = depthnav_measured("record", "--device", f"replay:{bags['bare.mcap']}", "--frames", "2",
                             str(out))  # fmt: skip
    assert done.returncode == 0, done.stderr
    return done.peak_mb


def _refused(spec: str, code: int = 1) -> tuple[str, str, float]:
    """``depthnav record --device spec`` refused: (its one error line, stderr, peak MB)."""
    with tempfile.TemporaryDirectory(prefix="depthnav-r3-") as folder:
        out = Path(folder) / "rec"
        done = depthnav_measured("record", "--device", spec, "--frames", "1", str(out))
        assert done.returncode == code, done.stderr
        assert not out.exists()  # nothing written
    return one_error_line(done.stderr), done.stderr, done.peak_mb


# --- class 1: decompression and metadata are bounded ------------------------------------------
@pytest.mark.parametrize("name", list(hostile.BAG_BOMBS))
def test_an_mcap_bomb_is_one_line_in_bounded_memory(
    tmp_path: Path, name: str, clean_peak_mb: float
) -> None:
    bomb = hostile.mcap_bomb(tmp_path / "bomb.mcap", name)
    assert bomb.stat().st_size < 3 << 20  # small on disk, GiBs when inflated
    line, err, peak = _refused(f"replay:{bomb}?rate=max")
    assert str(bomb) in line and "not a readable ROS bag" in line, err
    codec, _size, declared = hostile.BAG_BOMBS[name]
    if declared > (300 << 20):
        assert f"declares {declared} bytes" in line
    elif declared == 1000:
        assert f"{codec} chunk inflates beyond its declared 1000 bytes" in line
    assert "hint: the bag is damaged or built to exhaust memory" in err
    assert peak < clean_peak_mb + MEMORY_MARGIN_MB, f"{peak:.0f} MB, clean {clean_peak_mb:.0f}"


def test_a_chunk_of_zeros_or_of_millions_of_tiny_records_is_refused_early(
    tmp_path: Path, clean_peak_mb: float
) -> None:
    from backports import zstd

    size = 256 * hostile.MIB  # declared honestly, within the chunk bound
    zeros = hostile.mcap_file(
        tmp_path / "zeros.mcap",
        [hostile.mcap_chunk("zstd", hostile.zeros_compressed("zstd", size), size)],
    )
    line, _, peak = _refused(f"replay:{zeros}?rate=max")
    assert "holds no MCAP record at byte 0" in line
    assert peak < clean_peak_mb + MEMORY_MARGIN_MB  # refused at its first piece, not its end
    tiny = bytes([0x0F]) + struct.pack("<Q", 0)  # 9-byte records: rosbags lists each one
    raw = tiny * 2_000_000
    many = hostile.mcap_file(
        tmp_path / "many.mcap", [hostile.mcap_chunk("zstd", zstd.compress(raw), len(raw))]
    )
    line, _, peak = _refused(f"replay:{many}?rate=max")
    assert "holds more than 250000 records" in line
    assert peak < clean_peak_mb + MEMORY_MARGIN_MB


def _ros1_compressed(path: Path, codec: str) -> Path:
    """A ROS 1 bag of FRAMES images and CameraInfos in ``codec`` (lz4, bz2) chunks."""
    from rosbags.rosbag1 import Writer

    ts, spec = bagkit._typestore("ros1"), BagSpec("ros1")
    writer = Writer(path)
    writer.set_compression(Writer.CompressionFormat[codec.upper()])
    writer.open()
    image = writer.add_connection(DEPTH_TOPIC, "sensor_msgs/msg/Image", typestore=ts)
    info = writer.add_connection(INFO_TOPIC, "sensor_msgs/msg/CameraInfo", typestore=ts)
    for frame in ramp_frames(FRAMES):
        t_ns = bagkit.T0_S * 10**9 + round(frame.timestamp_s * 1e9)
        stamp = ts.types["builtin_interfaces/msg/Time"](sec=t_ns // 10**9, nanosec=t_ns % 10**9)
        msg = bagkit.image_msg(ts, frame, stamp, spec, "16UC1")
        writer.write(image, t_ns, ts.serialize_ros1(msg, msg.__msgtype__))
        msg = bagkit.info_msg(ts, frame, stamp, spec)
        writer.write(info, t_ns, ts.serialize_ros1(msg, msg.__msgtype__))
    writer.close()
    return path


@pytest.mark.parametrize("codec", ["lz4", "bz2"])
def test_a_ros1_chunk_larger_than_it_declares_is_refused(tmp_path: Path, codec: str) -> None:
    bag = _ros1_compressed(tmp_path / f"{codec}.bag", codec)
    done = depthnav_measured("replay", str(bag), "--sink", "stdout")
    assert done.returncode == 0 and len(json_lines(done.stdout)) == FRAMES, done.stderr
    hostile.ros1_chunk_size_lie(bag, 1000)
    line, _, _ = _refused(f"replay:{bag}?rate=max")
    assert f"{codec} chunk inflates beyond its declared 1000 bytes" in line


@pytest.mark.parametrize("name", list(hostile.HOSTILE_BAG_METADATA))
def test_hostile_metadata_yaml_is_one_line_at_once(
    tmp_path: Path, name: str, clean_peak_mb: float
) -> None:
    folder = hostile.bag_metadata(tmp_path / "bag", hostile.HOSTILE_BAG_METADATA[name])
    t0 = time.monotonic()
    line, _, peak = _refused(f"replay:{folder}?rate=max")
    assert "metadata.yaml" in line, line
    assert time.monotonic() - t0 < WAIT_S  # was past 120 s for a 50 MB comment line
    assert peak < clean_peak_mb + MEMORY_MARGIN_MB


def test_a_bomb_through_run_snapshot_and_as_a_sensor(tmp_path: Path, bags) -> None:
    """The same one line through every command that opens a device (their peak includes the
    numeric kernels: the issue's bound, 1 GB, is checked). A clean run first, so a cold kernel
    cache is filled by it, not by the runs measured (compiling took one to 1.46 GB)."""
    warm = depthnav_measured(
        "run", "--device", f"replay:{bags['bare.mcap']}?rate=max", "--sink", "null"
    )
    assert warm.returncode == 0, warm.stderr
    # the issue's bound, or the clean run's peak where this machine's run costs more (under the
    # full suite runs peaked at 1.2-1.5 GB with a valid bag too): the bomb adds nothing to it
    bound = max(ISSUE_BOUND_MB, warm.peak_mb + MEMORY_MARGIN_MB)
    bomb = hostile.mcap_bomb(tmp_path / "bomb.mcap", "zstd 4 GiB declared as 1000 B")
    done = depthnav_measured("run", "--device", f"replay:{bomb}", "--sink", "null")
    assert done.returncode == 1, done.stderr
    assert "inflates beyond its declared 1000 bytes" in one_error_line(done.stderr)
    assert done.peak_mb < bound, (done.peak_mb, warm.peak_mb)
    done = depthnav_measured("snapshot", "--device", f"replay:{bomb}", str(tmp_path / "s.png"))
    assert done.returncode == 1, done.stderr
    assert "inflates beyond its declared 1000 bytes" in one_error_line(done.stderr)
    assert done.peak_mb < bound, (done.peak_mb, warm.peak_mb)
    config = tmp_path / "robot.toml"
    config.write_text(
        f'[[sensor]]\nname = "front"\ndevice = "replay:{bomb}?rate=max"\n'
        "[sensor.mount]\nheight_m = 0.5\ntilt_deg = 10.0\n"
    )
    done = depthnav_measured("run", "--config", str(config), "--sink", "null")
    assert done.returncode == 1, done.stderr
    assert "inflates beyond its declared 1000 bytes" in one_error_line(done.stderr)
    assert done.peak_mb < bound, (done.peak_mb, warm.peak_mb)


def _slow_bag(path: Path, chunks: int = 24) -> Path:
    """An MCAP of ``chunks`` valid 256 MiB chunks (one big message each, on a channel nobody
    reads): its probing inflates them all, seconds of work, without breaking a bound."""
    from backports import zstd

    size = 256 * hostile.MIB
    head = struct.pack("<HIQQ", 7, 0, 0, 0)
    record = bytes([0x05]) + struct.pack("<Q", size - 9) + head
    data = zstd.compress(record + bytes(size - len(record)))
    return hostile.mcap_file(path, [hostile.mcap_chunk("zstd", data, size)] * chunks)


def _has_open(pid: int, path: Path) -> bool:
    try:
        fds = os.listdir(f"/proc/{pid}/fd")
    except FileNotFoundError:
        return False
    for fd in fds:
        try:
            if os.readlink(f"/proc/{pid}/fd/{fd}") == str(path):
                return True
        except OSError:
            continue
    return False


@pytest.fixture(scope="module")
def slow_bag(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return _slow_bag(tmp_path_factory.mktemp("slow") / "slow.mcap")


@pytest.mark.parametrize(
    ("command", "sig", "code"),
    [("run", signal.SIGTERM, 0), ("run", signal.SIGINT, 130), ("record", signal.SIGTERM, 0)],
    ids=["run-TERM", "run-INT", "record-TERM"],
)
def test_a_stop_ends_a_bags_probing_within_a_second(
    tmp_path: Path, slow_bag: Path, command: str, sig: int, code: int
) -> None:
    """Found: SIGTERM waited for the probing (a 256 MiB chunk takes ~2 s to inflate here).
    The stop is seen between two pieces of a chunk: the command's stop code, nothing written."""
    out = tmp_path / "rec"
    args = (
        ["run", "--device", f"replay:{slow_bag}?rate=max", "--sink", "stdout"]
        if command == "run"
        else ["record", "--device", f"replay:{slow_bag}", "--frames", "2", str(out)]
    )
    proc = subprocess.Popen(
        [sys.executable, "-m", "depthnav_daemon", *args],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=ROOT,
    )  # fmt: skip
    deadline = time.monotonic() + 120  # a cold kernel cache compiles first
    while not _has_open(proc.pid, slow_bag):  # the bag is open: its probing has begun
        assert proc.poll() is None, proc.communicate()
        assert time.monotonic() < deadline, "the bag was never opened"
        time.sleep(0.005)
    t0 = time.monotonic()
    proc.send_signal(sig)
    stdout, err = proc.communicate(timeout=WAIT_S)
    took = time.monotonic() - t0
    assert proc.returncode == code, err
    assert "Traceback" not in err and "error:" not in err, err
    assert stdout == "" and not out.exists()
    assert took < 1.0, f"stopped {took:.2f} s after the signal"


# --- issue 32 item 6: a cut .mcap, topics, hints ----------------------------------------------
def test_an_mcap_cut_short_still_gives_its_frames(tmp_path: Path, bags: dict[str, Path]) -> None:
    data = bags["bare.mcap"].read_bytes()
    for cut in (1, 40):  # into the footer; into the summary
        path = tmp_path / f"cut{cut}.mcap"
        path.write_bytes(data[:-cut])
        done = depthnav_measured("replay", str(path), "--sink", "stdout")
        assert done.returncode == 0, done.stderr
        assert len(json_lines(done.stdout)) == FRAMES
        assert "no readable summary or footer (cut short?)" in done.stderr
    folder = tmp_path / "folder"  # a ROS 2 folder whose storage file is cut
    shutil.copytree(bags["mcap"], folder)
    (storage,) = folder.glob("*.mcap")
    storage.write_bytes(storage.read_bytes()[:-1])
    done = depthnav_measured("replay", str(folder), "--sink", "stdout")
    assert done.returncode == 0 and len(json_lines(done.stdout)) == FRAMES, done.stderr
    half = tmp_path / "half.mcap"  # cut inside its only chunk: nothing whole to read
    half.write_bytes(data[: len(data) // 2])
    line, err, _ = _refused(f"replay:{half}?rate=max")
    assert "not a readable ROS bag" in line and "mcap recover" in err
    assert "rosbag reindex" not in err


def test_the_cut_file_hint_names_rosbag_reindex_only_for_ros1(
    tmp_path: Path, bags: dict[str, Path]
) -> None:
    bag = tmp_path / "cut.bag"
    bag.write_bytes(bags["ros1"].read_bytes()[:-200])
    _, err, _ = _refused(f"replay:{bag}?rate=max")
    assert "rosbag reindex" in err
    db3 = tmp_path / "cut.db3"
    (storage,) = bags["db3"].glob("*.db3")
    db3.write_bytes(storage.read_bytes()[:1000])
    _, err, _ = _refused(f"replay:{db3}?rate=max")
    assert "rosbag reindex" not in err and "mcap recover" not in err


def test_a_wrong_topic_is_bad_usage(bags: dict[str, Path]) -> None:
    line, err, _ = _refused(f"replay:{bags['ros1']}?topic=/nope", code=2)
    assert "no topic '/nope'" in line and f"image topics: {DEPTH_TOPIC}" in err
    line, err, _ = _refused(f"replay:{bags['mcap']}?topic={INFO_TOPIC}", code=2)
    assert "CameraInfo, not an sensor_msgs/msg/Image" in line
    line, err, _ = _refused(f"replay:{bags['mcap']}?info_topic=/nope", code=2)
    assert "no CameraInfo messages on '/nope'" in line and INFO_TOPIC in err


def test_a_topic_without_messages_is_said_as_such(tmp_path: Path) -> None:
    from rosbags.rosbag1 import Writer

    bag = tmp_path / "empty.bag"
    with Writer(bag) as writer:
        writer.add_connection(
            DEPTH_TOPIC, "sensor_msgs/msg/Image", typestore=bagkit._typestore("ros1")
        )
    line, _, _ = _refused(f"replay:{bag}")
    assert f"no depth images: the image topic {DEPTH_TOPIC} holds no message" in line
    line, _, _ = _refused(f"replay:{bag}?topic={DEPTH_TOPIC}")
    assert f"topic '{DEPTH_TOPIC}' holds no message" in line


# --- class 5: a CameraInfo connection on the depth topic --------------------------------------
@pytest.mark.parametrize("kind", ["ros1", "mcap"])
@pytest.mark.parametrize("separate_info", [True, False])
def test_camera_info_on_the_depth_topic(tmp_path: Path, kind: str, separate_info: bool) -> None:
    """Found: "'CameraInfo' object has no attribute 'encoding'" after the first frame. The
    depth topic's images are read, its CameraInfo gives the intrinsics when no other does."""
    name = "b.bag" if kind == "ros1" else "b"
    spec = BagSpec(kind, info=separate_info, info_on_depth=True)
    bag = write_bag(tmp_path / name, ramp_frames(FRAMES), spec)
    done = depthnav_measured("replay", str(bag), "--sink", "stdout")
    assert done.returncode == 0, done.stderr
    lines = json_lines(done.stdout)
    assert [m["seq"] for m in lines] == list(range(FRAMES))
    assert "Traceback" not in done.stderr and "error:" not in done.stderr
    assert all(len(m["scan"]["ranges"]) > 0 for m in lines)  # a scan came out of every frame


# --- generated: chunks of any codec, content and declared size ---------------------------------
def _records(kind: str, size: int, seed: int) -> bytes:
    """``size`` bytes of chunk content: zeros, Image message records of random data, 9-byte
    records, or noise."""
    import random

    rng = random.Random(seed)
    if kind == "zeros":
        return bytes(size)
    if kind == "tiny":
        return (bytes([0x0F]) + struct.pack("<Q", 0)) * (size // 9)
    if kind == "noise":
        return rng.randbytes(min(size, 1 << 20))
    out = bytearray()  # message records on the image channel (1), data that is not an Image
    while len(out) < size:
        data = rng.randbytes(rng.randint(0, 4096))
        body = struct.pack("<HIQQ", 1, 0, len(out), len(out)) + data
        out += bytes([0x05]) + struct.pack("<Q", len(body)) + body
    return bytes(out)


def _compress(codec: str, raw: bytes) -> bytes:
    if codec == "zstd":
        from backports import zstd

        return zstd.compress(raw, 1)
    if codec == "lz4":
        import lz4.frame

        return lz4.frame.compress(raw)
    return raw


@settings(deadline=None, suppress_health_check=list(HealthCheck), derandomize=True,
          database=None, max_examples=40)  # fmt: skip
@given(
    codec=st.sampled_from(["zstd", "lz4", ""]),
    kind=st.sampled_from(["zeros", "records", "tiny", "noise"]),
    size=st.sampled_from([0, 1, 1000, 1 << 20, 48 << 20]),
    declared=st.sampled_from(["true", "+1", "-1", "1000", "0", "huge", "max"]),
    cut=st.sampled_from([0, 1, 17]),
    seed=st.integers(0, 1000),
)
def test_fuzz_mcap_chunks(
    tmp_path_factory: pytest.TempPathFactory, codec, kind, size, declared, cut, seed
) -> None:
    """Any chunk: the bag is read or refused with a RecordingError of one line, never a hang,
    and the process's peak memory grows by less than 250 MB (a chunk is at most 48 MiB here,
    bombs of GiBs are the cases above)."""
    from drivers.errors import RecordingError
    from drivers.formats.bag_limits import CHUNK_MAX_BYTES
    from drivers.formats.rosbag import DepthBag

    raw = _records(kind, size, seed)
    data = _compress(codec, raw)
    data = data[: len(data) - cut] if cut else data
    said = {"true": len(raw), "+1": len(raw) + 1, "-1": max(len(raw) - 1, 0), "1000": 1000,
            "0": 0, "huge": CHUNK_MAX_BYTES + 1, "max": 2**64 - 1}[declared]  # fmt: skip
    path = tmp_path_factory.mktemp("chunk") / "x.mcap"
    hostile.mcap_file(path, [hostile.mcap_chunk(codec, data, said)])
    with hostile.PeakMemory() as peak, hostile.Watchdog():
        try:
            bag = DepthBag(path)
            bag.probe(intrinsics_given=True)
            for _ in bag.frames():
                pass
        except RecordingError as exc:
            assert "\n" not in str(exc) and str(path) in str(exc)
    assert peak.growth_mb is None or peak.growth_mb < 250, peak.growth_mb
