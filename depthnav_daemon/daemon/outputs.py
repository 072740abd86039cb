"""The frame loops' outputs (loop.py, multi.py): open the sinks, add the memory to a result, fan
the result out to every sink (one that fails is dropped and the others go on), and at the end of
a run tell systemd and close (flush) every sink."""

from __future__ import annotations

import dataclasses
import logging
import time
from collections.abc import Callable

from depthnav_daemon.daemon.memory_keeper import MemoryKeeper
from depthnav_daemon.daemon.notify import ServiceNotifier
from depthnav_daemon.daemon.report import RunReport
from depthnav_daemon.errors import DepthnavError, SinkError
from depthnav_daemon.pipeline import Result, StageParams
from depthnav_daemon.sinks.base import Sink, SinkContext
from drivers.base import Frame

log = logging.getLogger(__name__)


class OpenSinks(list[Sink]):
    """The sinks that started, and (``never_started``) each asked for that could not: (spec,
    why, hint), said again by close_outputs() in the run's summary."""

    never_started: list[tuple[str, str, str | None]]


def open_sinks(
    specs: tuple[str, ...], context: SinkContext, factory: Callable[[str], Sink]
) -> OpenSinks:
    """Open every sink; one that cannot start is reported and left out while others started.

    Raises:
        DepthnavError: no sink could start (each failure is named in the message, once).
    """
    sinks = OpenSinks()
    sinks.never_started = []
    failures: list[tuple[str, str | None]] = []  # (what failed, its hint)
    for spec in specs:
        sink = factory(spec)
        try:
            sink.open(context)
        except (SinkError, OSError) as exc:
            failures.append(
                (f"sink {spec} could not start: {_one_line(exc)}", getattr(exc, "hint", None))
            )
            sinks.never_started.append((spec, _one_line(exc), getattr(exc, "hint", None)))
            continue
        sinks.append(sink)
    if not sinks:
        if len(failures) == 1:
            what, hint = failures[0]
            raise DepthnavError(
                f"{what}; no output sink could start", hint=hint or "check the --sink spec"
            )
        for what, hint in failures:
            log.error("%s%s", what, f" ({hint})" if hint else "")
        raise DepthnavError(
            f"no output sink could start ({len(failures)} tried, see above)",
            hint="check the --sink specs (depthnav run --help)",
        )
    for what, hint in failures:  # only now is "going on without it" true
        log.error("%s; going on without it%s", what, f" ({hint})" if hint else "")
    return sinks


def _one_line(exc: BaseException) -> str:
    text = str(exc)
    return text.splitlines()[0] if text else type(exc).__name__


def fan_out(sinks: list[Sink], frame: Frame, result: Result, report: RunReport) -> None:
    for sink in list(sinks):
        try:
            sink.write(frame, result)
        except Exception as exc:
            hint = getattr(exc, "hint", None)
            log.error(
                "sink %s failed: %s; dropped, the others go on%s",
                sink.name,
                _one_line(exc),
                f" ({hint})" if hint else "",
            )
            report.dropped_sinks.append(sink.name)
            sinks.remove(sink)
            try:
                sink.close()
            except Exception:
                log.debug("closing failed sink %s", sink.name, exc_info=True)
    if not sinks:
        raise DepthnavError("every output sink failed", hint="see the errors above")


def with_memory(
    keeper: MemoryKeeper,
    frame: Frame,
    arrival_s: float,
    results: list[tuple[Result, StageParams]],
    out: Result,
) -> Result:
    """``out`` with the memory updated by ``results`` (and its time in timings_s["memory"])."""
    if not keeper.enabled:
        return out
    t0 = time.perf_counter()
    memory = keeper.step(frame, arrival_s, results)
    if memory is None:
        return out
    out.timings_s["memory"] = time.perf_counter() - t0
    return dataclasses.replace(out, memory=memory)


def close_outputs(sinks: list[Sink], notifier: ServiceNotifier, report: RunReport) -> None:
    """At the end of a run: tell systemd it stops, then close (flush) every sink.

    A sink asked for that never started is said again here, last, in one WARNING line each
    (``sink SPEC never ran: ...``; its ERROR came at start-up), and listed in the run's summary
    as ``SPEC (never started)``: the run went on without it (exit 0), so the end of the log must
    say that an output the user asked for holds nothing (a second daemon on the same ``.rrd``).
    """
    notifier.stopping(f"stopping after {report.frames} frames")
    notifier.close()
    for sink in sinks:
        try:
            sink.close()
        except Exception as exc:
            log.error("sink %s did not close cleanly: %s", sink.name, exc)
    for spec, why, hint in getattr(sinks, "never_started", ()):
        log.warning(
            "sink %s never ran: it could not start (%s)%s; %d frames went to the other sinks",
            spec,
            why,
            f" ({hint})" if hint else "",
            report.frames,
        )
        report.dropped_sinks.append(f"{spec} (never started)")
