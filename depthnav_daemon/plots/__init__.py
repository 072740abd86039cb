"""Figures from depthnav's own numbers (the paper's figs. 6, 7, 9, 11-13), drawn with matplotlib.

matplotlib is the optional extra ``depthnav[plot]``: only the commands that draw import this
package, never the daemon. Every figure is a ``matplotlib.figure.Figure`` (no pyplot, no global
state, no display); :func:`save` writes it as PNG or SVG, chosen by the file's extension.

Modules: ``mount_side`` (side view of one mount, eq. 15-16), ``sweep`` (dead zone and highest
visible obstacle against tilt, fig. 6), ``experiment`` (the box experiment, figs. 11-12),
``snapshot`` (one frame: depth image with overlays beside a top-down view, figs. 9 and 13).
"""

from __future__ import annotations

import io
import os
from pathlib import Path
from typing import TYPE_CHECKING, Any

from depthnav_daemon.errors import ConfigError, DepthnavError

if TYPE_CHECKING:
    from matplotlib.figure import Figure

FORMATS = {".png": "png", ".svg": "svg"}
DPI = 100  # a figure of 8 x 4.5 inches is 800 x 450 px: the README's width
INSTALL_HINT = "pip install 'depthnav[plot]' (or pip install matplotlib)"

# one palette for every figure and the viewer (sinks/rerun reads it through rgb()): strong
# colours over the depth palette (near = light, far = dark) and muted memory
COLORS = {
    "scan": "#00a651",  # green: the laser scan
    "obstacle": "#e8192c",  # red: obstacle pixels, "too close" (-inf) bearings
    "cliff": "#d400d4",  # magenta: drop-offs (their floor area, the cliff scan)
    "untrusted": "#ffaa00",  # amber: scan and drop-offs while the mount is not trusted
    "fov": "#4a90d9",  # blue: the field of view
    "dead": "#f5a623",  # orange: dead zones
    "robot": "#555555",  # dark grey: the robot
    "band": "#ffd400",  # yellow: the rows the scan reads
    "memory_obstacle": "#8c8c28",  # olive: remembered obstacles
    "memory_cliff": "#8c3c8c",  # plum: remembered drop-offs
    "memory_scan": "#1fa8a8",  # teal: the memory's 360 deg scan
    "floor": "#00c8ff",  # cyan: floor estimates (against the mount in use)
    "no_reading": "#64738c",  # blue-grey: pixels without a depth reading
}
DEPTH_CMAP = "inferno"  # drawn reversed: near = light yellow, far (range_max and beyond) = black


def rgb(name: str) -> tuple[int, int, int]:
    """A palette colour as 0-255 (R, G, B), for the viewer."""
    h = COLORS[name].lstrip("#")
    return int(h[0:2], 16), int(h[2:4], 16), int(h[4:6], 16)


def check_output(path: Path | str, option: str) -> tuple[Path, str]:
    """Where a figure goes and its format, checked before any work is done.

    Args:
        path: the file to write, ending in .png or .svg.
        option: the command-line option that named it, for messages.

    Returns:
        The path and the matplotlib format name ("png" or "svg").

    Raises:
        ConfigError: another extension, a folder that does not exist, or a directory.
        DepthnavError: matplotlib is not installed.
    """
    p = Path(path)
    fmt = FORMATS.get(p.suffix.lower())
    if fmt is None:
        raise ConfigError(
            f"{option} {str(p)!r}: cannot tell the format from the name (accepted: .png, .svg)",
            hint=f"name the file like {p.stem or 'figure'}.png or {p.stem or 'figure'}.svg",
        )
    if p.is_dir():
        raise ConfigError(
            f"{option} {str(p)!r} is a directory", hint="give a file name inside it, e.g. x.png"
        )
    parent = p.parent if str(p.parent) else Path(".")
    if not parent.is_dir():
        raise ConfigError(
            f"{option} {str(p)!r}: folder {str(parent)!r} does not exist",
            hint=f"create it first (mkdir -p {parent})",
        )
    _require_matplotlib()
    return p, fmt


def _require_matplotlib() -> None:
    try:
        import matplotlib  # noqa: F401  (only whether it imports)
    except ModuleNotFoundError:
        raise DepthnavError(
            "drawing figures needs matplotlib, which is not installed", hint=INSTALL_HINT
        ) from None


def new_figure(width_in: float, height_in: float, **kw: Any) -> Figure:
    """A figure that belongs to no GUI and no pyplot state.

    Raises:
        DepthnavError: matplotlib is not installed.
    """
    _require_matplotlib()
    from matplotlib.figure import Figure

    return Figure(figsize=(width_in, height_in), dpi=DPI, layout="constrained", **kw)


def render(fig: Figure, fmt: str) -> bytes:
    """The figure's file contents in ``fmt`` (PNG metadata without a date, so builds repeat)."""
    buf = io.BytesIO()
    meta = {"Software": None} if fmt == "png" else {"Date": None}
    fig.savefig(buf, format=fmt, dpi=DPI, metadata=meta)
    return buf.getvalue()


def save(fig: Figure, path: Path | str, option: str = "--plot") -> Path:
    """Write ``fig`` to ``path`` (PNG or SVG by extension); nothing is left behind on failure.

    Raises:
        ConfigError: see :func:`check_output`.
        DepthnavError: the file cannot be written (read-only place, disk full, ...).
    """
    p, fmt = check_output(path, option)
    data = render(fig, fmt)
    try:
        with open(p, "wb") as fh:
            fh.write(data)
    except OSError as exc:
        if p.is_file() and not p.is_symlink():
            _remove_partial(p)
        raise DepthnavError(
            f"cannot write {option} {str(p)!r}: {exc.strerror or type(exc).__name__}",
            hint="choose a writable place with free space",
        ) from None
    return p


def _remove_partial(p: Path) -> None:
    """Remove a half-written figure (best effort)."""
    try:
        os.unlink(p)
    except OSError:
        pass
