"""``text``: one human-readable line per frame on stdout, for a person at a terminal.

Spec: ``text[?every=N]`` (print every Nth frame, default 1). For programs use ``stdout`` (JSON).
A line reads, for example (one line, cut here at "|")::

    #3  mount 0.550 m, tilt 15.0 deg, roll 0.0 deg (floor, floor confirmed)
        |  right 1.17 m @ -21 deg  ahead 1.98 m  left 1.45 m @ 21 deg
        |  drop-off 1.95 m @ 0 deg (12 blocks)

The brackets say where the mount came from (default, config, accel, serial, floor; "pinned"
when floor estimates may not replace it) and whether the floor confirms it. While it does not
trust the mount, the daemon writes "drop-off UNTRUSTED ..." and the reason at the end of the line.
"right/ahead/left" are the nearest obstacles in the scan's right third, middle third and left
third of bearings; "clear" means valid readings and nothing within range, "no data" no reading.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import numpy as np

from depthnav_daemon.errors import ConfigError
from depthnav_daemon.sinks.base import SinkSpec, check_options, number_option
from depthnav_daemon.sinks.json.stdout import StdoutSink

if TYPE_CHECKING:
    from depthnav_daemon.pipeline import Result
    from depthnav_daemon.pipeline.scan import LaserScan
    from drivers.base import Frame

GRAMMAR = "text[?every=N]"


def nearest(scan: LaserScan, lo_rad: float, hi_rad: float) -> str:
    """The nearest obstacle among bearings in [lo, hi), as text."""
    angles = scan.angles
    sel = (angles >= lo_rad) & (angles < hi_rad)
    r = scan.ranges[sel].astype(np.float64)
    if r.size == 0 or np.isnan(r).all():
        return "no data"
    if np.isneginf(r).any():
        return "too close"
    finite = np.isfinite(r)
    if not finite.any():
        return "clear"
    k = int(np.argmin(np.where(finite, r, np.inf)))
    return f"{r[k]:.2f} m @ {math.degrees(angles[sel][k]):.0f} deg"


class TextSink(StdoutSink):
    """Summary lines for people; the stream handling (broken pipe, flush) is the stdout sink's."""

    def __init__(self, name: str = "text", every: int = 1) -> None:
        super().__init__(name)
        self.every = every

    @classmethod
    def from_spec(cls, spec: SinkSpec) -> TextSink:  # type: ignore[override]
        """Build from a parsed spec (no I/O)."""
        check_options(spec, ("every",), GRAMMAR)
        if spec.target:
            raise ConfigError(
                f"the text sink takes no target, got {spec.text!r}", hint=f"write {GRAMMAR}"
            )
        return cls(spec.text, int(number_option(spec, "every", 1, 1, 1_000_000, integer=True)))

    def format(self, frame: Frame, result: Result) -> str | None:
        """One summary line, or None between every-th frames."""
        if frame.seq % self.every:
            return None
        m = result.mount
        scan = result.scan
        third = (scan.angle_max - scan.angle_min) / 3.0
        a0, a1 = scan.angle_min + third, scan.angle_min + 2 * third
        trust = result.mount_trust
        parts = [
            f"#{frame.seq}  mount {m.height_m:.3f} m, tilt {m.tilt_deg:.1f} deg, "
            f"roll {m.roll_deg:.1f} deg "
            f"({_mount_origin(result)})",
            f"right {nearest(scan, -math.inf, a0)}  ahead {nearest(scan, a0, a1)}  "
            f"left {nearest(scan, a1, math.inf)}",
        ]
        if result.cliff is not None:
            blocks = len(result.cliff.points_m)
            drop = nearest(result.cliff.scan, -math.inf, math.inf) if blocks else "none"
            doubtful = trust is not None and not trust.dropoffs_trusted
            flag = " UNTRUSTED" if blocks and doubtful else ""
            parts.append(f"drop-off{flag} {drop}" + (f" ({blocks} blocks)" if blocks else ""))
        if result.pose is not None and not result.pose.ok:
            parts.append(f"floor estimate failed: {result.pose.reason}")
        if result.warning:
            parts.append(result.warning)
        return "  |  ".join(parts)


def _mount_origin(result: Result) -> str:
    """Where the mount came from and what the floor says of it: "config, floor confirmed"."""
    trust = result.mount_trust
    if trust is None:
        return result.mount_source
    return f"{trust.source}{', pinned' if trust.pinned else ''}, floor {trust.floor}"
