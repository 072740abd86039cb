"""Negative obstacles (steps down, holes): the paper's eq. 6-8 decides that a drop-off is there;
the exact method then finds its edge on every image column.

A *drop-off sample* is a pixel that sees farther than the floor should be: its ray goes below the
floor plane. Samples are taken on a grid (``row_step`` x ``col_step``) inside square blocks of
``block_size`` pixels over the bottom ``used_depth_height`` rows (eq. 7); a block with at least
``block_points_thresh`` samples is a negative obstacle (eq. 8).

``exact`` (the default, the fix): a sample counts when its reading lies *below the floor plane*
(tilt AND roll, as ``level_rays``: the floor depth of a pixel is t = h / -kz, kz = level-frame z
per metre of optical depth) by more than both ``ground_margin_m`` (vertical: depth > t (h +
margin) / h; it keeps Kinect quantisation, centimetres of depth at 4 m but millimetres of height
along a grazing ray, from faking drops) and ``noise_sigmas`` sigmas of the sensor's depth noise
at the floor's depth (depth > t + n k t^2, ``depth_noise``: k of sigma(z) = k z^2, a stereo
camera's grows fast). Only pixels whose ray meets the floor within [range_min_m, range_max_m] of
horizontal range are read; rays at or above the horizon never count. Where blocks are found, the
edge is searched for on every image column of them, of the block below (the block straddling the
edge may miss the threshold) and of the block columns either side (``cliff_kernels.edges``):
the first lower-floor pixel going up the column, and the floor reading under it. The edge hiding the
lower floor lies between their two rays, so the floor point of the lower ray is at most one
pixel's floor footprint before the edge (two where the sensor dropped the last floor pixel) and
never beyond it; where an obstacle hides the edge, its point is taken. ``points_m`` holds these
edge points, one per column and drop-off; the cliff scan bins each by its pixel's footprint (the
bearings between its left and right edges, as the obstacle scan), nearest first. A bin without a
drop-off is +inf only where the read rows see the floor on it out to range_max
(``coverage.floor_extent``) and no sample of its columns, or of the sample columns beside them,
read a drop-off (one too few samples saw to make a block), else NaN (the safety contract).

``paper``: eq. 6 as published: per-row floor depth with the linear row angle (eq. 3), no roll,
margin in optical depth, ``range_min_m < depth < range_max_m`` (ROS 1 cliff_detector); every
detected block is reported at the point where the ray through its centre meets the floor plane
(tilt and roll included), and the cliff scan holds the nearest floor range of a drop-off sample
inside a detected block. No noise term, no edges, no coverage mask: the original's behaviour.

With either method a 0/NaN reading never counts, and the cliff scan follows REP 117 (+inf = no
drop-off, NaN = unknown, no valid reading).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from depthnav_daemon.pipeline.cliff_kernels import cliff_kernel
from depthnav_daemon.pipeline.cliff_table import cliff_table
from depthnav_daemon.pipeline.geometry import (
    F32,
    Mount,
    check_int,
    check_range,
    depth_to_mm,
)
from depthnav_daemon.pipeline.laser_scan import LaserScan

# CliffParams lives apart for cliff_table; importable here as before
from depthnav_daemon.pipeline.params import CliffParams
from depthnav_daemon.pipeline.scan_kernels import MAX_CODE_INDEX
from drivers.base import Intrinsics


@dataclass(frozen=True, slots=True)
class CliffResult:
    """Drop-offs found in one frame.

    Attributes:
        points_m: (P, 2) float32 floor points (x forward, y left), metres, in the level frame at the
            sensor's foot. exact: the drop-offs' edges, one per image column and drop-off (the
            module docstring says where); paper: where each detected block's centre ray meets the
            floor (P = K, in the order of ``blocks``).
        blocks: (K, 2) int64 (row, col) of each detected block's top-left pixel (for drawing).
        block_size: block side in pixels (for drawing).
        scan: nearest drop-off per bearing, in the layout the caller asked for (REP 117).
    """

    points_m: F32
    blocks: npt.NDArray[np.int64]
    block_size: int
    scan: LaserScan


def detect_cliffs(
    depth: np.ndarray,
    intr: Intrinsics,
    mount: Mount,
    params: CliffParams,
    angle_min: float,
    angle_increment: float,
    n_bins: int,
) -> CliffResult:
    """Find steps down and holes in one depth image.

    Args:
        depth: (H, W) uint16 millimetres (0 = no reading) or float32 metres (NaN = none).
        intr: intrinsics of ``depth``.
        mount: sensor height, tilt (positive down) and roll (positive left side up).
        params: detector parameters.
        angle_min, angle_increment, n_bins: layout of the cliff scan (radians, radians, count);
            pass the obstacle scan's layout (``scan.scan_layout``) so the two line up.

    Returns:
        The detected blocks, the drop-offs' floor points (exact: their edges) and the cliff scan.

    Raises:
        FrameError: wrong dtype or shape. ConfigError: a layout or block size that does not fit.
    """
    check_range("cliff angle_min", angle_min, -math.pi - 1e-9, math.pi, " rad")
    check_range("cliff angle_increment", angle_increment, 1e-6, math.pi, " rad")
    check_int("cliff n_bins", n_bins, 1, MAX_CODE_INDEX)
    mm = depth_to_mm(depth, intr)
    t = cliff_table(intr, mount, params, float(angle_min), float(angle_increment), int(n_bins))
    if t.col_step:  # a view: sample column k is image column cols[0] + k * col_step
        src, rows = mm[:, int(t.cols[0]) : int(t.cols[-1]) + 1 : t.col_step], t.rows
    else:  # unevenly spaced sample columns: gather the samples once
        src, rows = mm[np.ix_(t.rows, t.cols)], np.arange(t.rows.size, dtype=np.intp)
    _, nj, _, ni = t.shape4
    out = np.empty(n_bins + 1, dtype=np.float32)  # + a scratch slot for runs covering no bin
    blocks, points = cliff_kernel(
        src,
        rows,
        nj,
        ni,
        t.lo_mm,
        np.uint16(t.hi_mm),
        t.range_m,
        t.block_ok,
        params.block_points_thresh,
        t.ev_block,
        t.ev_code,
        t.cov_start,
        t.cov_code,
        t.cov_lo_mm,
        t.cov_ob_mm,
        t.probe_start,
        t.probe_code,
        t.block_xy_m,
        intr.height,
        params.block_size,
        out,
        mm,
        t.row0,
        t.px_band_mm,
        t.px_xyt_m,
        t.px_bins,
        t.short,
        np.float32(params.range_min_m),
        params.method == "exact",
    )
    ranges = out[:-1]
    scan = LaserScan(
        float(angle_min),
        float(angle_min + (n_bins - 1) * angle_increment),
        float(angle_increment),
        params.range_min_m,
        params.range_max_m,
        ranges,
    )
    return CliffResult(points, blocks, params.block_size, scan)
