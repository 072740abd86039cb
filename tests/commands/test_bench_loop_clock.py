"""How ``depthnav bench`` times the whole loop against the pipeline (bench_process._Clock): blocks
of as many loop cycles as one reference call has frames, each followed by one timed call."""

from __future__ import annotations

import pytest

from depthnav_daemon.commands.bench.process import _Clock
from depthnav_daemon.commands.bench.stages import Work
from depthnav_daemon.errors import DepthnavError


class _Sink:
    name = "fake"

    def __init__(self) -> None:
        self.writes = 0

    def write(self, frame: object, result: object) -> None:
        self.writes += 1


class _Result:
    def __init__(self) -> None:
        self.timings_s = {"scan": 0.002, "cliff": 0.001}  # what the stages said they took


def _reference(calls: list[int]) -> Work:
    return Work("reference", lambda: calls.append(1), frames_per_call=3)


def test_a_reference_call_follows_every_block_and_each_block_pairs_with_it() -> None:
    calls: list[int] = []
    clock = _Clock(_reference(calls))
    sink = _Sink()
    timed = clock.wrap(sink, "fake")
    for _ in range(11):  # 10 cycles: 3 whole blocks of 3
        timed.write(None, _Result())
    clock.finish()
    assert sink.writes == 11 and timed.name == "fake"
    assert len(clock.blocks) == 3 and len(calls) == 3 and len(clock.references) == 3
    assert len(clock.ratios()) == 3 and all(r > 0 for r in clock.ratios())
    assert clock.per_frame_s() > 0


def test_a_run_shorter_than_a_block_is_timed_as_one_and_a_single_frame_is_an_error() -> None:
    calls: list[int] = []
    clock = _Clock(_reference(calls))
    timed = clock.wrap(_Sink(), "fake")
    for _ in range(3):  # 2 cycles
        timed.write(None, _Result())
    clock.finish()
    assert len(clock.blocks) == 1 and len(calls) == 1 and len(clock.ratios()) == 1
    lonely = _Clock(_reference([]))
    lonely.wrap(_Sink(), "fake").write(None, _Result())
    with pytest.raises(DepthnavError, match="fewer than 2 frames"):
        lonely.finish()


def test_every_sinks_write_and_the_stages_of_every_frame_are_noted() -> None:
    clock = _Clock(_reference([]))
    first, second = _Sink(), _Sink()
    timed = [clock.wrap(first, "stdout"), clock.wrap(second, "udp")]
    for _ in range(4):
        for sink in timed:  # as the loop's fan-out writes a frame to each sink
            sink.write(None, _Result())
    assert first.writes == second.writes == 4
    assert set(clock.parts) == {"stages", "stdout", "udp"}
    assert len(clock.parts["stdout"]) == len(clock.parts["udp"]) == 4
    assert all(t >= 0 for t in clock.parts["stdout"] + clock.parts["udp"])
    assert clock.parts["stages"] == [pytest.approx(0.003)] * 4  # once a frame, not per sink
    assert clock._cycles == 3  # only the first sink ticks the clock
