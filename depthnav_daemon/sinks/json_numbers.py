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
# global arrays are constants to numba: frozen into the compiled code
_NULL = np.frombuffer(b"null", np.uint8).copy()
_POS_INF = np.frombuffer(b'"Infinity"', np.uint8).copy()
_NEG_INF = np.frombuffer(b'"-Infinity"', np.uint8).copy()


@njit(cache=True, nogil=True, boundscheck=False, error_model="numpy")
def _write_mm(  # noqa: PLR0912, PLR0915 - one function: each one more is a second of compiling
    values: np.ndarray, out: np.ndarray, pairs: bool
) -> int:  # pragma: no cover - compiled; tests/sinks/test_json_numbers.py checks its output
    """Write ``values`` (float64, flat) as a JSON list into ``out`` (uint8); ``pairs``: as a list
    of [x, y] pairs. Non-finite values are written as ``null``/``"Infinity"``/``"-Infinity"``.

    Returns:
        The number of bytes written, or -1 for a value it cannot write exactly (see the module
        docstring).
    """
    out[0] = 91  # [
    n = 1
    for i in range(values.size):
        if pairs and i % 2 == 0:
            if i:
                out[n] = 93  # ]
                out[n + 1] = 44  # ,
                n += 2
            out[n] = 91
            n += 1
        elif i:
            out[n] = 44
            n += 1
        x = values[i]
        if np.isnan(x):
            for j in range(_NULL.size):
                out[n + j] = _NULL[j]
            n += _NULL.size
            continue
        if x == np.inf:
            for j in range(_POS_INF.size):
                out[n + j] = _POS_INF[j]
            n += _POS_INF.size
            continue
        if x == -np.inf:
            for j in range(_NEG_INF.size):
                out[n + j] = _NEG_INF[j]
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
            first = n
            while q:
                out[n] = 48 + q % 10
                q //= 10
                n += 1
            a, b = first, n - 1
            while a < b:
                out[a], out[b] = out[b], out[a]
                a += 1
                b -= 1
        out[n] = 46  # .
        out[n + 1] = 48 + frac // 100
        n += 2
        tens, ones = (frac // 10) % 10, frac % 10
        if tens or ones:  # 2.5, not 2.500
            out[n] = 48 + tens
            n += 1
            if ones:
                out[n] = 48 + ones
                n += 1
    if pairs and values.size:
        out[n] = 93  # ]
        n += 1
    out[n] = 93  # ]
    return n + 1


KERNELS = [_write_mm]  # for the first run's "compiling kernels" progress (tools/warmup.py)


def mm_json(values: np.ndarray, pairs: bool = False) -> bytes | None:
    """``values`` rounded to 1 mm as JSON list text (NaN -> null, +-inf -> "+-Infinity"), or None
    when a value lies outside what the kernel writes exactly (then use the reference path).

    Args:
        values: (N,) for a flat list, or (N, 2) with ``pairs`` for a list of [x, y] pairs; metres.
    """
    flat = np.ascontiguousarray(values, dtype=np.float64).reshape(-1)
    out = np.empty(CHARS_PER_VALUE * flat.size + 4, np.uint8)
    n = _write_mm(flat, out, pairs)
    return None if n < 0 else out[:n].tobytes()
