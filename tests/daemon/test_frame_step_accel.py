"""The accelerometer's tilt is converted once per distinct reading and follows a new one."""

from __future__ import annotations

import pytest

from depthnav_daemon.config.loader import Config
from depthnav_daemon.daemon.frame_step import FrameStep
from depthnav_daemon.pipeline import StageParams
from depthnav_daemon.pipeline.pose import tilt_roll_from_accel
from drivers.base import tilt_roll_to_accel


def test_a_repeated_reading_gives_its_tilt_and_a_new_one_the_new_tilt() -> None:
    cfg = Config()
    step = FrameStep(cfg, StageParams(scan=cfg.scan), None)
    try:
        a = tuple(float(v) for v in tilt_roll_to_accel(15.0, 2.0))
        b = tuple(float(v) for v in tilt_roll_to_accel(25.0, -3.0))
        for reading in (a, a, b, b, a):
            assert step._tilt_roll(reading) == tilt_roll_from_accel(reading)  # type: ignore[arg-type]
        assert step._tilt_roll(b) == pytest.approx((25.0, -3.0))  # type: ignore[arg-type]
        with pytest.raises(ValueError, match="magnitude"):  # a bad reading is refused every time
            step._tilt_roll((0.0, 0.0, 0.0))
        with pytest.raises(ValueError, match="magnitude"):
            step._tilt_roll((0.0, 0.0, 0.0))
    finally:
        step.close()
