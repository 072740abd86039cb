"""Mount planner: eq. 15 and 16 by hand, and against the ray-cast floor."""

from __future__ import annotations

import math

import numpy as np
import pytest

from depthnav_daemon.errors import ConfigError
from depthnav_daemon.pipeline.geometry import Mount
from depthnav_daemon.pipeline.mount_planner import (
    lower_dead_zone_m,
    max_visible_height_m,
    min_visible_height_m,
    plan_table,
)
from depthnav_daemon.sim.synthetic import LABEL_FLOOR, Scene, render
from drivers.base import Intrinsics


def test_eq15_by_hand() -> None:
    # Kinect: theta = 43 deg; h = 0.55 m, tilt 15 deg down: lower edge 21.5 + 15 = 36.5 deg below
    # the horizon, d_m = 0.55 tan(90 - 36.5) = 0.55 * 1.351422 = 0.74328 m;
    # at h1 = 0.2 m: 0.35 * 1.351422
    got = lower_dead_zone_m(0.55, 15.0, 43.0, [0.0, 0.2])
    np.testing.assert_allclose(got, [0.74328, 0.47300], atol=1e-5)
    # level sensor, same FOV: 0.55 tan(68.5 deg) = 0.55 * 2.538648 = 1.39626 m
    assert float(lower_dead_zone_m(0.55, 0.0, 43.0)) == pytest.approx(1.39626, abs=1e-5)
    # pitched up past half the FOV: the lower edge never meets the floor
    assert np.isinf(lower_dead_zone_m(0.55, -30.0, 43.0))
    # pitched down so far that the view includes straight down: no dead zone
    assert float(lower_dead_zone_m(0.55, 80.0, 43.0)) == 0.0


def test_eq16_by_hand() -> None:
    # tilt 15: upper edge 21.5 - 15 = 6.5 deg above the horizon, tan 6.5 = 0.113936:
    # at 2 m, 0.55 + 2 * 0.113936 = 0.77787 m; at 0 m, the sensor height itself
    np.testing.assert_allclose(
        max_visible_height_m(0.55, 15.0, 43.0, [0.0, 2.0]), [0.55, 0.77787], atol=1e-5
    )
    # tilt 30: the upper edge points 8.5 deg DOWN (sgn negative):
    # 0.55 - 2 * tan 8.5 = 0.55 - 0.29890
    assert float(max_visible_height_m(0.55, 30.0, 43.0, 2.0)) == pytest.approx(0.25110, abs=1e-5)
    # lowest point seen at 2 m with tilt 15: 0.55 - 2 tan 36.5 = 0.55 - 2 * 0.739961 < 0,
    # so the floor is seen
    assert float(min_visible_height_m(0.55, 15.0, 43.0, 2.0)) == pytest.approx(-0.929922, abs=1e-5)


@pytest.mark.parametrize(("h", "tilt"), [(0.55, 15.0), (1.0, 35.0), (0.3, 0.0)])
def test_dead_zone_matches_the_nearest_floor_the_renderer_shows(h: float, tilt: float) -> None:
    # a camera with exactly this vertical FOV: the bottom pixel centre sits half a pixel inside the
    # edge, so the rendered nearest floor point lies between the dead zone and one pixel further
    intr = Intrinsics.from_fov(320, 240, 57.0, 43.0)
    view = render(Scene(), intr, Mount(h, tilt, 0.0))
    centre = int(intr.cx)
    floor = view.label[:, centre] == LABEL_FLOOR
    nearest = np.nanmin(view.points_m[floor, centre, 0])
    dead = float(lower_dead_zone_m(h, tilt, 43.0))
    # one pixel of depression (43 deg / 240) at the edge moves the floor point by d(h cot x)/dx
    pixel = math.radians(43.0 / 240) * h / math.sin(math.radians(21.5 + tilt)) ** 2
    assert dead <= nearest <= dead + pixel


def test_plan_table_rows() -> None:
    rows = plan_table(0.55, 15.0, 43.0, [0.5, 2.0])
    assert [r["distance_m"] for r in rows] == [0.5, 2.0]
    assert rows[0]["floor_seen"] is False and rows[1]["floor_seen"] is True  # dead zone 0.743 m
    assert rows[1]["lowest_seen_m"] == 0.0
    # at 0.5 m the lowest point seen is 0.55 - 0.5 tan 36.5 = 0.55 - 0.369981 = 0.180019 m
    assert rows[0]["lowest_seen_m"] == pytest.approx(0.180019, abs=1e-5)
    assert rows[1]["highest_seen_m"] == pytest.approx(0.77787, abs=1e-5)


@pytest.mark.parametrize(
    ("call", "text"),
    [
        (
            lambda: lower_dead_zone_m(0.0, 15.0, 43.0),
            "height_m=0.0 is out of range (accepted: 0.01..10 m)",
        ),
        (
            lambda: lower_dead_zone_m(0.5, 95.0, 43.0),
            "tilt_deg=95.0 is out of range (accepted: -89..89 deg)",
        ),
        (
            lambda: lower_dead_zone_m(0.5, 15.0, 0.0),
            "vfov_deg=0.0 is out of range (accepted: 1..179 deg)",
        ),
        (
            lambda: lower_dead_zone_m(0.5, 15.0, 43.0, 0.8),
            "h1_m=0.8 is out of range (accepted: 0..0.5 m)",
        ),
        (
            lambda: max_visible_height_m(0.5, 15.0, 43.0, [1.0, -2.0]),
            "distance_m=-2.0 is out of range",
        ),
        (lambda: plan_table(0.5, 15.0, 43.0, ["x"]), "distances_m=['x'] is not a number"),
    ],
)
def test_bad_values_raise_config_error(call: object, text: str) -> None:
    with pytest.raises(ConfigError) as e:
        call()  # type: ignore[operator]
    assert text in str(e.value) and "\n" not in str(e.value)
