"""Depth as robots record it: mono16 and image_transport's compressedDepth (PNG and RVL).

The compressedDepth bytes are made here by a test-side encoder written from the reference
format (compressed_depth_image_transport's codec.cpp, compression_common.h, rvl_codec.cpp), not
by the decoder under test: a 12-byte ConfigHeader packed with ``struct`` (int32 format 0 =
INV_DEPTH, float32 depthParam a, b), then a 16-bit grayscale PNG written by Pillow, or uint32
width, height and an RVL stream from :func:`rvl_encode` (Wilson's algorithm: zero-run and
non-zero-run lengths, zigzag deltas, 3-bit variable-length nibbles packed most significant
first into little-endian 32-bit words).
"""

from __future__ import annotations

import io
import json
import struct
import zlib
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

import drivers
from drivers.base import Frame
from drivers.errors import RecordingError
from drivers.formats.rosbag import DepthBag
from tests.drivers.bagkit import DEPTH_TOPIC, BagSpec, write_bag
from tests.drivers.driverkit import ramp_frames
from tests.faults.kit import depthnav, one_error_line

PACKED_TOPIC = DEPTH_TOPIC + "/compressedDepth"
Z0, DEPTH_MAX_M = 100.0, 10.0  # the plugin's depth_quantization and depth_max defaults


# --- the test-side encoder ----------------------------------------------------------------------
def png16(image: np.ndarray) -> bytes:
    """A 16-bit grayscale PNG of a uint16 image (Pillow)."""
    out = io.BytesIO()
    Image.fromarray(image.astype(np.uint16)).save(out, format="PNG")
    return out.getvalue()


def config_header(a: float = 0.0, b: float = 0.0) -> bytes:
    return struct.pack("<iff", 0, a, b)  # compressionFormat INV_DEPTH, depthParam[2]


def rvl_encode(image: np.ndarray) -> bytes:
    """uint32 cols, rows, then the RVL words of a uint16 image (Wilson 2017)."""
    nibbles: list[int] = []

    def vle(value: int) -> None:
        while True:  # 3 bits a nibble, least significant first; bit 3: more follow
            low, value = value & 7, value >> 3
            nibbles.append(low | 8 if value else low)
            if not value:
                return

    pixels = [int(v) for v in image.reshape(-1)]
    i, previous = 0, 0
    while i < len(pixels):
        zeros = 0
        while i < len(pixels) and pixels[i] == 0:
            zeros, i = zeros + 1, i + 1
        vle(zeros)
        run = 0
        while i + run < len(pixels) and pixels[i + run]:
            run += 1
        vle(run)
        for value in pixels[i : i + run]:
            delta = value - previous
            vle(2 * delta if delta >= 0 else -2 * delta - 1)  # zigzag
            previous = value
        i += run
    nibbles += [0] * (-len(nibbles) % 8)
    words = [
        sum(n << (28 - 4 * k) for k, n in enumerate(nibbles[j : j + 8]))
        for j in range(0, len(nibbles), 8)
    ]
    h, w = image.shape
    return struct.pack("<II", w, h) + struct.pack(f"<{len(words)}I", *words)


def png_16uc1(frame: Frame) -> tuple[str, bytes]:
    return "16UC1; compressedDepth png", config_header() + png16(frame.depth_mm)


def rvl_16uc1(frame: Frame) -> tuple[str, bytes]:
    return "16UC1; compressedDepth rvl", config_header() + rvl_encode(frame.depth_mm)


def png_32fc1(frame: Frame) -> tuple[str, bytes]:
    """The plugin's inverse-depth quantisation of metres: q = a / d + b (0: none or beyond
    depth_max)."""
    a = np.float32(Z0 * (Z0 + 1.0))
    b = np.float32(1.0 - a / np.float32(DEPTH_MAX_M))
    metres = frame.depth_mm.astype(np.float32) / np.float32(1000.0)
    with np.errstate(divide="ignore"):
        held = (frame.depth_mm > 0) & (metres < np.float32(DEPTH_MAX_M))
        q = np.where(held, a / metres + b, 0).astype(np.uint16)  # C truncation
    return "32FC1; compressedDepth png", config_header(float(a), float(b)) + png16(q)


# --- frames and bags -----------------------------------------------------------------------------
def frames(n: int = 3) -> list[Frame]:
    """Random depth with holes, a full-scale pixel and zero runs at the row ends."""
    out = []
    for f in ramp_frames(n):
        depth = f.depth_mm.copy()
        depth[0, :5] = 0
        depth[-1, -7:] = 0
        depth[1, 3] = 65535
        out.append(Frame(f.seq, f.timestamp_s, depth, f.intrinsics, accel_mps2=f.accel_mps2))
    return out


ENCODINGS: dict[str, dict[str, object]] = {
    "16UC1": {},
    "mono16": {"encoding": "mono16"},
    "png": {"compress": png_16uc1, "depth_topic": PACKED_TOPIC},
    "rvl": {"compress": rvl_16uc1, "depth_topic": PACKED_TOPIC},
}


