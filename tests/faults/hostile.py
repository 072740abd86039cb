"""Builders of hostile inputs for the fault tests: zip bombs, .npz archives written member by
member (duplicates, lying headers), PNGs of any claimed size, special files in place of inputs,
billion-laughs YAML, deep nesting, numbers no reader should choke on.

Bombs are built without compressing their zeros: a deflate block of 1 MiB of zeros ended by a
full flush holds no reference to what came before, so it can be repeated; a 512 MiB member takes
a millisecond to build and 0.5 MiB on disk.
"""

from __future__ import annotations

import io
import os
import struct
import zlib
from dataclasses import dataclass
from pathlib import Path

import numpy as np

MIB = 1 << 20
_ZEROS = bytes(MIB)


def _zero_block() -> bytes:
    c = zlib.compressobj(9, zlib.DEFLATED, -15)
    return c.compress(_ZEROS) + c.flush(zlib.Z_FULL_FLUSH)


_ZERO_BLOCK = _zero_block()
_FINAL_BLOCK = zlib.compressobj(9, zlib.DEFLATED, -15).flush()  # an empty final block


@dataclass(frozen=True)
class Deflated:
    """Raw deflate data of ``prefix`` + ``zeros`` zero bytes, with the zip fields it needs."""

    data: bytes
    crc: int
    size: int  # uncompressed


