"""Tilt and roll from an accelerometer's gravity vector: convention pins."""

from __future__ import annotations

import math

import numpy as np
import pytest

from depthnav_daemon.errors import ConfigError
from depthnav_daemon.pipeline.geometry import cam_to_level
from depthnav_daemon.pipeline.pose import tilt_roll_from_accel
from drivers.base import STANDARD_GRAVITY_MPS2 as G_MPS2


def test_fifteen_degrees_down_reads_minus_9p47_minus_2p54() -> None:
    # at rest the specific force points up; pitched down 15 deg: (0, -g cos 15, -g sin 15)
    # = (0, -9.4726, -2.5382) m/s^2 with g = 9.80665
    assert tilt_roll_from_accel((0.0, -9.47, -2.54)) == pytest.approx((15.0, 0.0), abs=0.02)
    assert tilt_roll_from_accel((0.0, -9.47, 2.54))[0] == pytest.approx(
        -15.0, abs=0.02
    )  # pitched up


def test_level_and_rolled() -> None:
    assert tilt_roll_from_accel((0.0, -G_MPS2, 0.0)) == pytest.approx((0.0, 0.0), abs=1e-12)
    # roll +10 deg (left side up), tilt 0: ax = -g sin 10 = -1.7029, ay = -g cos 10 = -9.6577
    tilt, roll = tilt_roll_from_accel((-1.7029, -9.6577, 0.0))
    assert tilt == pytest.approx(0.0, abs=1e-9) and roll == pytest.approx(10.0, abs=0.01)


@pytest.mark.parametrize(
    ("tilt_deg", "roll_deg"), [(0, 0), (30, 0), (-20, 5), (45, -12), (70, 30), (10, 44)]
)
def test_recovers_the_mount_that_cam_to_level_defines(tilt_deg: float, roll_deg: float) -> None:
    # "up" in the level frame (0, 0, g), in the camera frame by the inverse of cam_to_level
    rot = cam_to_level(math.radians(tilt_deg), math.radians(roll_deg))
    accel = rot.T @ np.array([0.0, 0.0, G_MPS2])
    assert tilt_roll_from_accel(accel) == pytest.approx((tilt_deg, roll_deg), abs=1e-9)


@pytest.mark.parametrize(
    ("vector", "text"),
    [
        ((0.0, 0.0, 0.0), "magnitude 0 m/s^2 (accepted: 4.90..14.71 m/s^2"),
        ((0.0, math.nan, 0.0), "magnitude nan"),
        ((0.0, -19.6, 0.0), "magnitude 19.6 m/s^2"),
        ((0.0, -1.0, 0.0), "magnitude 1 m/s^2"),
        ((1.0, 2.0), "is not 3 numbers"),
        ("abc", "is not 3 numbers"),
    ],
)
def test_bad_vectors_raise_config_error(vector: object, text: str) -> None:
    with pytest.raises(ConfigError) as e:
        tilt_roll_from_accel(vector)  # type: ignore[arg-type]
    assert text in str(e.value) and "\n" not in str(e.value)
