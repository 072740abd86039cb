"""Soak: a max-rate replay through every sink with flat memory and no frame dropped.

The short form (1,500 frames, about 10 s) runs in CI; the long form (100,000 frames, 10-15
minutes) with ``pytest tests/faults --soak`` or DEPTHNAV_SOAK=1, or as ``scripts/soak.py``.
"""

from __future__ import annotations

import pytest

from depthnav_daemon.tools.soak import RSS_LIMIT_MB, run_soak

SHORT, LONG = 1500, 100_000


def test_soak_through_every_sink(soak_long: bool, tmp_path) -> None:
    frames = LONG if soak_long else SHORT
    # the short form logs every 50th frame to the .rrd: rerun's batcher climbs by about 6 MB
    # per 100 logged frames for the first ~4,000 before its saw tooth comes back down (the long
    # form, every 10th over 100,000 frames, ends 41 MB below its warm-up: docs/hardening.md),
    # and 1,000 frames at every 10th cannot tell that climb from a leak
    report = run_soak(
        frames,
        workdir=tmp_path,
        warmup=max(500, frames // 10),
        rrd_every=10 if soak_long else 50,
        timeout_s=3600.0 if soak_long else 600.0,
    )
    text = report.text()
    print(text)  # noqa: T201 - the figures, with -s
    assert report.exit_code == 0, text
    assert report.frames_processed == frames, text
    # no frame dropped: every seq once and in order on stdout, every seq over UDP
    assert report.stdout_lines == frames and report.stdout_out_of_order == 0, text
    assert report.udp_received == frames and report.udp_missing == 0, text
    assert report.mavlink_bytes > 0 and report.rrd_bytes > 0, text  # the other sinks were fed
    assert len([s for s in report.samples if s[0] >= report.warmup_frames]) >= 2, text
    assert report.rss_growth_mb < RSS_LIMIT_MB, text


@pytest.mark.parametrize("frames", [1])
def test_soak_report_fails_on_a_drop(frames: int) -> None:
    """The report's verdict is not a tautology: a missing datagram makes it fail."""
    from depthnav_daemon.tools.soak import SoakReport

    good = SoakReport(frames, frames_processed=1, stdout_lines=1, udp_received=1, exit_code=0)
    assert good.ok
    assert not SoakReport(
        frames, frames_processed=1, stdout_lines=1, udp_received=0, udp_missing=1, exit_code=0
    ).ok
    assert not SoakReport(
        frames,
        frames_processed=1,
        stdout_lines=1,
        udp_received=1,
        exit_code=0,
        rss_growth_mb=RSS_LIMIT_MB,
    ).ok