def deflate_zeros(prefix: bytes, zeros: int) -> Deflated:
    """``prefix`` followed by ``zeros`` zero bytes (rounded down to whole MiB past the prefix's
    own padding), deflated without compressing the zeros."""
    head = zlib.compressobj(9, zlib.DEFLATED, -15)
    pad = zeros % MIB
    data = [head.compress(prefix + bytes(pad)) + head.flush(zlib.Z_FULL_FLUSH)]
    crc = zlib.crc32(prefix + bytes(pad))
    for _ in range(zeros // MIB):
        data.append(_ZERO_BLOCK)
        crc = zlib.crc32(_ZEROS, crc)
    data.append(_FINAL_BLOCK)
    return Deflated(b"".join(data), crc & 0xFFFFFFFF, len(prefix) + zeros)


def deflate(raw: bytes) -> Deflated:
    c = zlib.compressobj(6, zlib.DEFLATED, -15)
    return Deflated(c.compress(raw) + c.flush(), zlib.crc32(raw) & 0xFFFFFFFF, len(raw))


def npy_header(dtype: str, shape: tuple[int, ...], fortran: bool = False) -> bytes:
    out = io.BytesIO()
    np.lib.format.write_array_header_1_0(
        out, {"descr": np.dtype(dtype).str, "fortran_order": fortran, "shape": shape}
    )
    return out.getvalue()


def npy_bytes(array: np.ndarray) -> bytes:
    out = io.BytesIO()
    np.lib.format.write_array(out, array, allow_pickle=False)
    return out.getvalue()


def bomb(dtype: str, shape: tuple[int, ...]) -> Deflated:
    """A .npy member whose header and data are true to each other: all zeros, tiny deflated."""
    nbytes = int(np.prod(shape, dtype=np.int64)) * np.dtype(dtype).itemsize
    return deflate_zeros(npy_header(dtype, shape), nbytes)


def write_zip(path: Path, members: list[tuple[str, Deflated]]) -> None:
    """A zip archive (deflate, no zip64) of the given members, names repeated as given."""
    local, central = io.BytesIO(), io.BytesIO()
    for name, m in members:
        raw_name = name.encode()
        offset = local.tell()
        fields = (20, 0, 8, 0, 0x21, m.crc, len(m.data), m.size, len(raw_name))
        local.write(struct.pack("<4sHHHHHIIIHH", b"PK\x03\x04", *fields, 0))
        local.write(raw_name + m.data)
        central.write(
            struct.pack(
                "<4sHHHHHHIIIHHHHHII",
                b"PK\x01\x02",
                20,
                *fields,
                0,
                0,
                0,
                0,
                0,
                offset,
            )
            + raw_name
        )
    count = len(members)
    end = struct.pack(
        "<4sHHHHIIH", b"PK\x05\x06", 0, 0, count, count, central.tell(), local.tell(), 0
    )
    path.write_bytes(local.getvalue() + central.getvalue() + end)


def npz(path: Path, members: dict[str, np.ndarray | Deflated] | list) -> Path:
    """An .npz of real arrays and/or prepared (bomb) members; a list keeps repeated names."""
    items = members.items() if isinstance(members, dict) else members
    built = []
    for name, value in items:
        member = value if isinstance(value, Deflated) else deflate(npy_bytes(value))
        built.append((name if "." in name or name == "depth_mm" else name + ".npy", member))
    write_zip(path, built)
    return path


def valid_arrays(n: int = 3, height: int = 48, width: int = 64) -> dict[str, np.ndarray]:
    """The arrays of a small valid bare .npz recording."""
    rng = np.random.default_rng(1)
    return {
        "depth_mm.npy": rng.integers(500, 4000, (n, height, width), dtype=np.uint16),
        "intrinsics": np.array([60.0, 60.0, (width - 1) / 2, (height - 1) / 2]),
        "timestamp_s": np.arange(n) / 30.0,
        "accel_mps2": np.tile([0.0, -9.7, -1.4], (n, 1)),
    }


# --- PNGs of any claimed size ------------------------------------------------------------------
def _chunk(kind: bytes, data: bytes) -> bytes:
    return (
        struct.pack(">I", len(data))
        + kind
        + data
        + struct.pack(">I", zlib.crc32(kind + data) & 0xFFFFFFFF)
    )


def png_of_zeros(path: Path, width: int, height: int) -> Path:
    """A valid 16-bit greyscale PNG of ``width`` x ``height`` zeros (a few hundred KiB for any
    size: its zlib stream is built from repeated zero blocks)."""
    raw = height * (1 + 2 * width)  # a filter byte and two bytes a pixel, each row
    body = deflate_zeros(b"", raw)
    adler = 1
    for _ in range(raw // MIB):
        adler = zlib.adler32(_ZEROS, adler)
    adler = zlib.adler32(bytes(raw % MIB), adler)
    stream = b"\x78\xda" + body.data + struct.pack(">I", adler & 0xFFFFFFFF)
    ihdr = struct.pack(">IIBBBBB", width, height, 16, 0, 0, 0, 0)
    chunks = _chunk(b"IHDR", ihdr) + _chunk(b"IDAT", stream) + _chunk(b"IEND", b"")
    path.write_bytes(b"\x89PNG\r\n\x1a\n" + chunks)
    return path


def png_header_only(path: Path, width: int, height: int, tail: bytes = b"") -> Path:
    """A PNG signature and IHDR claiming ``width`` x ``height``, then ``tail`` (no image data)."""
    ihdr = struct.pack(">IIBBBBB", width, height, 16, 0, 0, 0, 0)
    path.write_bytes(b"\x89PNG\r\n\x1a\n" + _chunk(b"IHDR", ihdr) + tail)
    return path


# --- special files in place of an input --------------------------------------------------------
SPECIAL_KINDS = ("fifo", "folder", "dev_zero", "dev_urandom", "dangling", "loop")


def make_special(path: Path, kind: str) -> None:
    """Put a FIFO, a folder, a symlink to /dev/zero or /dev/urandom, a dangling symlink or a
    symlink loop where a file belongs (replacing whatever is there)."""
    if path.is_symlink() or path.is_file():
        path.unlink()
    elif path.is_dir():
        import shutil

        shutil.rmtree(path)
    if kind == "fifo":
        os.mkfifo(path)
    elif kind == "folder":
        path.mkdir()
    elif kind == "dev_zero":
        path.symlink_to("/dev/zero")
    elif kind == "dev_urandom":
        path.symlink_to("/dev/urandom")
    elif kind == "dangling":
        path.symlink_to(path.with_name("nowhere"))
    elif kind == "loop":
        path.symlink_to(path.name)
    else:
        raise ValueError(kind)


# --- text -------------------------------------------------------------------------------------
def billion_laughs(levels: int = 9, width: int = 9, key: str = "range_min") -> str:
    """A YAML document whose last key expands to ``width ** levels`` strings."""
    lines = [f"l0: &l0 [{', '.join(['lol'] * width)}]"]
    for i in range(1, levels):
        lines.append(f"l{i}: &l{i} [{', '.join([f'*l{i - 1}'] * width)}]")
    lines.append(f"{key}: *l{levels - 1}")
    return "\n".join(lines) + "\n"


def nested(depth: int, kind: str = "[") -> str:
    """A TOML/YAML flow value nested ``depth`` deep: ``[[[...]]]`` or ``{a={a=...}}``."""
    if kind == "[":
        return "[" * depth + "]" * depth
    return "{a = " * depth + "1" + "}" * depth


HOSTILE_NUMBERS = (
    "9" * 400,  # an integer past float range
    "9" * 5000,  # past Python's 4300-digit int() limit
    "-" + "9" * 400,
    "1e400",
    "-1e400",
    "inf",
    "-inf",
    "nan",
    "5e-324",
    "1" + "0" * 308 + ".0",
    "0x7fffffffffffffffffff",
)
# what Python's int()/float() read as numbers but depthnav must not: Arabic-Indic and full-width
# digits, a superscript, underscores; and near-numbers
NOT_ASCII_NUMBERS = (
    "\u0665",  # ARABIC-INDIC DIGIT FIVE
    "5\u00b2",  # 5 SUPERSCRIPT TWO
    "1_000",
    "\uff11\uff12",  # FULLWIDTH 12
    "\u0661e\u0663",
    "0x10",
    "1e",
    ".",
    "+-1",
)


# --- guards for in-process fuzzing --------------------------------------------------------------
def _status_kb(field: str) -> int:
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith(field + ":"):
            return int(line.split()[1])
    return 0


class PeakMemory:
    """The growth of this process's peak resident memory (VmHWM) over a block, in MB.

    The kernel's peak is reset at the start (``/proc/self/clear_refs``, Linux >= 4.0); where
    that is not allowed, ``growth_mb`` stays None and callers skip the check.
    """

    def __init__(self) -> None:
        self.growth_mb: float | None = None
        self._start_kb = 0

    def __enter__(self) -> PeakMemory:
        try:
            Path("/proc/self/clear_refs").write_text("5")
        except OSError:
            self._start_kb = -1
            return self
        self._start_kb = _status_kb("VmRSS")
        return self

    def __exit__(self, *exc: object) -> None:
        if self._start_kb >= 0:
            self.growth_mb = (_status_kb("VmHWM") - self._start_kb) / 1024


class Watchdog:
    """Interrupts the main thread after ``seconds`` (a blocking open() or read() included) with
    TimeoutError, and caps its address space at ``address_space_mb`` more than it has, so a
    reader that hangs or reads /dev/zero to the end fails its case instead of the machine.

    A thread sends SIGUSR1 (pytest-timeout owns SIGALRM); the limit is RLIMIT_AS's soft value,
    restored at the end.
    """

    def __init__(self, seconds: float = 20.0, address_space_mb: int = 4096) -> None:
        self.seconds = seconds
        self.extra = address_space_mb << 20

    def __enter__(self) -> Watchdog:
        import resource
        import signal
        import threading

        def interrupt(_signum: int, _frame: object) -> None:
            raise TimeoutError(f"still reading after {self.seconds} s (a hang)")

        self._old_handler = signal.signal(signal.SIGUSR1, interrupt)
        main = threading.get_ident()
        self._timer = threading.Timer(
            self.seconds, lambda: signal.pthread_kill(main, signal.SIGUSR1)
        )
        self._timer.start()
        self._old_limit = resource.getrlimit(resource.RLIMIT_AS)
        size = _status_kb("VmSize") * 1024 + self.extra
        hard = self._old_limit[1]
        if hard == resource.RLIM_INFINITY or size < hard:
            resource.setrlimit(resource.RLIMIT_AS, (size, hard))
        return self

    def __exit__(self, *exc: object) -> None:
        import resource
        import signal

        self._timer.cancel()
        resource.setrlimit(resource.RLIMIT_AS, self._old_limit)
        signal.signal(signal.SIGUSR1, self._old_handler)


# --- ROS bags: MCAP built record by record, bombs, lying sizes, hostile metadata ------
MCAP_MAGIC = b"\x89MCAP0\r\n"
BAG_DEPTH_TOPIC = "/camera/depth/image_raw"
_BOMB_FRAME = 64 * MIB  # one compressed frame of zeros; a bomb repeats it (frames concatenate)


def _mcap_record(op: int, body: bytes) -> bytes:
    return bytes([op]) + struct.pack("<Q", len(body)) + body


def _mcap_str(text: str) -> bytes:
    raw = text.encode()
    return struct.pack("<I", len(raw)) + raw


def zeros_compressed(codec: str, size: int) -> bytes:
    """``size`` zero bytes (a multiple of 64 MiB, or less) as concatenated ``codec`` frames
    (zstd, lz4 or bz2): 4 GiB of zstd is about 130 KB, built in a few milliseconds."""
    import bz2

    import lz4.frame
    from backports import zstd

    one = min(size, _BOMB_FRAME)
    compress = {"zstd": zstd.compress, "lz4": lz4.frame.compress, "bz2": bz2.compress}[codec]
    frame = compress(bytes(one))
    return frame * (size // one)


def mcap_chunk(compression: str, data: bytes, declared: int) -> bytes:
    """An MCAP chunk record holding ``data`` (already compressed) that says it inflates to
    ``declared`` bytes (true or not), crc 0 (not checked)."""
    body = struct.pack("<QQQI", 0, 0, declared, 0) + _mcap_str(compression)
    return _mcap_record(6, body + struct.pack("<Q", len(data)) + data)


def mcap_file(path: Path, records: list[bytes]) -> Path:
    """A ROS 2 MCAP with one Image channel on BAG_DEPTH_TOPIC, ``records`` as its data, no
    summary (the reader scans the data section), a whole footer."""
    header = _mcap_record(1, _mcap_str("ros2") + _mcap_str("depthnav hostile"))
    schema = _mcap_record(
        3,
        struct.pack("<H", 1) + _mcap_str("sensor_msgs/msg/Image") + _mcap_str("ros2msg")
        + struct.pack("<I", 0),
    )  # fmt: skip
    channel = _mcap_record(
        4, struct.pack("<HH", 1, 1) + _mcap_str(BAG_DEPTH_TOPIC) + _mcap_str("cdr")
        + struct.pack("<I", 0),
    )  # fmt: skip
    tail = _mcap_record(0x0F, struct.pack("<I", 0)) + _mcap_record(2, struct.pack("<QQI", 0, 0, 0))
    path.write_bytes(MCAP_MAGIC + header + schema + channel + b"".join(records) + tail + MCAP_MAGIC)
    return path


BAG_BOMBS = {  # name -> (codec, bytes it inflates to, bytes it declares)
    "zstd 4 GiB declared": ("zstd", 4 << 30, 4 << 30),
    "zstd 4 GiB declared as 1000 B": ("zstd", 4 << 30, 1000),
    "lz4 512 MiB declared as 1000 B": ("lz4", 512 * MIB, 1000),
    "zstd 256 MiB declared as 64 MiB": ("zstd", 256 * MIB, 64 * MIB),
}


def mcap_bomb(path: Path, name: str) -> Path:
    """An MCAP whose one chunk is the BAG_BOMBS entry ``name``."""
    codec, size, declared = BAG_BOMBS[name]
    return mcap_file(path, [mcap_chunk(codec, zeros_compressed(codec, size), declared)])


def ros1_chunk_size_lie(bag: Path, declared: int) -> Path:
    """Rewrite the ``size`` field of every chunk header of a ROS 1 bag in place (same length):
    the chunks then inflate to more (or less) than they declare."""
    data = bytearray(bag.read_bytes())
    key = b"size="
    at = 0
    while (at := data.find(key, at)) >= 0:
        # a chunk header's fields: <len u32>size=<u32>; the op field sits in the same header
        head_start = data.rfind(b"op=\x05", max(0, at - 64), at)
        if head_start >= 0:
            data[at + len(key) : at + len(key) + 4] = struct.pack("<I", declared)
        at += len(key)
    bag.write_bytes(bytes(data))
    return bag


def bag_metadata(folder: Path, data: bytes) -> Path:
    """A ROS 2 bag folder whose metadata.yaml holds ``data`` (and nothing else)."""
    folder.mkdir(parents=True, exist_ok=True)
    (folder / "metadata.yaml").write_bytes(data)
    return folder


HOSTILE_BAG_METADATA = {  # name -> metadata.yaml bytes (each refused in one line, at once)
    "a 2 MB comment line": b"# " + b"x" * (2 * MIB) + b"\nrosbag2_bagfile_information: {}\n",
    "nested 5000 deep": f"rosbag2_bagfile_information: {nested(5000)}\n".encode(),
    "billion laughs": billion_laughs(9, 9, key="rosbag2_bagfile_information").encode(),
    "a list, not a mapping": b"- 1\n- 2\n",
    "UTF-16": "rosbag2_bagfile_information: {}\n".encode("utf-16"),
}


# --- names that reach log lines, outputs that are not files -----------------
HOSTILE_NAMES = {  # name -> a [[sensor]] name no log line may carry raw or whole
    "newline": "front\nERROR: forged line",
    "NUL": "front\x00rear",
    "ESC": "front\x1b[31mred\x1b[0m",
    "10 KB": "s" * 10_000,
    "bidi override": "front\u202erear",
    "bell and backspace": "front\x07\x08",
}
OUTPUT_KINDS = ("fifo", "folder", "dev_null", "dev_full", "dev_zero", "long name", "long path")


def make_output(folder: Path, kind: str, suffix: str = ".png") -> Path:
    """Where a figure (or any output) is asked to go: a FIFO, a folder, a symlink to a device, a
    name of 300 bytes or a path of 5000, each named with ``suffix``; returns the path to give."""
    if kind == "long name":
        return folder / ("n" * 300 + suffix)
    if kind == "long path":
        return folder / "/".join(["d" * 200] * 25) / f"x{suffix}"
    path = folder / f"{kind}{suffix}"
    devices = {"dev_null": "/dev/null", "dev_full": "/dev/full", "dev_zero": "/dev/zero"}
    if kind in devices:
        path.symlink_to(devices[kind])
    elif kind in ("fifo", "folder"):
        make_special(path, kind)
    else:
        raise ValueError(kind)
    return path
