"""A whole JSON line written by one compiled call: a template's text with its numbers filled in.

In the frame loop a line's small parts (four numbers rounded by Python's ``round()``, two small
dicts for orjson, the pieces joined) cost as much as writing its 1500 numbers (paired blocks of
frames: each microsecond of Python here costs the loop about one and a half, as it also pushes the
stages' data out of the caches). So the line's text is given as a template, the static text (keys,
the scan heads, the pose and trust objects: made once, kept) with a control byte where a number
goes, and :func:`_write_template` writes it in one call, numbers and all.

The control bytes cannot occur in JSON text otherwise (orjson escapes them inside strings):

- FLAT, PAIRS: the next of the three arrays, as json_numbers.put_list writes it (a flat list;
  a list of [x, y] pairs);
- SECONDS: the next value, as orjson writes Python's ``round(value, 6)`` (``null`` if not
  finite): see :func:`_put_seconds`;
- INTEGER: the next value, an integer (float64: exact below 2**53).

A value outside what the kernel writes exactly makes it return -1: the caller then takes the
reference path (the message's dicts and orjson). tests/sinks/test_json_template.py compares the
seconds with ``orjson.dumps(round(v, 6))`` on random values, ties and the domain's bounds.
"""

from __future__ import annotations

# importing json_numbers first sets numba's cache folder (pipeline/_jit.py) before numba loads
from depthnav_daemon.sinks.json.numbers import (
    _EMPTY,
    _F32,
    _F64,
    _LOCAL,
    _OPTIONS,
    _TEXTS,
    CHARS_PER_VALUE,
    _buffer,
    as_flat,
    put_digits,
    put_list,
)

# isort: split
import array
import math

import numpy as np
from numba import njit

FLAT, PAIRS, SECONDS, INTEGER = b"\x01", b"\x02", b"\x03", b"\x04"
# |value| below this is rounded exactly (value * 1e6 stays below 2**52, see _micros) and its
# text is the decimal of the rounded microseconds (its shortest text: the doubles there lie closer
# together than 1e-6): UNIX times until 2106
MAX_SECONDS = 2.0**32
MAX_INTEGER = 2.0**53
CHARS_PER_SCALAR = 24  # '-' + 10 + '.' + 6 digits, or 'null', and room for nothing else


@njit(**_OPTIONS, inline="always")
def _micros(x: float) -> int:  # pragma: no cover - compiled
    """Python's ``round(x, 6) * 1e6`` for finite |x| < MAX_SECONDS: the exact value x * 10**6
    rounded to the nearest integer, ties to even (CPython rounds the exact binary value).

    p = x * 1e6 is rounded; Dekker's product gives its error e exactly (1e6 has 14 significant
    bits, so splitting x in halves of 26 bits makes every partial product exact): x * 10**6 = p +
    e. From k0 = rint(p) the answer moves by one only where d = p - k0 (exact) and e together pass
    a half: |e| <= ulp(p) / 2 <= 1/4 here (p < 2**52), so that needs |d| >= 1/4, where 1/2 - |d|
    is exact (Sterbenz) and the comparison too. An exact tie (x an odd multiple of 1/128, the only
    doubles at one) has p exact and e = 0: rint rounds it to even, as round() does.
    """
    p = x * 1e6
    c = 134217729.0 * x  # 2**27 + 1: Veltkamp's split
    hi = c - (c - x)
    lo = x - hi
    e = (hi * 1e6 - p) + lo * 1e6
    k0 = np.rint(p)
    d = p - k0
    k = np.int64(k0)
    if d > 0.0 and e > 0.5 - d:
        k += 1
    elif d < 0.0 and e < -0.5 - d:
        k -= 1
    return k


