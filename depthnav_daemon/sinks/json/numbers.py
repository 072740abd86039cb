"""The JSON text of arrays rounded to 1 mm, written by a compiled loop (the JSON sinks' hot path).

Building the stdout/UDP line cost more than the stages it reports: two 640-bin scans went through
``np.round`` -> object array -> Python floats -> orjson, ~80 us each. The kernel here writes the
same bytes straight from the float64 array: every value is rounded as ``np.round(v, 3)`` does
(``rint(v * 1000) / 1000``) and written as orjson (and Python's ``repr``) writes that float. For
|v| < 1e12 m that float's shortest text is the decimal ``k / 1000`` itself (a decimal of at most 15
significant digits is the only one that short reading back as its double), so the kernel writes
the digits of ``k`` with the point three places from the right and the trailing zeros dropped
(``2.5``, ``12.0``, ``-0.0``). Anything outside that domain returns -1 and the caller takes the
reference path (``jsonmsg.encode_ranges`` + orjson); tests/sinks/test_json_numbers.py compares
both on random arrays, at the table's bounds and for every entry of it.

Below 100 m (nearly every range and point) the text comes from a table (:func:`_texts`): entry
``|k|`` holds the text and a comma in one 64-bit word, so a value costs a rint, a bound test and
two 8-byte stores (a '-', kept only for a negative value, then the entry); beyond, the digits of
the metres are written one by one before the fraction's entry. The infinities and NaN take the
same two stores. Stores go to unsigned indices: numba checks a signed index for wrapping, per
byte, which kept LLVM from merging a copy's bytes into one store. ~2 ns a value, against 6-9 ns
for the digit loop it replaced.

A frame's lists (its scan's ranges, the cliff's points and ranges) are written by one call
(:func:`lists_json`): each call has a cost of its own (numpy's and numba's dispatch, a few us on a
2-core machine), a good part of what writing 640 numbers costs.
"""

from __future__ import annotations

# importing the pipeline first sets numba's cache folder (pipeline/_jit.py) before numba loads
import depthnav_daemon.pipeline  # noqa: F401

# isort: split
import math
import threading

import numpy as np
from numba import njit

MAX_K = 1e15  # |value| * 1000 below this is written exactly (see above); beyond: the caller's path
CHARS_PER_VALUE = 24  # '-' + 15 digits + '.' + ',' and a pair's brackets, rounded up (room for
# the 8-byte stores past a text too: tests/sinks/test_json_numbers.py guards the buffer's end)
NOT_FINITE = -2  # _write_lists: a non-finite value in a list of pairs (the caller filters them)
TABLE_K = 100_000  # values below 100 m (|k| < TABLE_K): one entry of the table


def _packed(text: str) -> int:
    """``text`` (at most 7 bytes) as the bytes of an integer from the lowest, its length on top."""
    return int.from_bytes(text.encode(), "little") | len(text) << 56


