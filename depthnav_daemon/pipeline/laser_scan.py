"""LaserScan: the planar scan that both scan methods (scan.py, scan_paper.py) and the cliff detector
return, in a module of its own so that each builds it without importing another.

Range semantics (REP 117): a finite value is the nearest obstacle; +inf = valid readings but no
obstacle within range_max; -inf = an obstacle closer than range_min; NaN = no valid reading.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from depthnav_daemon.pipeline.geometry import F32, F64


@dataclass(frozen=True, slots=True)
class LaserScan:
    """A planar scan in the level frame at the sensor (x forward, y left), as sensor_msgs/LaserScan.

    ``ranges[i]`` is at bearing ``angle_min + i * angle_increment`` (radians, counter-clockwise from
    forward). Values follow REP 117 (see the module docstring).

    Attributes:
        ranges: (N,) float32 metres.
        far: (N,) float32 metres, the exact level scan's only: per bin the range of the farthest
            obstacle pixel it saw (-inf: none): the memory marks [ranges, far] as a place where
            something seen may stand that it did not keep. None elsewhere.
    """

    angle_min: float
    angle_max: float
    angle_increment: float
    range_min: float
    range_max: float
    ranges: F32
    far: F32 | None = None

    @property
    def angles(self) -> F64:
        """(N,) bearing of every range, radians."""
        return self.angle_min + self.angle_increment * np.arange(self.ranges.size)
