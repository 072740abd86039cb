""".npz archives read member by member, each one's shape and size checked before it is decoded.

``np.load`` decodes a member in full before anyone can look at its shape: a 2.8 MB archive whose
``timestamp_s`` inflates to 2.4 GB took 2.4 GB. Here an archive is opened through
drivers.files (a regular file, never a FIFO or a device), its members are listed once (one name
twice, such as ``depth_mm.npy`` beside ``depth_mm``, is refused: which one np.load would read
is not the one whose size was checked), each member's ``.npy`` header is read first (shape,
dtype, order, checked against the archive's own size record), and only the bytes that header
declares are decoded. Members nobody asks for are never decompressed; object arrays are never
read (no pickles).
"""

from __future__ import annotations

import contextlib
import math
import os
import zipfile
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import IO, Any

import numpy as np
import numpy.typing as npt

from drivers.errors import RecordingError
from drivers.files import open_input
from drivers.values import short_text

MAX_HEADER_SIZE = 10_000  # np.load's limit on a .npy header, bytes


@contextlib.contextmanager
def reading(path: Path) -> Iterator[None]:
    """Turn whatever a damaged archive raises into one RecordingError line naming it."""
    try:
        yield
    except RecordingError:
        raise
    except MemoryError:
        raise RecordingError(f"{path}: too big to read into memory") from None
    except Exception as exc:
        # BadZipFile, zlib.error, EOFError, ValueError, SyntaxError, tokenize.TokenError, ...
        # (found by tests/faults/test_fuzz_inputs.py); every one means the same to the user
        reason = short_text(str(exc).splitlines()[0], 120) if str(exc) else ""
        raise RecordingError(
            f"{path}: not a readable .npz archive (corrupt or truncated: "
            f"{type(exc).__name__}{': ' + reason if reason else ''})",
            hint="re-record it or restore it from git",
        ) from exc


@dataclass(frozen=True, slots=True)
class Member:
    """One array of an archive, from its ``.npy`` header (nothing decoded).

    Attributes:
        name: the array's name ("depth_mm"), without ``.npy``.
        info: its zip entry: the one whose sizes were checked is the one that is read.
        shape, fortran_order, dtype: from the header.
        data_offset: bytes of the header, where the data starts in the member.
    """

    name: str
    info: zipfile.ZipInfo
    shape: tuple[int, ...]
    fortran_order: bool
    dtype: np.dtype[Any]
    data_offset: int

    @property
    def nbytes(self) -> int:
        """Decoded size of the array, bytes."""
        return math.prod(self.shape) * self.dtype.itemsize

    @property
    def stored_bytes(self) -> int:
        """Size of the member's data as the archive records it, bytes."""
        return self.info.file_size - self.data_offset


def read_header(fid: IO[bytes]) -> tuple[tuple[int, ...], bool, np.dtype[Any]]:
    """(shape, Fortran order, dtype) from the start of a .npy member; leaves fid after it."""
    version = np.lib.format.read_magic(fid)
    if version == (1, 0):
        shape, fortran, dtype = np.lib.format.read_array_header_1_0(fid, MAX_HEADER_SIZE)
    elif version == (2, 0):
        shape, fortran, dtype = np.lib.format.read_array_header_2_0(fid, MAX_HEADER_SIZE)
    else:
        raise ValueError(f"unsupported .npy format version {version[0]}.{version[1]}")
    if any(int(n) < 0 for n in shape):
        raise ValueError(f"negative size in shape {shape}")
    return tuple(int(n) for n in shape), bool(fortran), dtype


class Archive:
    """An open ``.npz``: ``member(name)`` reads a header, ``read(member)`` its data."""

    def __init__(self, path: Path, zf: zipfile.ZipFile) -> None:
        self.path = path
        self.zf = zf
        self.members: dict[str, zipfile.ZipInfo] = {}
        for info in zf.infolist():
            name = info.filename.removesuffix(".npy")
            seen = self.members.get(name)
            if seen is not None:
                raise RecordingError(
                    f"{path}: holds {short_text(name, 40)!r} twice ({short_text(seen.filename, 40)}"
                    f" and {short_text(info.filename, 40)}); which one to read is ambiguous",
                    hint="save the arrays again with np.savez",
                )
            self.members[name] = info

    def names(self) -> list[str]:
        """The arrays' names, for messages."""
        return list(self.members)

    def member(self, name: str) -> Member | None:
        """The header of array ``name``, or None if the archive has none."""
        info = self.members.get(name)
        if info is None:
            return None
        with self.zf.open(info) as fid:
            try:
                shape, fortran, dtype = read_header(fid)
            except ValueError as exc:
                raise RecordingError(
                    f"{self.path}: {name!r} is not a readable .npy array "
                    f"({short_text(str(exc), 80)})"
                ) from None
            offset = fid.tell()
        if dtype.hasobject:
            raise RecordingError(
                f"{self.path}: {name!r} holds Python objects; depthnav reads numbers only "
                "(pickles are never loaded)"
            )
        member = Member(name, info, shape, fortran, dtype, offset)
        if member.stored_bytes < member.nbytes:  # the header claims more than the archive holds
            raise RecordingError(
                f"{self.path}: {name!r} holds {max(member.stored_bytes, 0)} bytes, too few for "
                f"{dtype} {shape} (truncated or damaged)",
                hint="re-record it or restore it from git",
            )
        return member

    @contextlib.contextmanager
    def data(self, member: Member) -> Iterator[IO[bytes]]:
        """The member's stream, positioned at its first data byte."""
        with self.zf.open(member.info) as fid:
            if read_header(fid) != (member.shape, member.fortran_order, member.dtype):
                raise RecordingError(f"{self.path}: {member.name!r} changed while being read")
            yield fid

    def read(self, member: Member) -> npt.NDArray[Any]:
        """Decode exactly ``member.nbytes`` bytes of the member (a writable array)."""
        buffer = bytearray(member.nbytes)
        with self.data(member) as fid:
            view = memoryview(buffer)
            while view:
                got = fid.readinto(view)
                if not got:
                    raise EOFError(f"{member.name!r} ends early")
                view = view[got:]
            if member.stored_bytes == member.nbytes:
                fid.read(1)  # at the end of the member, where zipfile checks its CRC-32
        order = "F" if member.fortran_order else "C"
        return np.frombuffer(buffer, dtype=member.dtype).reshape(member.shape, order=order)


@contextlib.contextmanager
def open_archive(path: str | os.PathLike[str]) -> Iterator[Archive]:
    """Open an ``.npz`` (a regular file) for reading member by member.

    Raises:
        RecordingError: missing, not a regular file, not a zip archive, a name twice; errors
            inside the ``with`` block are turned into one line as well.
    """
    where = Path(path)
    with (
        reading(where),
        open_input(where, what=".npz archive") as fh,
        zipfile.ZipFile(fh) as zf,
    ):
        yield Archive(where, zf)


def is_numeric(member: Member) -> bool:
    """True for integer and real floating-point arrays (not bool, complex, text or records)."""
    return member.dtype.kind in "iuf" and member.dtype.fields is None