def _texts(size: int) -> np.ndarray:
    """(size,) uint64: entry k the text of k / 1000 and a comma (``0.0,``, ``2.5,``, ``99.999,``:
    at most 7 bytes) in its bytes from the lowest, and the text's length in its top byte: written
    by one 8-byte store instead of a digit loop and the divisions of the fraction. Built from the
    texts of the metres and of the fractions (``.5,``, ``.125,``, trailing zeros dropped but one
    digit kept): no loop over every entry (~2 ms at import)."""
    count = -(-size // 1000)
    wholes = np.array([_packed(str(w)) for w in range(count)], np.uint64)
    fractions = np.array(
        [_packed("." + (f"{f:03d}".rstrip("0") or "0") + ",") for f in range(1000)], np.uint64
    )
    whole, fraction = np.repeat(wholes, 1000)[:size], np.tile(fractions, count)[:size]
    low, top = np.uint64(2**56 - 1), np.uint64(56)
    shift = (whole >> top) * np.uint64(8)  # the metres' text, then the fraction's after it
    length = (whole >> top) + (fraction >> top)
    if size and int(length.max()) > len("99.999,"):  # 7 bytes below the length's
        raise ValueError(f"a table of {size} texts: one is longer than 7 bytes (100000 fit)")
    return (whole & low) | ((fraction & low) << shift) | (length << top)


_TEXTS = _texts(TABLE_K)
# the special values' texts as the table's entries (constants to numba), an infinity's as its first
# 8 bytes (no length: always 8) and an entry of the rest
_POS_INF = int.from_bytes(b'"Infinit', "little"), _packed('y",')
_NEG_INF = int.from_bytes(b'"-Infini', "little"), _packed('ty",')
_NULL = _packed("null,")
_LOW = 2**56 - 1  # the bytes of a text below its length


_OPTIONS = {"cache": True, "nogil": True, "boundscheck": False, "error_model": "numpy"}


@njit(**_OPTIONS, inline="always")
def put_digits(q: int, out: np.ndarray, n: int) -> int:  # pragma: no cover - compiled
    """Write the decimal digits of the integer ``q`` >= 0 into ``out`` from byte ``n``; where
    they end."""
    lo = n
    while True:  # least significant first, then turned round
        out[np.uint64(n)] = 48 + q % 10
        q //= 10
        n += 1
        if q == 0:
            break
    a, b = lo, n - 1
    while a < b:
        out[np.uint64(a)], out[np.uint64(b)] = out[np.uint64(b)], out[np.uint64(a)]
        a += 1
        b -= 1
    return n


@njit(**_OPTIONS, inline="always")
def put_list(  # noqa: PLR0912 - every kind of value in the one loop LLVM sees
    values: np.ndarray, pairs: bool, texts: np.ndarray, out: np.ndarray, n: int
) -> int:  # pragma: no cover - compiled; tests/sinks/test_json_numbers.py checks
    """Write the flat array ``values`` (float32 or float64) as a JSON list into ``out`` (uint8)
    from byte ``n``; with ``pairs``, as a list of [x, y] pairs. Non-finite values are written as
    ``null``/``"Infinity"``/``"-Infinity"`` (in a flat list; pairs: see Returns). ``texts`` is
    :func:`_texts` of at least 1000 entries (an argument: a global array of 800 KB numba would
    freeze into the machine code and its cache). Inlined into each kernel that calls it.

    Every value is written with a comma after it (the table's entries end in one): the last one
    becomes the list's ``]``, and a pair's second its ``]`` before a new comma.

    Returns:
        Where the text ends (the next free byte), -1 for a value it cannot write exactly (see the
        module docstring), or NOT_FINITE for a non-finite value in a list of pairs.
    """
    table_k = texts.size
    out[np.uint64(n)] = 91  # [
    n += 1
    for i in range(values.size):
        if pairs and not i & 1:
            out[np.uint64(n)] = 91  # a pair's [
            n += 1
        x = np.float64(values[i])  # exact for float32
        k = abs(np.rint(x * 1000.0))
        minus = math.copysign(1.0, x) < 0.0
        if k < table_k:  # false for NaN and inf too
            head, skip = np.uint64(45), np.int64(minus)  # "-" (-0.0 is written "-0.0")
            text = texts[np.uint64(np.int64(k))]
        elif k == math.inf:
            if pairs:
                return NOT_FINITE
            skip = np.int64(8)  # its first 8 bytes, then the rest (the sign in the quotes)
            head = np.uint64(_NEG_INF[0] if minus else _POS_INF[0])
            text = np.uint64(_NEG_INF[1] if minus else _POS_INF[1])
        elif math.isnan(x):
            if pairs:
                return NOT_FINITE
            head, skip = np.uint64(0), np.int64(0)
            text = np.uint64(_NULL)
        elif k < MAX_K:  # 100 m and beyond: the digits of the metres, then a fraction's text
            if minus:
                out[np.uint64(n)] = 45
                n += 1
            q = np.int64(k)
            frac = q % 1000
            n = put_digits(q // 1000, out, n)
            head, skip = np.uint64(0), np.int64(0)
            text = texts[np.uint64(frac)]  # ".5," of "0.5,": its bytes moved down by one
            length = (text >> np.uint64(56)) - np.uint64(1)
            text = (text & np.uint64(_LOW)) >> np.uint64(8) | length << np.uint64(56)
        else:
            return -1
        for c in range(8):  # two 8-byte stores: the head, then the text (its top byte junk)
            out[np.uint64(n + c)] = (head >> np.uint64(8 * c)) & np.uint64(255)
        n += skip
        for c in range(8):
            out[np.uint64(n + c)] = (text >> np.uint64(8 * c)) & np.uint64(255)
        n += np.int64(text >> np.uint64(56))
        if pairs and i & 1:
            out[np.uint64(n - 1)] = 93  # the pair's ]
            out[np.uint64(n)] = 44  # ,
            n += 1
    if pairs and values.size & 1:  # an odd count: the last pair holds one value
        out[np.uint64(n - 1)] = 93
        out[np.uint64(n)] = 44
        n += 1
    n -= values.size > 0  # the last comma
    out[np.uint64(n)] = 93  # ]
    return n + 1


@njit(**_OPTIONS)
def _write_lists(
    first: np.ndarray,
    second: np.ndarray,
    third: np.ndarray,
    texts: np.ndarray,
    out: np.ndarray,
) -> tuple[int, int, int]:  # pragma: no cover - compiled; tests/sinks/test_json_numbers.py checks
    """Write three flat arrays (float32 or float64, the same type) as JSON lists into ``out``
    (uint8), one after the other, the second as [x, y] pairs (:func:`put_list`).

    Returns:
        The number of bytes written, or put_list's error (-1 or NOT_FINITE); and the offsets
        where the first and the second list end.
    """
    end_first = put_list(first, False, texts, out, 0)
    if end_first < 0:
        return end_first, 0, 0
    end_second = put_list(second, True, texts, out, end_first)
    if end_second < 0:
        return end_second, 0, 0
    n = put_list(third, False, texts, out, end_second)
    if n < 0:
        return n, 0, 0
    return n, end_first, end_second


KERNELS = [_write_lists]  # for the first run's "compiling kernels" progress (tools/warmup.py)
_F32, _F64 = np.dtype(np.float32), np.dtype(np.float64)
_EMPTY = {_F32: np.zeros(0, np.float32), _F64: np.zeros(0)}  # a list not given: "[]"


_LOCAL = threading.local()  # each thread's output buffer (the frame loop's, a sensor thread's)
MIN_BUFFER = 1 << 16  # bytes: a 640x480 frame's lists need ~36 KB


def _buffer(size: int) -> np.ndarray:
    """This thread's output buffer of at least ``size`` bytes, kept from call to call: a new ~36 KB
    array a frame cost the frame loop 1-3 % (paired blocks of frames in the loop, stdout and
    stdout + UDP). Bounded: the largest frame's lists."""
    buf: np.ndarray | None = getattr(_LOCAL, "buf", None)
    if buf is None or buf.size < size:
        buf = np.empty(max(size, MIN_BUFFER), np.uint8)
        _LOCAL.buf, _LOCAL.view = buf, memoryview(buf)  # a view made once: slices copy nothing
    return buf


def _flat(values: np.ndarray, dtype: np.dtype) -> np.ndarray:
    """``values`` as a flat, C-ordered, writable array of ``dtype`` (float32 or float64): the one
    array type the kernel is compiled for, each (a read-only one would compile anew)."""
    flags = values.flags
    if values.dtype == dtype and flags.c_contiguous and flags.writeable:
        return values if values.ndim == 1 else values.reshape(-1)
    return np.array(values, dtype=dtype, order="C").reshape(-1)


def as_flat(
    first: np.ndarray | None, second: np.ndarray | None = None, third: np.ndarray | None = None
) -> tuple[np.dtype, np.ndarray | None, np.ndarray | None, np.ndarray | None]:
    """Up to three arrays as the kernels take them: flat, C-ordered and writable, float32 when
    every one given is (the stages' ranges and points, as they are), else all float64 (the two
    types the kernels are compiled for); None stays None. Returns (dtype, first, second, third).
    """
    given = [None if a is None else np.asarray(a) for a in (first, second, third)]
    dtype = _F32 if all(a is None or a.dtype == _F32 for a in given) else _F64
    one, two, three = (None if a is None else _flat(a, dtype) for a in given)
    return dtype, one, two, three


def lists_json(
    first: np.ndarray, second: np.ndarray | None = None, third: np.ndarray | None = None
) -> tuple[bytes, bytes, bytes] | None:
    """Up to three arrays rounded to 1 mm as JSON list text, written by one kernel call (a call
    costs microseconds of its own: a frame's lists are written by one).

    Args:
        first, third: (N,) metres for flat lists (NaN -> null, +-inf -> "+-Infinity").
        second: (N, 2) metres for a list of [x, y] pairs, all finite.

    Returns:
        The lists' texts (``[]`` for one not given), or None when a value lies outside what the
        kernel writes exactly or a pair is not finite (then use the reference path).
    """
    dtype, one, two, three = as_flat(first, second, third)
    empty = _EMPTY[dtype]
    one = empty if one is None else one
    two = empty if two is None else two
    three = empty if three is None else three
    out = _buffer(CHARS_PER_VALUE * (one.size + two.size + three.size) + 12)
    n, a, b = _write_lists(one, two, three, _TEXTS, out)
    if n < 0:
        return None
    text = _LOCAL.view
    return bytes(text[:a]), bytes(text[a:b]), bytes(text[b:n])


def mm_json(values: np.ndarray, pairs: bool = False) -> bytes | None:
    """``values`` rounded to 1 mm as JSON list text (NaN -> null, +-inf -> "+-Infinity"), or None
    when a value lies outside what the kernel writes exactly (then use the reference path).

    Args:
        values: (N,) for a flat list, or (N, 2) with ``pairs`` for a list of [x, y] pairs; metres.
    """
    if not pairs:
        texts = lists_json(values)
        return None if texts is None else texts[0]
    if not np.isfinite(values).all():
        return _pairs_with_specials(values)
    texts = lists_json(np.zeros(0), values)
    return None if texts is None else texts[1]


def _pairs_with_specials(values: np.ndarray) -> bytes | None:
    """Pairs holding non-finite values: each pair a list of its own (null, "Infinity", ...)."""
    texts = [mm_json(p) for p in np.asarray(values).reshape(-1, 2)]
    if any(t is None for t in texts):
        return None
    return b"[" + b",".join(t for t in texts if t is not None) + b"]"