def bag(tmp_path: Path, kind: str, name: str, fs: list[Frame], **spec: object) -> Path:
    path = tmp_path / (f"{kind}-{name}" + (".bag" if kind == "ros1" else ".mcap"))
    if kind == "ros1":
        return write_bag(path, fs, BagSpec("ros1", **spec))  # type: ignore[arg-type]
    folder = write_bag(tmp_path / f"{kind}-{name}", fs, BagSpec("mcap", **spec))  # type: ignore[arg-type]
    (storage,) = folder.glob("*.mcap")
    return storage.rename(path)  # a bare .mcap, as robots copy them


def replayed(spec: str) -> list[Frame]:
    with drivers.opened(drivers.create_driver(spec)) as driver:
        return list(drivers.iter_frames(driver))


def error(spec: str) -> RecordingError:
    with pytest.raises(RecordingError) as info:
        replayed(spec)
    assert "\n" not in str(info.value) and info.value.hint, info.value
    return info.value


# --- the same frames in every encoding -----------------------------------------------------------
@pytest.mark.parametrize("kind", ["ros1", "mcap"])
def test_every_depth_encoding_replays_bit_identical(tmp_path: Path, kind: str, caplog) -> None:
    fs = frames()
    for name, spec in ENCODINGS.items():
        path = bag(tmp_path, kind, name, fs, **spec)
        with caplog.at_level("INFO", logger="drivers.formats.rosbag"):
            got = replayed(f"replay:{path}?rate=max")  # found without ?topic=
        assert len(got) == len(fs), name
        for g, f in zip(got, fs, strict=True):
            np.testing.assert_array_equal(g.depth_mm, f.depth_mm, err_msg=name)
            assert g.depth_mm.dtype == np.uint16
    assert "mono16 images read as depth in millimetres" in caplog.text


def test_32fc1_compressed_depth_within_its_quantisation(tmp_path: Path) -> None:
    fs = frames(2)
    path = bag(tmp_path, "mcap", "inv", fs, compress=png_32fc1, depth_topic=PACKED_TOPIC)
    got = replayed(f"replay:{path}?rate=max")
    for g, f in zip(got, fs, strict=True):
        held = (f.depth_mm > 0) & (f.depth_mm < DEPTH_MAX_M * 1000)
        assert np.array_equal(g.depth_mm > 0, held)
        d = f.depth_mm[held].astype(np.float64)
        # q truncated: the decoded depth is at most d^2 / (a - d) metres further
        a = Z0 * (Z0 + 1.0)
        slack_mm = (d / 1000.0) ** 2 / (a - d / 1000.0) * 1000.0 + 1.0  # + mm rounding
        got_mm = g.depth_mm[held].astype(np.float64)
        assert np.all(got_mm - d >= -1.0) and np.all(got_mm - d <= slack_mm)


def test_raw_topic_preferred_over_its_compressed_twin_and_mono16(tmp_path: Path) -> None:
    """X beside X/compressedDepth and an infrared mono16 topic: X; mono16 alone: mono16."""
    fs = frames(2)
    spec = BagSpec(
        "ros1",
        compress=rvl_16uc1,
        depth_topic=PACKED_TOPIC,
        extra_images={DEPTH_TOPIC: "16UC1", "/camera/ir/image": "mono16"},
    )
    both = write_bag(tmp_path / "both.bag", fs, spec)
    assert DepthBag(both).probe().depth_topic == DEPTH_TOPIC
    ir = write_bag(
        tmp_path / "ir.bag", fs, BagSpec("ros1", depth_topic="/camera/ir/image", encoding="mono16")
    )
    got = replayed(f"replay:{ir}?rate=max")
    np.testing.assert_array_equal(got[1].depth_mm, fs[1].depth_mm)


def test_the_cli_gives_the_same_scans_for_every_encoding(tmp_path: Path) -> None:
    fs = frames()
    outputs = {}
    for kind, name in (("ros1", "16UC1"), ("mcap", "mono16"), ("ros1", "png"), ("mcap", "rvl")):
        path = bag(tmp_path, kind, name, fs, **ENCODINGS[name])
        p = depthnav("run", "--device", f"replay:{path}", "--sink", "stdout", "--max-frames", "3")
        assert p.returncode == 0, p.stderr
        lines = [json.loads(line) for line in p.stdout.splitlines()]
        assert len(lines) == 3, p.stdout
        outputs[name] = [(x["t_s"], x["scan"], x["cliff"]) for x in lines]
    first = outputs["16UC1"]
    assert all(o == first for o in outputs.values()), list(outputs)


# --- hostile and odd bags ------------------------------------------------------------------------
def _hostile_png_bomb() -> bytes:
    """A 16-bit grayscale PNG that declares 60000x60000 pixels in a few hundred bytes."""
    ihdr = struct.pack(">IIBBBBB", 60000, 60000, 16, 0, 0, 0, 0)

    def chunk(kind: bytes, body: bytes) -> bytes:
        crc = zlib.crc32(kind + body)
        return struct.pack(">I", len(body)) + kind + body + struct.pack(">I", crc)

    idat = zlib.compress(b"\0" * 200_000, 9)  # the start of a zero image, highly compressible
    return b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + chunk(b"IDAT", idat) + chunk(b"IEND", b"")


