"""The tables' memory per pixel (scan_table.TABLE_BUDGET_B_PER_PX): the exact scan's and the
cliff stage's tables built for one camera in a fresh child process, whose peak resident memory
(VmHWM, reset through /proc/self/clear_refs after the imports and a small build that loads the
kernels) is read before and after each step. Run as a module it measures one size and prints JSON.
"""

from __future__ import annotations

import json
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path

SIZES = ((640, 480), (2048, 2048))  # the fixture's and a 4 M pixel camera (~200 MB at peak)
CHILD_TIMEOUT_S = 300


@dataclass(frozen=True)
class TableMemory:
    """Bytes per pixel of a ``resolution`` camera: ``rays`` the shared camera rays
    (geometry.pixel_rays), ``tables`` the tables' peak beyond them while building (kept tables and
    scratch: the budgeted figure), ``kept`` what the two tables hold once built, ``build_ms``."""

    resolution: str
    rays: float
    tables: float
    kept: float
    build_ms: float
    exact: bool  # the peak was reset (clear_refs); else an upper bound


def _status(key: str) -> int:
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith(key):
            return int(line.split()[1]) * 1024
    return 0


def _reset_peak() -> bool:
    try:
        Path("/proc/self/clear_refs").write_text("5")
    except OSError:
        return False
    return True


def measure(width: int, height: int) -> TableMemory:
    """Build the rays, then both tables, for a width x height pinhole camera at 0.5 m, 15 deg."""
    import dataclasses

    import numpy as np

    from depthnav_daemon.pipeline.cliff_table import cliff_table
    from depthnav_daemon.pipeline.geometry import Mount, pixel_rays
    from depthnav_daemon.pipeline.params import CliffParams, ScanParams
    from depthnav_daemon.pipeline.scan_table import exact_table
    from drivers.base import Intrinsics

    def build(intr: Intrinsics, cliff: CliffParams) -> tuple[object, object]:
        t = exact_table(intr, mount, ScanParams())
        return t, cliff_table(intr, mount, cliff, t.angle_min, t.angle_increment, t.n_bins)

    mount = Mount(0.5, 15.0, 0.0)
    small = Intrinsics(64, 64, 52.5, 52.5, 31.5, 31.5)  # loads the kernels
    build(small, CliffParams(used_depth_height=48, block_size=16))
    f = 525.0 * width / 640
    intr = Intrinsics(width, height, f, f, width / 2 - 0.5, height / 2 - 0.5)
    n = width * height
    base = _status("VmRSS")
    pixel_rays(intr)
    after_rays = _status("VmRSS")
    exact = _reset_peak()  # the rays' own building peak (their x, y on top) is theirs, not counted
    t0 = time.perf_counter()
    tables = build(intr, CliffParams())
    build_ms = (time.perf_counter() - t0) * 1e3
    peak = _status("VmHWM") - after_rays
    rays = after_rays - base
    kept = sum(
        v.nbytes
        for t in tables
        for fl in dataclasses.fields(t)  # type: ignore[arg-type]
        if isinstance(v := getattr(t, fl.name), np.ndarray)
    )
    return TableMemory(f"{width}x{height}", rays / n, peak / n, kept / n, build_ms, exact)


def table_memory(sizes: tuple[tuple[int, int], ...] = SIZES) -> list[TableMemory]:
    """``measure`` of each size, each in a fresh child process (its own peak, empty caches)."""
    out = []
    for w, h in sizes:
        run = subprocess.run(
            [sys.executable, "-m", __name__, str(w), str(h)],
            capture_output=True,
            text=True,
            timeout=CHILD_TIMEOUT_S,
            check=False,
        )
        if run.returncode != 0:
            raise RuntimeError(f"table memory at {w}x{h}: {run.stderr.strip()[-300:]}")
        out.append(TableMemory(**json.loads(run.stdout.splitlines()[-1])))
    return out


def format_table_memory(rows: list[TableMemory], budget: int) -> str:
    """The figures as the report's lines."""
    lines = [
        f"table bytes per pixel (exact scan + cliff, peak while building; budget {budget} B; "
        "beside them the camera rays they share):"
    ]
    for r in rows:
        bound = "" if r.exact else " (upper bound: peak not resettable here)"
        lines.append(
            f"  {r.resolution}: {r.tables:.1f} B/px at peak, {r.kept:.1f} B/px kept, rays "
            f"{r.rays:.1f} B/px; built in {r.build_ms:.0f} ms{bound}"
        )
    return "\n".join(lines)


if __name__ == "__main__":
    print(json.dumps(measure(int(sys.argv[1]), int(sys.argv[2])).__dict__))  # noqa: T201
