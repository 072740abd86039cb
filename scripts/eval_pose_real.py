"""Floor pose on the real CMU Panoptic Kinect v2 frames against their reference (read in place).

    python3 scripts/eval_pose_real.py [--data ../shared/data/real/cmu_panoptic_kinoptic_10view]
                                      [--seeds 5] [--height-max-m 3.0] [--lens]

Prints per view the estimate minus the leave-one-out reference (height mm, tilt and roll degrees;
the reference's roll is atan2(n_x, -n_y), the opposite sign of depthnav's), and the median time
per estimate. ``--lens`` gives each view its lens distortion (the first five ``distCoeffs_depth``
of the calibration, OpenCV order k1 k2 p1 p2 k3). The data are non-commercial research only:
never copy them into the repository.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from depthnav_daemon.pipeline.pose import PoseParams, estimate_pose
from drivers.base import Intrinsics

DEFAULT = (
    Path(__file__).resolve().parents[2]
    / "shared"
    / "data"
    / "real"
    / "cmu_panoptic_kinoptic_10view"
)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", type=Path, default=DEFAULT)
    ap.add_argument("--seeds", type=int, default=5)
    ap.add_argument("--height-max-m", type=float, default=3.0)
    ap.add_argument("--lens", action="store_true", help="apply the lens distortion coefficients")
    args = ap.parse_args(argv)
    calib = json.loads((args.data / "kcalibration_171026_cello3.json").read_text())["sensors"]
    data = np.load(args.data / "views.npz")
    depth, intrinsics = data["depth_mm"], data["intrinsics_per_view"]
    ref = json.loads((args.data / "floor_reference.json").read_text())["cameras"]
    params = PoseParams(height_max_m=args.height_max_m)
    times: list[float] = []
    worst = np.zeros(3)
    print(
        f"{'view':>4} {'seed':>4} {'ok':>3} {'dh mm':>7} {'dtilt':>7} {'droll':>7} {'inliers':>8} "
        f"{'resid mm':>8}"
    )
    for i in range(depth.shape[0]):
        fx, fy, cx, cy = (float(v) for v in intrinsics[i])
        lens = [float(c) for c in calib[i]["distCoeffs_depth"][:5]] if args.lens else []
        intr = Intrinsics(depth.shape[2], depth.shape[1], fx, fy, cx, cy, *lens)
        frame = np.ascontiguousarray(depth[i])
        r = ref[i]["reference_leave_one_out"]
        for seed in range(args.seeds):
            t0 = time.perf_counter()
            est = estimate_pose(frame, intr, params, np.random.default_rng(seed))
            times.append(time.perf_counter() - t0)
            err = np.array(
                [
                    est.height_m - r["height_m"],
                    est.tilt_deg - r["pitch_down_deg"],
                    est.roll_deg + r["roll_deg"],
                ]
            )
            worst = np.fmax(worst, np.abs(err))
            print(
                f"{i:>4} {seed:>4} {'y' if est.ok else 'n':>3} {err[0] * 1000:>7.1f} "
                f"{err[1]:>7.2f} {err[2]:>7.2f} "
                f"{est.inliers:>8} {est.residual_m * 1000:>8.1f}  {est.reason}"
            )
    print(
        f"worst |dh| {worst[0] * 1000:.1f} mm, |dtilt| {worst[1]:.2f} deg, |droll| {worst[2]:.2f} "
        "deg; "
        f"median {np.median(times) * 1000:.1f} ms per estimate ({depth.shape[2]}x{depth.shape[1]})"
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
