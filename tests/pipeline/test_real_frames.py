"""Real depth frames from ../shared/data/real run through the scan (robustness, not accuracy)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from depthnav_daemon.pipeline.geometry import Mount
from depthnav_daemon.pipeline.scan import ScanParams, depth_to_scan
from drivers.base import Intrinsics

SHARED = Path(__file__).resolve().parents[2].parent / "shared" / "data" / "real"


def load_png_mm(path: Path, units_per_m: float) -> np.ndarray:
    if not path.exists():
        pytest.skip(f"{path} is not here (the ../shared folder sits beside the project in CI)")
    raw = np.asarray(Image.open(path)).astype(np.float64)
    return np.rint(raw * (1000.0 / units_per_m)).astype(np.uint16)


@pytest.mark.parametrize("method", ["exact", "paper"])
def test_tum_desk_frame_runs_through_the_scan(method: str) -> None:
    # TUM fr1 Kinect v1, 5000 units per metre; the README gives intrinsics 517.3/516.5/318.6/255.3
    # and a camera about 0.83 m over the desk top, pitched ~31 deg down
    depth = load_png_mm(SHARED / "tum_desk_pair_slambook" / "1_depth.png", 5000.0)
    intr = Intrinsics(640, 480, 517.3, 516.5, 318.6, 255.3)
    scan = depth_to_scan(depth, intr, Mount(0.83, 31.0, 0.0), ScanParams(method=method))
    assert scan.ranges.dtype == np.float32 and scan.ranges.size > 300
    finite = scan.ranges[np.isfinite(scan.ranges)]
    assert finite.size > 0 and (finite >= 0.4).all() and (finite <= 5.0 * 1.2).all()
