"""The device spec options: one table, and every option a driver accepts is in ``--help``."""

from __future__ import annotations

import subprocess
import sys

import pytest

from drivers import replay
from drivers.kinect import driver as kinect
from drivers.openni import driver as openni
from drivers.spec_options import DEVICE_OPTIONS, help_text, option_names
from tests.test_cli import ROOT

ACCEPTED = {
    "replay": set(replay.OPTIONS),
    "kinect": set(kinect.OPTIONS),
    "openni": set(openni.LIVE_OPTIONS) | set(openni.FILE_OPTIONS),
}


@pytest.mark.parametrize("scheme", sorted(ACCEPTED))
def test_the_table_lists_exactly_the_options_each_driver_accepts(scheme):
    assert set(option_names(scheme)) == ACCEPTED[scheme]
    assert len(option_names(scheme)) == len(set(option_names(scheme)))


def test_every_scheme_with_a_driver_is_in_the_table():
    import drivers

    assert set(DEVICE_OPTIONS) == set(drivers.DRIVERS)


@pytest.mark.parametrize("command", ["run", "replay", "record", "calibrate", "snapshot"])
def test_help_shows_every_option_the_parsers_accept(command):
    out = subprocess.run(
        [sys.executable, "-m", "depthnav_daemon", command, "--help"],
        capture_output=True,
        text=True,
        cwd=ROOT,
        timeout=120,
        env={"COLUMNS": "100", "PATH": "/usr/bin:/bin"},
        check=True,
    ).stdout
    assert help_text() in out
    lines = out.splitlines()
    for scheme, options in ACCEPTED.items():
        for name in options:
            # one line per option, under its scheme's line
            assert any(line.split()[:1] == [name] for line in lines), (scheme, name)


def test_an_unknown_option_error_lists_what_help_shows():
    import drivers
    from drivers.errors import DeviceSpecError

    with pytest.raises(DeviceSpecError) as info:
        drivers.create_driver("replay:x?globb=*.png")
    for name in option_names("replay"):
        assert name in str(info.value)
