"""One way to read a number from untrusted input, and one way to show any value in a message.

Every number depthnav reads from a file, a spec option, ``--set`` or a parameter file goes through
:func:`to_number`: text must be plain ASCII digits (Python's ``int()`` and ``float()`` also take
``'٥٦٠٠'``, ``'1_000'`` and ``' 5 '``), at most MAX_NUMBER_CHARS long; values must be finite and
within bounds, compared exactly (a 400-digit integer is "out of range", not an ``OverflowError``
from a float conversion; one over Python's 4300-digit limit never reaches ``int()``). Failures are
:class:`NumberError`, a ValueError whose message is a short reason, to which each caller adds what
it was reading and raises its own error type.

:func:`short_repr` is the only way a value read from input enters a message: bounded in length and
in the work it does (a YAML document of shared lists, a billion laughs, is not expanded; an integer
of 5000 digits is not converted to text).
"""

from __future__ import annotations

import math
import re
import reprlib
from typing import Any

MAX_NUMBER_CHARS = 100  # longer text is not a number depthnav needs
MAX_MAGNITUDE = 1e300  # beyond it no parameter makes sense and products overflow a float
INT_LIMIT = 2**63  # integers depthnav reads fit a signed 64-bit integer
_INT = re.compile(r"[+-]?[0-9]+\Z")
_FLOAT = re.compile(r"[+-]?(?:[0-9]+(?:\.[0-9]*)?|\.[0-9]+)(?:[eE][+-]?[0-9]+)?\Z")
_SPECIAL = {"nan", "+nan", "-nan", "inf", "+inf", "-inf", "infinity", "+infinity", "-infinity"}
REPR_CHARS = 60  # the longest a value is shown in a message
_BIG_INT_BITS = 200  # integers longer than this (about 60 digits) are shown by their size
_COUNTABLE_BITS = 14_000  # about 4200 digits: below Python's 4300-digit str() limit


class NumberError(ValueError):
    """A value that is not an accepted number; the message is a short reason, e.g.
    ``is not a number`` or ``is out of range (accepted: 1..8192)``."""


class _Repr(reprlib.Repr):
    """reprlib with big integers shown by their size (``repr()`` raises over 4300 digits)."""

    def repr_int(self, x: int, level: int) -> str:
        if x.bit_length() <= _BIG_INT_BITS:
            return repr(x)
        sign = "-" if x < 0 else ""
        if x.bit_length() <= _COUNTABLE_BITS:  # str() is allowed and cheap up to here
            return f"<{sign}integer of {len(str(abs(x)))} digits>"
        return f"<{sign}integer of about {int(x.bit_length() * math.log10(2)) + 1} digits>"

    def repr_bool(self, x: bool, level: int) -> str:
        return repr(x)


_REPR = _Repr()
_REPR.maxlevel = 3
_REPR.maxstring = REPR_CHARS
_REPR.maxother = REPR_CHARS
_REPR.maxlong = REPR_CHARS
for _attr in ("maxlist", "maxtuple", "maxdict", "maxset", "maxfrozenset", "maxdeque", "maxarray"):
    setattr(_REPR, _attr, 4)


def short_repr(value: Any, limit: int = REPR_CHARS) -> str:
    """``repr(value)`` cut to about ``limit`` characters, at bounded cost for any value."""
    try:
        text = _REPR.repr(value)
    except Exception:  # a value whose own repr fails: name its type
        text = f"<{type(value).__name__}>"
    return text if len(text) <= limit + 3 else text[:limit] + "..."


def short_text(text: str, limit: int = 120) -> str:
    """``text`` on one line, cut to about ``limit`` characters (for messages quoting input)."""
    line = " ".join(str(text).split())
    return line if len(line) <= limit + 3 else line[:limit] + "..."


def _bounds_text(low: float | None, high: float | None) -> str:
    lo = "" if low is None else f"{low:g}"
    hi = "" if high is None else f"{high:g}"
    return f"{lo}..{hi}"


def parse_number_text(text: str, *, integer: bool = False) -> int | float:
    """An ASCII decimal number (``nan``/``inf`` parse as floats, to be refused by bounds).

    Raises:
        NumberError: not a number (or not an integer), or longer than MAX_NUMBER_CHARS.
    """
    raw = text.strip()
    kind = "an integer" if integer else "a number"
    if len(raw) > MAX_NUMBER_CHARS:
        raise NumberError(f"is too long to be {kind} (more than {MAX_NUMBER_CHARS} characters)")
    if _INT.match(raw):
        return int(raw)
    if not integer and (_FLOAT.match(raw) or raw.lower() in _SPECIAL):
        return float(raw)
    raise NumberError(f"is not {kind}")


def to_number(
    value: Any,
    *,
    integer: bool = False,
    low: float | None = None,
    high: float | None = None,
) -> int | float:
    """A finite number from a parsed value (int, float, numpy scalar) or ASCII text.

    Args:
        value: what was read; booleans are not numbers.
        integer: the result must be an integer (an integral float such as 3.0 is accepted).
        low, high: inclusive bounds, or None for the defaults (|x| < 2**63 for integers,
            |x| <= 1e300 for floats).

    Returns:
        An int when ``integer``, else a float.

    Raises:
        NumberError: with a short reason (the caller names the value and its origin).
    """
    if isinstance(value, str):
        value = parse_number_text(value, integer=integer)
    elif isinstance(value, bool) or not hasattr(value, "__float__"):
        raise NumberError("is not a number")
    if hasattr(value, "__index__"):  # int, numpy integer: exact comparisons, never a float
        number: int | float = int(value)
    else:
        try:
            number = float(value)
        except (TypeError, ValueError, OverflowError):
            raise NumberError("is not a number") from None
        if not math.isfinite(number):
            raise NumberError("is not a finite number")
        if integer:
            if not number.is_integer():
                raise NumberError("is not an integer")
            number = int(number)
    limit = INT_LIMIT - 1 if integer else MAX_MAGNITUDE
    if abs(number) > limit and (low is None or high is None):
        raise NumberError(f"is too large (more than {limit:.3g} in size)")
    if not (low is None or low <= number) or not (high is None or number <= high):
        raise NumberError(f"is out of range (accepted: {_bounds_text(low, high)})")
    return number if integer else float(number)