@njit(**_OPTIONS, inline="always")
def _put_seconds(x: float, out: np.ndarray, n: int) -> int:  # pragma: no cover - compiled
    """Write ``round(x, 6)`` as orjson writes it (``null`` if x is not finite) from ``n``; where
    it ends, or -1 beyond MAX_SECONDS.

    The double nearest k / 10**6 (k = :func:`_micros`) is what ``round()`` returns; orjson writes
    its shortest digits, which are k's with the trailing zeros dropped, fixed from 1e-5 up
    (``0.000012``, ``1796200926.69914``) and as ``3e-6`` below; 0 as ``0.0`` or ``-0.0``.
    """
    if not x - x == 0.0:  # inf or NaN
        out[np.uint64(n)] = 110  # null
        out[np.uint64(n + 1)] = 117
        out[np.uint64(n + 2)] = 108
        out[np.uint64(n + 3)] = 108
        return n + 4
    if abs(x) >= MAX_SECONDS:
        return -1
    k = _micros(x)
    if math.copysign(1.0, x) < 0.0:
        out[np.uint64(n)] = 45  # '-' (round() keeps the sign of a value rounded to zero)
        n += 1
    k = abs(k)
    if 0 < k < 10:  # noqa: PLR2004 - 1e-6 .. 9e-6: orjson writes these with an exponent
        out[np.uint64(n)] = 48 + k
        out[np.uint64(n + 1)] = 101  # e
        out[np.uint64(n + 2)] = 45  # -
        out[np.uint64(n + 3)] = 54  # 6
        return n + 4
    n = put_digits(k // 1000000, out, n)
    out[np.uint64(n)] = 46  # .
    frac = k % 1000000
    if frac == 0:
        out[np.uint64(n + 1)] = 48
        return n + 2
    width = 6
    while frac % 10 == 0:
        frac //= 10
        width -= 1
    for i in range(width):  # the fraction's digits, leading zeros included
        out[np.uint64(n + width - i)] = 48 + frac % 10
        frac //= 10
    return n + width + 1


@njit(**_OPTIONS, inline="always")
def _put_integer(x: float, out: np.ndarray, n: int) -> int:  # pragma: no cover - compiled
    """Write the integer ``x`` (a float64, |x| < MAX_INTEGER) from ``n``; where it ends, or -1."""
    if not abs(x) < MAX_INTEGER or x != np.floor(x):
        return -1
    if x < 0.0:
        out[np.uint64(n)] = 45
        n += 1
    return put_digits(np.int64(abs(x)), out, n)


@njit(**_OPTIONS)
def _write_template(
    template: bytes,
    first: np.ndarray,
    pairs: np.ndarray,
    third: np.ndarray,
    values: np.ndarray,
    texts: np.ndarray,
    out: np.ndarray,
) -> int:  # pragma: no cover - compiled; tests/sinks/test_json_template.py checks
    """Copy ``template`` into ``out``, each control byte replaced by what it stands for (see the
    module docstring): the lists ``first``, ``pairs`` ((N, 2)) and ``third`` (float32 or
    float64, one type) in turn, ``values`` (float64) in turn. Returns the bytes written, or < 0
    for what cannot be written exactly."""
    second = pairs.reshape(pairs.size)
    n = 0
    lists = 0
    v = 0
    for j in range(len(template)):
        ch = template[j]
        if ch > 4:  # noqa: PLR2004 - text
            out[np.uint64(n)] = ch
            n += 1
            continue
        if ch <= 2:  # noqa: PLR2004 - FLAT or PAIRS
            values_of = first if lists == 0 else (second if lists == 1 else third)
            # a constant ``pairs`` in each inlined copy: LLVM drops the pair tests from the
            # flat lists' loop (11 of its ~33 instructions a value)
            if ch == 2:  # noqa: PLR2004
                n = put_list(values_of, True, texts, out, n)
            else:
                n = put_list(values_of, False, texts, out, n)
            lists += 1
        elif ch == 3:  # noqa: PLR2004 - SECONDS
            n = _put_seconds(values[v], out, n)
            v += 1
        else:
            n = _put_integer(values[v], out, n)
            v += 1
        if n < 0:
            return n
    return n


KERNELS = [_write_template]  # for the first run's "compiling kernels" progress (tools/warmup.py)
_NO_PAIRS = {_F32: np.zeros((0, 2), np.float32), _F64: np.zeros((0, 2))}


def template_text(
    template: bytes,
    first: np.ndarray,
    pairs: np.ndarray | None,
    third: np.ndarray | None,
    values: array.array[float],
) -> memoryview | None:
    """``template`` with its numbers written in (see the module docstring), left in this thread's
    buffer (json_numbers' kept buffer: valid until its next use); None when a value lies outside
    what the kernel writes exactly.

    Args:
        template: UTF-8 text with at most three list markers (FLAT or PAIRS) and one SECONDS or
            INTEGER marker per entry of ``values``.
        first, pairs, third: the lists' values in metres, in the order of their markers (an
            absent one None): (N,), (M, 2) and (K,); float32 arrays as they are (the stages'),
            anything else as float64.
        values: the SECONDS and INTEGER markers' values in order, as an ``array("d")``.
    """
    # the stages' arrays go as they are: a check each, written out (every numpy call or Python
    # function call here costs the frame loop about a microsecond); C order and writable: a
    # read-only array is another type to numba, compiled anew
    if (
        type(first) is np.ndarray
        and first.dtype == _F32
        and first.ndim == 1
        and first.flags.carray
        and (
            pairs is None
            or (
                type(pairs) is np.ndarray
                and pairs.dtype == _F32
                and pairs.ndim == 2  # noqa: PLR2004
                and pairs.shape[1] == 2  # noqa: PLR2004
                and pairs.flags.carray
            )
        )
        and (
            third is None
            or (
                type(third) is np.ndarray
                and third.dtype == _F32
                and third.ndim == 1
                and third.flags.carray
            )
        )
    ):
        one, two, three = first, pairs, third
        dtype = _F32
    else:
        dtype, one, two, three = as_flat(first, pairs, third)
        if two is not None:
            if two.size % 2:
                return None  # not pairs
            two = two.reshape(-1, 2)
    if one is None:
        one = _EMPTY[dtype]
    if two is None:
        two = _NO_PAIRS[dtype]
    if three is None:
        three = _EMPTY[dtype]
    room = (
        len(template)
        + CHARS_PER_VALUE * (one.size + two.size + three.size)
        + CHARS_PER_SCALAR * len(values)
        + 16  # the 8-byte stores past a text's end
    )
    out = getattr(_LOCAL, "buf", None)
    if out is None or out.size < room:
        out = _buffer(room)
    n = _write_template(template, one, two, three, values, _TEXTS, out)
    if n < 0:
        return None
    return _LOCAL.view[:n]
