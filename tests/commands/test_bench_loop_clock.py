"""How ``depthnav bench`` times the whole loop against the pipeline (bench_process._Clock): blocks
of as many loop cycles as one reference call has frames, each followed by one timed call."""

from __future__ import annotations

import pytest

from depthnav_daemon.commands.bench_process import _Clock
from depthnav_daemon.commands.bench_stages import Work
from depthnav_daemon.errors import DepthnavError


class _Sink:
    name = "fake"

    def __init__(self) -> None:
        self.writes = 0

    def write(self, frame: object, result: object) -> None:
        self.writes += 1


def _reference(calls: list[int]) -> Work:
    return Work("reference", lambda: calls.append(1), frames_per_call=3)


def test_a_reference_call_follows_every_block_and_each_block_pairs_with_it() -> None:
    calls: list[int] = []
    clock = _Clock(_reference(calls))
    sink = _Sink()
    timed = clock.wrap(sink)
    for _ in range(11):  # 10 cycles: 3 whole blocks of 3
        timed.write(None, None)
    clock.finish()
    assert sink.writes == 11 and timed.name == "fake"
    assert len(clock.blocks) == 3 and len(calls) == 3 and len(clock.references) == 3
    assert len(clock.ratios()) == 3 and all(r > 0 for r in clock.ratios())
    assert clock.per_frame_s() > 0


def test_a_run_shorter_than_a_block_is_timed_as_one_and_a_single_frame_is_an_error() -> None:
    calls: list[int] = []
    clock = _Clock(_reference(calls))
    timed = clock.wrap(_Sink())
    for _ in range(3):  # 2 cycles
        timed.write(None, None)
    clock.finish()
    assert len(clock.blocks) == 1 and len(calls) == 1 and len(clock.ratios()) == 1
    lonely = _Clock(_reference([]))
    lonely.wrap(_Sink()).write(None, None)
    with pytest.raises(DepthnavError, match="fewer than 2 frames"):
        lonely.finish()
