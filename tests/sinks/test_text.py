"""The human-readable text sink, end to end through the CLI on the bundled fixture."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from depthnav_daemon.errors import ConfigError
from depthnav_daemon.pipeline.scan import LaserScan
from depthnav_daemon.sinks import create_sink
from depthnav_daemon.sinks.text import nearest

ROOT = Path(__file__).resolve().parents[2]


def test_text_lines_name_the_fixture_obstacles_and_drop_off() -> None:
    p = subprocess.run(
        [
            sys.executable,
            "-m",
            "depthnav_daemon",
            "run",
            "--device",
            f"replay:{ROOT / 'fixtures' / 'corridor_step'}?rate=max",
            "--sink",
            "text?every=2",
            "--max-frames",
            "4",
            "-q",
        ],
        capture_output=True,
        text=True,
        timeout=120,
        cwd=ROOT,
    )
    assert p.returncode == 0, p.stderr
    lines = p.stdout.splitlines()
    assert [line.split()[0] for line in lines] == ["#0", "#2"]
    # fixture truth: 0.55 m, 15 deg; the right box's near corner ~1.2 m away, the hole ~1.0 m ahead
    assert "mount 0.550 m, tilt 15.0 deg" in lines[0]
    assert "right 1.1" in lines[0] or "right 1.2" in lines[0]
    assert "drop-off 1.0" in lines[0] or "drop-off 1.1" in lines[0]


def test_nearest_reads_rep117_values() -> None:
    scan = LaserScan(
        -0.2, 0.2, 0.1, 0.4, 5.0, np.array([np.nan, np.inf, 2.0, 1.5, -np.inf], np.float32)
    )
    assert nearest(scan, -1, -0.15) == "no data"
    assert nearest(scan, -0.15, -0.05) == "clear"
    assert nearest(scan, -0.05, 0.15) == "1.50 m @ 6 deg"
    assert nearest(scan, 0.15, 1) == "too close"


def test_text_sink_rejects_bad_options() -> None:
    with pytest.raises(ConfigError, match="every"):
        create_sink("text?every=0")
    with pytest.raises(ConfigError):
        create_sink("text?colour=1")
