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
both on random arrays.

A frame's lists (its scan's ranges, the cliff's points and ranges) are written by one call
(:func:`lists_json`): each call has a cost of its own (numpy's and numba's dispatch, a few us on a
2-core machine), a good part of what writing 640 numbers costs.
"""

from __future__ import annotations

# importing the pipeline first sets numba's cache folder (pipeline/_jit.py) before numba loads
import depthnav_daemon.pipeline  # noqa: F401

# isort: split
import math

import numpy as np
from numba import njit

MAX_K = 1e15  # |value| * 1000 below this is written exactly (see above); beyond: the caller's path
CHARS_PER_VALUE = 24  # '-' + 15 digits + '.' + ',' and a pair's brackets, rounded up
NOT_FINITE = -2  # _write_lists: a non-finite value in a list of pairs (the caller filters them)
# global arrays are constants to numba: frozen into the compiled code
_NULL = np.frombuffer(b"null", np.uint8).copy()
_POS_INF = np.frombuffer(b'"Infinity"', np.uint8).copy()
_NEG_INF = np.frombuffer(b'"-Infinity"', np.uint8).copy()


def _fractions() -> np.ndarray:
    """(1000, 4) uint8: the digits after the point of k / 1000 for k % 1000 = 0..999, trailing
    zeros dropped but one digit kept (``.5``, ``.0``, ``.125``), and their count in column 3:
    one table read instead of three divisions and two branches per value."""
    out = np.zeros((1000, 4), np.uint8)
    for f in range(1000):
        text = f"{f:03d}".rstrip("0") or "0"
        out[f, : len(text)] = np.frombuffer(text.encode(), np.uint8)
        out[f, 3] = len(text)
    return out


_FRACTIONS = _fractions()


@njit(cache=True, nogil=True, boundscheck=False, error_model="numpy")
def _write_lists(  # noqa: PLR0912, PLR0915 - one function: each one more is a second of compiling
    first: np.ndarray,
    second: np.ndarray,
    third: np.ndarray,
    pairs_second: bool,
    out: np.ndarray,
    ends: np.ndarray,
) -> int:  # pragma: no cover - compiled; tests/sinks/test_json_numbers.py checks its output
    """Write three flat arrays (float32 or float64, the same type) as JSON lists into ``out``
    (uint8), one after the other, the second as [x, y] pairs when ``pairs_second``; ``ends[s]``
    gets the offset where list ``s`` ends. Non-finite values are written as
    ``null``/``"Infinity"``/``"-Infinity"`` (in a flat list; pairs: see Returns).

    Returns:
        The number of bytes written, -1 for a value it cannot write exactly (see the module
        docstring), or NOT_FINITE for a non-finite value in a list of pairs.
    """
    n = 0
    for s in range(3):
        values = first if s == 0 else (second if s == 1 else third)
        pairs = pairs_second and s == 1
        start, stop = 0, values.size
        out[n] = 91  # [
        n += 1
        for i in range(start, stop):
            j = i - start
            if pairs and j % 2 == 0:
                if j:
                    out[n] = 93  # ]
                    out[n + 1] = 44  # ,
                    n += 2
                out[n] = 91
                n += 1
            elif j:
                out[n] = 44
                n += 1
            x = np.float64(values[i])  # exact for float32
            if not np.isfinite(x):
                if pairs:
                    return NOT_FINITE
                if np.isnan(x):
                    for c in range(_NULL.size):
                        out[n + c] = _NULL[c]
                    n += _NULL.size
                elif x > 0:
                    for c in range(_POS_INF.size):
                        out[n + c] = _POS_INF[c]
                    n += _POS_INF.size
                else:
                    for c in range(_NEG_INF.size):
                        out[n + c] = _NEG_INF[c]
                    n += _NEG_INF.size
                continue
            k = np.rint(x * 1000.0)
            if not (-MAX_K < k < MAX_K):
                return -1
            if k < 0.0 or (k == 0.0 and math.copysign(1.0, k) < 0.0):  # -0.0 is written "-0.0"
                out[n] = 45  # -
                n += 1
                k = -k
            q = np.int64(k)
            frac = q % 1000
            q //= 1000
            if q < 10:  # noqa: PLR2004 - ranges: one digit of metres, mostly
                out[n] = 48 + q
                n += 1
            else:  # the digits least significant first, then turned round
                lo = n
                while q:
                    out[n] = 48 + q % 10
                    q //= 10
                    n += 1
                a, b = lo, n - 1
                while a < b:
                    out[a], out[b] = out[b], out[a]
                    a += 1
                    b -= 1
            out[n] = 46  # .
            out[n + 1] = _FRACTIONS[frac, 0]
            out[n + 2] = _FRACTIONS[frac, 1]
            out[n + 3] = _FRACTIONS[frac, 2]
            n += 1 + _FRACTIONS[frac, 3]  # 2.5, not 2.500
        if pairs and stop > start:
            out[n] = 93  # ]
            n += 1
        out[n] = 93  # ]
        n += 1
        ends[s] = n
    return n


KERNELS = [_write_lists]  # for the first run's "compiling kernels" progress (tools/warmup.py)
_EMPTY = {np.dtype(np.float32): np.zeros(0, np.float32), np.dtype(np.float64): np.zeros(0)}


def _flat(values: np.ndarray, dtype: np.dtype) -> np.ndarray:
    """``values`` as a flat, C-ordered, writable array of ``dtype`` (float32 or float64): the one
    array type the kernel is compiled for, each (a read-only one would compile anew)."""
    if values.dtype == dtype and values.flags.c_contiguous and values.flags.writeable:
        return values.reshape(-1)
    return np.array(values, dtype=dtype, order="C").reshape(-1)


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
    arrays = [np.asarray(a) for a in (first, second, third) if a is not None]
    # float32 arrays (the stages' ranges and points) as they are, anything else as float64
    dtype = np.dtype(np.float32)
    if any(a.dtype != dtype for a in arrays):
        dtype = np.dtype(np.float64)
    empty = _EMPTY[dtype]
    flat = [empty if a is None else _flat(np.asarray(a), dtype) for a in (first, second, third)]
    size = flat[0].size + flat[1].size + flat[2].size
    out = np.empty(CHARS_PER_VALUE * size + 12, np.uint8)
    ends = np.empty(3, np.int64)
    n = _write_lists(flat[0], flat[1], flat[2], True, out, ends)
    if n < 0:
        return None
    text = out[:n].tobytes()
    a, b = int(ends[0]), int(ends[1])
    return text[:a], text[a:b], text[b:]


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
