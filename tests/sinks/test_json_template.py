"""The template writer (json_template) writes what orjson writes: seconds as orjson writes Python's
``round(v, 6)``, integers, and the lists as json_numbers writes them; and it refuses (None) what it
cannot write exactly, so that the caller takes the reference path."""

from __future__ import annotations

from array import array

import numpy as np
import orjson
import pytest

from depthnav_daemon.sinks.json.numbers import lists_json
from depthnav_daemon.sinks.json.template import (
    FLAT,
    INTEGER,
    MAX_SECONDS,
    PAIRS,
    SECONDS,
    _write_template,
    template_text,
)

NONE = np.zeros(0, np.float32)


def _seconds(values: np.ndarray) -> bytes | None:
    """The values written by SECONDS markers, as a JSON list."""
    template = b"[" + b",".join([SECONDS] * len(values)) + b"]"
    text = template_text(template, NONE, None, None, array("d", values))
    return None if text is None else bytes(text)


def _want_seconds(values: np.ndarray) -> bytes:
    return orjson.dumps([round(v, 6) if np.isfinite(v) else None for v in values.tolist()])


def test_seconds_are_what_orjson_writes_of_pythons_round() -> None:
    rng = np.random.default_rng(7)
    special = [0.0, -0.0, 1e-9, -1e-9, 4.99e-7, 5e-7, 5.01e-7, 1e-6, -3e-6, 9.4e-6, 9.6e-6]
    special += [1e-5, 0.0078125, 1.5, 1796200926.6991435, MAX_SECONDS - 1e-6, 1e-300]
    special += [np.inf, -np.inf, np.nan, 5e-324]
    parts = [np.array(special)]
    for scale in (1e-6, 1e-5, 1e-4, 1e-2, 1.0, 1e3, 1e6, 1e9, 4e9):
        parts.append(rng.uniform(-scale, scale, 20_000))
    # Python's round() goes to the even neighbour only at an exact tie: value * 10**6 exactly
    # half way, which a double holds only as an odd multiple of 1/128; and their neighbours
    ties = (rng.integers(-(2**38), 2**38, 20_000) * 2 + 1) / 128.0
    parts += [ties, np.nextafter(ties, np.inf), np.nextafter(ties, -np.inf)]
    values = np.concatenate(parts)
    values = values[~(np.abs(values) >= MAX_SECONDS)]  # NaN stays
    assert _seconds(values) == _want_seconds(values)


@pytest.mark.parametrize("value", [MAX_SECONDS, -MAX_SECONDS, 1e16, -1e300])
def test_seconds_beyond_the_exact_domain_are_refused(value: float) -> None:
    assert _seconds(np.array([1.0, value])) is None


def test_integers() -> None:
    values = np.array([0, 7, -7, 114, 2**53 - 1, -(2**53 - 1)], np.float64)
    template = b"[" + b",".join([INTEGER] * len(values)) + b"]"
    text = template_text(template, NONE, None, None, array("d", values))
    assert text is not None
    assert bytes(text) == orjson.dumps([int(v) for v in values])
    for bad in (0.5, 2.0**53, np.nan, np.inf):
        assert template_text(INTEGER, NONE, None, None, array("d", [bad])) is None


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_the_lists_are_json_numbers_lists(dtype) -> None:
    rng = np.random.default_rng(3)
    first = rng.uniform(0.4, 150.0, 300).astype(dtype)
    first[:4] = [np.nan, np.inf, -np.inf, -0.0]
    pairs = rng.uniform(-3.0, 3.0, (57, 2)).astype(dtype)
    third = rng.uniform(0.0, 5.0, 11).astype(dtype)
    template = b'{"a":' + FLAT + b',"p":' + PAIRS + b',"b":' + FLAT + b',"t":' + SECONDS + b"}"
    text = template_text(template, first, pairs, third, array("d", [0.25]))
    assert text is not None
    got = bytes(text)  # (the buffer lists_json writes into too)
    a, p, b = lists_json(first, pairs, third)
    assert got == b'{"a":' + a + b',"p":' + p + b',"b":' + b + b',"t":0.25}'


def test_arrays_of_any_kind_go_through_without_a_new_compile() -> None:
    """Read-only, strided, float16 or mixed arrays are converted to the two kinds the kernel is
    compiled for (float32, float64: C order, writable); a compile in the frame loop stalls it."""
    rng = np.random.default_rng(4)
    base = rng.uniform(0.4, 5.0, (40, 2)).astype(np.float32)
    template = FLAT + PAIRS + FLAT
    template_text(template, base[:, 0].copy(), base, base[:, 1].copy(), array("d"))
    template_text(
        template, base[:, 0].astype(np.float64), base.astype(np.float64), None, array("d")
    )
    before = len(_write_template.signatures)
    read_only = base.copy()
    read_only.setflags(write=False)
    for first, pairs, third in (
        (base[:, 0], base, base[:, 1]),  # strided views
        (read_only[:, 0].copy(), read_only, None),
        (base[:, 0].astype(np.float16), base, base[:, 1].astype(np.float64)),
        (list(base[:, 0]), base.tolist(), None),
    ):
        text = template_text(template, first, pairs, third, array("d"))
        assert text is not None
        got = bytes(text)
        want = lists_json(
            np.asarray(first), np.asarray(pairs), np.zeros(0) if third is None else third
        )
        assert got == b"".join(want)
    assert len(_write_template.signatures) == before


def test_what_cannot_be_written_exactly_is_refused() -> None:
    template = FLAT + PAIRS
    assert template_text(template, np.array([1e16]), None, None, array("d")) is None
    bad_pair = np.array([[np.nan, 1.0]], np.float32)
    assert template_text(template, NONE, bad_pair, None, array("d")) is None
    assert template_text(template, NONE, np.zeros(3, np.float32), None, array("d")) is None
