"""memory.near_limits (the memory's lower dead zone per bin) is compiled (it is built on the
worker of a mount change, and numpy held the interpreter lock for parts of it): pinned here to the
numpy definition it replaced, bit for bit."""

from __future__ import annotations

import numpy as np
import pytest

from depthnav_daemon.pipeline import memory
from depthnav_daemon.pipeline.geometry import Mount, level_rays
from drivers.base import KINECT_V1, Intrinsics

HD = Intrinsics(1280, 720, 640.0, 640.0, 639.5, 359.5)
LENS = Intrinsics(640, 480, 580.0, 580.0, 319.5, 239.5, -0.28, 0.07, 0.001, -0.001)


def reference_near_limits(
    intr: Intrinsics, mount: Mount, angle_min: float, inc: float, n: int, rows: tuple[int, ...]
) -> np.ndarray:
    """near_limits as numpy computed it."""
    start, stop, step = rows
    stop = intr.height if stop < 0 else min(stop, intr.height)
    d = level_rays(intr, mount.tilt_rad, mount.roll_rad)[
        start : stop : max(1, step), :: memory.NEAR_STRIDE
    ].reshape(-1, 3)
    d = d[d[:, 2] < 0]
    r = mount.height_m / -d[:, 2] * np.hypot(d[:, 0], d[:, 1])
    b = np.floor((np.arctan2(d[:, 1], d[:, 0]) - angle_min) / inc + 0.5).astype(np.int64)
    ok = (b >= 0) & (b < n)
    out = np.full(n, np.inf)
    np.minimum.at(out, b[ok], r[ok])
    for shift in (1, -1):
        out = np.minimum(out, np.roll(out, shift) if n > 1 else out)
    return out.astype(np.float32)


@pytest.mark.parametrize("intr", [KINECT_V1, HD, LENS], ids=["640x480", "1280x720", "lens"])
def test_near_limits_equal_the_numpy_definition(intr: Intrinsics) -> None:
    rng = np.random.default_rng(7)
    seen_floor = 0
    for _ in range(12):
        mount = Mount(rng.uniform(0.1, 2.0), rng.uniform(-30.0, 80.0), rng.uniform(-20.0, 20.0))
        n = int(rng.integers(1, 900))
        inc = float(rng.uniform(0.0005, 0.01))
        rows = (
            int(rng.integers(0, 40)),
            int(rng.choice([-1, intr.height - 7])),
            1 + int(rng.integers(0, 3)),
        )
        got = memory.near_limits.__wrapped__(intr, mount, -n * inc / 2, inc, n, rows)
        want = reference_near_limits(intr, mount, -n * inc / 2, inc, n, rows)
        assert got.dtype == np.float32 and not got.flags.writeable
        np.testing.assert_array_equal(got, want)
        seen_floor += int(np.isfinite(got).any())
    assert seen_floor >= 6  # the cases do look at the floor


def test_near_limits_of_a_level_camera_are_its_lowest_rows_floor_range() -> None:
    # level camera 1 m up: the bottom row (v = 479, y = 240 / 580) meets the floor at
    # 580 / 240 m along the axis straight ahead
    intr = Intrinsics(640, 480, 580.0, 580.0, 319.5, 239.5)
    inc = 0.01
    n = 101
    out = memory.near_limits.__wrapped__(intr, Mount(1.0, 0.0, 0.0), -0.5, inc, n, (0, -1, 1))
    assert out[n // 2] == pytest.approx(1.0 * 580.0 / 239.5, rel=1e-6)
    assert np.isfinite(out).all()