def _rgb_png(frame: Frame) -> bytes:
    out = io.BytesIO()
    Image.fromarray(np.zeros((*frame.depth_mm.shape, 3), dtype=np.uint8)).save(out, format="PNG")
    return out.getvalue()


def _png8(frame: Frame) -> bytes:
    out = io.BytesIO()
    Image.fromarray((frame.depth_mm >> 8).astype(np.uint8)).save(out, format="PNG")
    return out.getvalue()


def _rvl_claims(frame: Frame, w: int, h: int) -> bytes:
    body = rvl_encode(frame.depth_mm)
    return struct.pack("<II", w, h) + body[8:]


HOSTILE: dict[str, tuple[Callable[[Frame], tuple[str, bytes]], str]] = {
    "truncated png": (
        lambda f: ("16UC1; compressedDepth png", config_header() + png16(f.depth_mm)[:-40]),
        "PNG is damaged",
    ),
    "short header": (lambda f: ("16UC1; compressedDepth png", b"\0" * 10), "header alone"),
    "no png after the header": (
        lambda f: ("16UC1; compressedDepth png", config_header() + b"GIF89a" + b"\0" * 64),
        "is not a PNG",
    ),
    "8-bit png": (
        lambda f: ("16UC1; compressedDepth png", config_header() + _png8(f)),
        "8-bit grayscale, not 16-bit",
    ),
    "rgb png": (
        lambda f: ("16UC1; compressedDepth png", config_header() + _rgb_png(f)),
        "8-bit RGB, not 16-bit",
    ),
    "png bomb": (
        lambda f: ("16UC1; compressedDepth png", config_header() + _hostile_png_bomb()),
        "60000x60000",
    ),
    "rvl bomb": (
        lambda f: ("16UC1; compressedDepth rvl", config_header() + _rvl_claims(f, 60000, 60000)),
        "60000x60000",
    ),
    "rvl more pixels than the image": (
        lambda f: ("16UC1; compressedDepth rvl", config_header() + _rvl_claims(f, 64, 40)),
        "RVL stream claims",
    ),
    "rvl cut short": (
        lambda f: ("16UC1; compressedDepth rvl", config_header() + rvl_encode(f.depth_mm)[:200]),
        "RVL stream ends after",
    ),
    "unknown codec": (
        lambda f: ("16UC1; compressedDepth zstd", config_header() + b"\0" * 32),
        "codec 'zstd'",
    ),
    "jpeg": (lambda f: ("jpeg", config_header() + b"\0" * 32), "'jpeg' is not depth"),
}


@pytest.mark.parametrize("case", list(HOSTILE))
def test_malformed_compressed_depth_is_one_error(tmp_path: Path, case: str) -> None:
    make, expected = HOSTILE[case]
    path = bag(tmp_path, "mcap", "bad", frames(1), compress=make, depth_topic=PACKED_TOPIC)
    err = error(f"replay:{path}?rate=max&topic={PACKED_TOPIC}")
    assert expected in str(err), str(err)


def test_the_cli_says_one_line_for_a_png_bomb(tmp_path: Path) -> None:
    path = bag(
        tmp_path,
        "ros1",
        "bomb",
        frames(1),
        compress=HOSTILE["png bomb"][0],
        depth_topic=DEPTH_TOPIC,
    )
    p = depthnav("run", "--device", f"replay:{path}", "--sink", "null", "--max-frames", "1")
    assert p.returncode in (1, 2), p.stderr
    line = one_error_line(p.stderr)
    assert "60000x60000" in line and "depthnav: hint:" in p.stderr


@pytest.mark.parametrize("kind", ["ros1", "mcap"])
def test_camera_info_on_the_depth_topic_is_skipped(tmp_path: Path, kind: str) -> None:
    fs = frames(2)
    path = bag(tmp_path, kind, "info", fs, info_on_depth=True)
    for spec in (f"replay:{path}?rate=max", f"replay:{path}?rate=max&topic={DEPTH_TOPIC}"):
        got = replayed(spec)
        assert len(got) == 2
        np.testing.assert_array_equal(got[1].depth_mm, fs[1].depth_mm)


def test_a_topic_without_messages_is_named(tmp_path: Path) -> None:
    from rosbags.rosbag1 import Writer
    from rosbags.typesys import Stores, get_typestore

    ts = get_typestore(Stores.ROS1_NOETIC)
    path = tmp_path / "empty.bag"
    with Writer(path) as writer:
        writer.add_connection(DEPTH_TOPIC, "sensor_msgs/msg/Image", typestore=ts)
    err = error(f"replay:{path}?rate=max")
    assert f"{DEPTH_TOPIC} holds no message" in str(err), str(err)
    assert f"{DEPTH_TOPIC} (no messages)" in (err.hint or "")
