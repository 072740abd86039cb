"""The paper's experiment of figs. 11-12, re-run on synthetic scenes for both scan methods.

Four boxes 40, 15, 3 and 1 cm high stand in front of the sensor at four poses (0.45 m, 15 deg),
(0.8 m, 40 deg), (1.2 m, 50 deg), (1.2 m, 60 deg); the ground margin e_g runs from 0 to 20 cm. For
``paper`` e_g is the depth margin of eq. 5; for ``exact`` it is the height above the floor below
which points count as floor (``min_obstacle_height_m``). A box counts as detected when a bin within
its bearings reports a range within 5 cm of its true front face. "False bins" counts bins that
report an obstacle away from every box: the floor, or a box drawn at the wrong bearing (the paper's
tilt compensation only rescales depth, so off-centre boxes move toward the centre line; issue #17).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from depthnav_daemon.pipeline.geometry import Mount
from depthnav_daemon.pipeline.scan import ScanParams, depth_to_scan
from depthnav_daemon.sim.synthetic import Box, KinectNoise, Scene, render, truth_obstacle_ranges
from drivers.base import KINECT_V1, Intrinsics

BOX_HEIGHTS_M = (0.40, 0.15, 0.03, 0.01)
POSES = ((0.45, 15.0), (0.8, 40.0), (1.2, 50.0), (1.2, 60.0))
MARGINS_M = (0.0, 0.02, 0.05, 0.10, 0.15, 0.20)
BEARINGS_DEG = (20.0, 7.0, -7.0, -20.0)  # left to right, one box each; spans never overlap
BOX_SIZE_M = 0.12

DETECTED_WITHIN_M = 0.05  # a bin reporting a box this close to its true front face


@dataclass(frozen=True, slots=True)
class Row:
    """One line of the table: which boxes one method detects at one pose and margin."""

    method: str
    height_m: float
    tilt_deg: float
    margin_m: float
    detected: tuple[bool, ...]  # per box, in BOX_HEIGHTS_M order
    false_bins: int  # bins that report an obstacle away from every box


def scene_for(mount: Mount, intr: Intrinsics) -> Scene:
    """Boxes at the distance where the principal ray meets the floor (clamped to 0.8..2.5 m)."""
    dist = min(max(mount.height_m / math.tan(max(mount.tilt_rad, 0.05)), 0.8), 2.5)
    boxes = []
    for h, b in zip(BOX_HEIGHTS_M, BEARINGS_DEG, strict=True):
        r = dist + BOX_SIZE_M / 2
        boxes.append(
            Box(
                r * math.cos(math.radians(b)),
                r * math.sin(math.radians(b)),
                BOX_SIZE_M,
                BOX_SIZE_M,
                h,
                yaw_deg=b,
            )
        )
    return Scene(boxes=tuple(boxes))


def run(intr: Intrinsics = KINECT_V1, seed: int = 11, noise: bool = True) -> list[Row]:
    """Run the whole grid; returns one Row per (method, pose, margin)."""
    rows: list[Row] = []
    for height_m, tilt_deg in POSES:
        mount = Mount(height_m, tilt_deg, 0.0)
        scene = scene_for(mount, intr)
        rng = np.random.default_rng(seed)
        view = render(scene, intr, mount, KinectNoise() if noise else None, rng)
        for margin in MARGINS_M:
            for method in ("paper", "exact"):
                if method == "paper":
                    params = ScanParams(method="paper", ground_margin_m=margin)
                else:
                    params = ScanParams(method="exact", min_obstacle_height_m=margin)
                scan = depth_to_scan(view.depth_mm, intr, mount, params)
                rows.append(_score(scan, scene, method, mount, margin))
    return rows


def _score(scan, scene: Scene, method: str, mount: Mount, margin: float) -> Row:
    angles = scan.angles
    detected = []
    near_any = np.zeros(angles.size, dtype=bool)
    for box in scene.boxes:
        truth = truth_obstacle_ranges(Scene(boxes=(box,)), angles, -1.0, 10.0)
        in_box = np.isfinite(truth)
        span = angles[in_box]
        if span.size:
            near_any |= (angles > span.min() - 0.03) & (angles < span.max() + 0.03)
        with np.errstate(invalid="ignore"):
            ok = (
                in_box
                & np.isfinite(scan.ranges)
                & (np.abs(scan.ranges - truth) < DETECTED_WITHIN_M)
            )
        detected.append(bool(ok.any()))
    false_bins = int((np.isfinite(scan.ranges) & ~near_any).sum())
    return Row(method, mount.height_m, mount.tilt_deg, margin, tuple(detected), false_bins)


def format_table(rows: list[Row]) -> str:
    """Markdown table: one line per pose and margin, detected boxes per method, floor false hits."""
    head = (
        "| pose (h, tilt) | e_g | paper: 40/15/3/1 cm | paper false bins "
        "| exact: 40/15/3/1 cm | exact false bins |"
    )
    lines = [head, "|---|---:|:---:|---:|:---:|---:|"]
    by_key = {(r.method, r.height_m, r.tilt_deg, r.margin_m): r for r in rows}
    for height_m, tilt_deg in POSES:
        for margin in MARGINS_M:
            p = by_key[("paper", height_m, tilt_deg, margin)]
            e = by_key[("exact", height_m, tilt_deg, margin)]
            mark = lambda r: " ".join("Y" if d else "-" for d in r.detected)  # noqa: E731
            lines.append(
                f"| ({height_m:.2f} m, {tilt_deg:.0f} deg) | {margin * 100:.0f} cm | {mark(p)} "
                f"| {p.false_bins} "
                f"| {mark(e)} | {e.false_bins} |"
            )
    return "\n".join(lines)


def draw(rows: list[Row]):  # -> matplotlib Figure (the plot extra)
    """The figs. 11-12 figure of ``rows`` (both methods side by side)."""
    from depthnav_daemon.plots.experiment import draw_experiment

    return draw_experiment(rows, POSES, MARGINS_M, BOX_HEIGHTS_M)


def main(argv: list[str] | None = None) -> int:
    """Print the table (``python -m depthnav_daemon.sim.paper_experiment [--plot FILE]``).

    Returns:
        The exit code: 0, or 2 / 1 with a one-line error for a bad or unwritable ``--plot`` file.
    """
    import argparse
    import sys

    from depthnav_daemon.errors import DepthnavError

    parser = argparse.ArgumentParser(
        prog="python -m depthnav_daemon.sim.paper_experiment", description=__doc__.split("\n")[0]
    )
    parser.add_argument(
        "--plot", metavar="FILE", help="also draw the figure (.png or .svg; needs depthnav[plot])"
    )
    args = parser.parse_args(argv)
    try:
        if args.plot:
            from depthnav_daemon.plots import check_output

            check_output(args.plot, "--plot")
        rows = run()
        print(format_table(rows))  # noqa: T201
        if args.plot:
            from depthnav_daemon.plots import save

            save(draw(rows), args.plot, "--plot")
            print(f"figure written to {args.plot}")  # noqa: T201
    except DepthnavError as exc:
        sys.stderr.write(f"paper_experiment: error: {exc}\n")
        if exc.hint:
            sys.stderr.write(f"paper_experiment: hint: {exc.hint}\n")
        return exc.exit_code
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
