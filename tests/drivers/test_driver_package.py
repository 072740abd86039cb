"""Package-level helpers: opened(), iter_frames(), detect_devices(), describe_backends(), recording
from a driver, and the layering rule that drivers/ never imports depthnav_daemon."""

from __future__ import annotations

import itertools
import json
import threading

import numpy as np
import pytest

import drivers
from drivers.errors import DriverError
from drivers.formats.recording import read_recording
from drivers.formats.recording_writer import write_recording
from drivers.replay import ReplayDriver
from tests.drivers.driverkit import ramp_frames, run_isolated


def test_opened_closes_even_when_the_body_raises(tmp_path):
    write_recording(tmp_path / "rec", ramp_frames(2))
    driver = drivers.create_driver(f"replay:{tmp_path / 'rec'}?rate=max")
    before = ReplayDriver.open_count
    with pytest.raises(RuntimeError), drivers.opened(driver):
        assert ReplayDriver.open_count == before + 1
        raise RuntimeError("boom")
    assert ReplayDriver.open_count == before
    with pytest.raises(DriverError, match="not open"):
        driver.read_frame()


def test_iter_frames_stops_on_the_stop_event(tmp_path):
    write_recording(tmp_path / "rec", ramp_frames(2))
    stop = threading.Event()
    seen = []
    with drivers.opened(drivers.create_driver(f"replay:{tmp_path / 'rec'}?rate=max&loop=1")) as d:
        for frame in drivers.iter_frames(d, stop):
            seen.append(frame.seq)
            if len(seen) == 5:
                stop.set()
    assert seen == [0, 1, 2, 3, 4]


def test_record_any_driver_to_a_recording_and_replay_it(tmp_path):
    write_recording(tmp_path / "src", ramp_frames(4), description="source")
    progress = []
    with drivers.opened(drivers.create_driver(f"replay:{tmp_path / 'src'}?rate=max")) as d:
        n = write_recording(
            tmp_path / "copy",
            itertools.islice(drivers.iter_frames(d), 3),
            description="copied",
            device=f"replay:{tmp_path / 'src'}",
            truth={"tilt_deg": 5.0},
            progress=progress.append,
        )
    assert n == 3 and progress == [1, 2, 3]
    rec = read_recording(tmp_path / "copy")
    src = read_recording(tmp_path / "src")
    np.testing.assert_array_equal(rec.depth_mm, src.depth_mm[:3])
    np.testing.assert_allclose(rec.accel_mps2, src.accel_mps2[:3])
    assert rec.device.startswith("replay:") and rec.truth == {"tilt_deg": 5.0}


def test_detect_devices_and_backends_never_raise():
    # In a child: OpenNI2 detection loads native code.
    code = """
import json, drivers
print(json.dumps({"devices": drivers.detect_devices(), "backends": drivers.describe_backends()}))
"""
    proc = run_isolated(code)
    assert proc.returncode == 0, proc.stderr[-2000:]
    out = json.loads(proc.stdout.strip().splitlines()[-1])
    assert all(
        len(item) == 2 and item[0].split(":")[0] in ("kinect", "openni") for item in out["devices"]
    )
    names = [name for name, _ in out["backends"]]
    assert {"kinect", "openni", "replay", "serialtilt"} <= set(names)


def test_drivers_never_import_the_daemon():
    code = """
import importlib, pkgutil, sys, drivers
for info in pkgutil.iter_modules(drivers.__path__):
    importlib.import_module("drivers." + info.name)
print(sorted(m for m in sys.modules if m.split(".")[0] == "depthnav_daemon"))
"""
    proc = run_isolated(code)
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert proc.stdout.strip().splitlines()[-1] == "[]"
