"""The TUM RGB-D layout, recognised by its structure: its depth scale (5000 units per metre) is
the format's definition, so a folder laid out as TUM's is read at it, said in one INFO line.

TUM RGB-D (and the tools that convert bags to its form) ship::

    rgb.txt  rgb/  depth.txt  depth/  (accelerometer.txt, groundtruth.txt)

with ``depth.txt`` reading::

    # depth maps
    # file: 'rgbd_dataset_freiburg1_xyz.bag'
    # timestamp filename
    1305031102.160407 depth/1305031102.160407.png

A folder is TUM when depth.txt's lines all name ``depth/*.png`` in a ``depth/`` folder, and either
its header names a TUM dataset bag (``rgbd_dataset_``) or it has TUM's header form (the lines
above, any bag named) beside ``rgb.txt`` and ``rgb/``. A folder with part of this (depthnav's own
``# depth maps written by depthnav`` folders, a depth.txt without rgb.txt) is not assumed to be
5000: a wrong scale is wrong everywhere downstream, so it is refused with the ``scale=`` hint.
"""

from __future__ import annotations

import os
from pathlib import Path

from drivers.files import INDEX_MAX_BYTES, read_bytes

INDEX = "depth.txt"
TUM_SCALE = 5000.0  # depth units per metre, TUM RGB-D's definition
TUM_MARK = "rgbd_dataset_"  # TUM RGB-D's depth.txt names its bag: "# file: 'rgbd_dataset_..."
_FIRST = "# depth maps"  # TUM's header, first line
_COLUMNS = "# timestamp filename"  # TUM's header, last line; "# file: '<bag>'" may come between
_BAG = "# file:"


def _header_and_lines(index: Path) -> tuple[list[str], list[str]]:
    """depth.txt's comment lines before its first entry (whitespace collapsed, lower case) and
    its entries (stripped)."""
    text = read_bytes(index, what="frame index", max_bytes=INDEX_MAX_BYTES)
    header: list[str] = []
    lines: list[str] = []
    for raw in text.decode("utf-8", errors="replace").splitlines():
        line = raw.strip()
        if line.startswith("#"):
            if not lines:
                header.append(" ".join(line.lower().split()))
        elif line:
            lines.append(line)
    return header, lines


def _names_depth_pngs(lines: list[str]) -> bool:
    """True if every entry is ``<timestamp> depth/<name>.png``."""
    for line in lines:
        parts = line.split()
        if len(parts) < 2 or not parts[1].startswith("depth/"):  # noqa: PLR2004
            return False
        if not parts[1].lower().endswith(".png"):
            return False
    return bool(lines)


def recognise_tum(folder: Path) -> tuple[bool, str]:
    """(True, how it was recognised) for a TUM RGB-D folder; (False, what is not TUM about it)
    for a folder with a depth.txt that looks partly like TUM's; (False, "") otherwise."""
    index = folder / INDEX
    if not os.path.lexists(index):
        return False, ""
    header, lines = _header_and_lines(index)
    marked = any(TUM_MARK in line for line in header)
    form = (
        len(header) >= 2  # noqa: PLR2004 - first and last line
        and header[0] == _FIRST
        and header[-1] == _COLUMNS
        and all(line.startswith(_BAG) for line in header[1:-1])
    )
    entries = _names_depth_pngs(lines) and (folder / "depth").is_dir()
    rgb = os.path.lexists(folder / "rgb.txt") and (folder / "rgb").is_dir()
    if entries and marked:
        return True, "depth.txt names a TUM RGB-D dataset bag"
    if entries and form and rgb:
        return True, "rgb.txt, rgb/, depth.txt and depth/ in TUM RGB-D's form"
    if not (entries or form or marked):
        return False, ""
    missing = []
    if not form and not marked:
        missing.append(f"depth.txt's header is not TUM's ('{_FIRST}' .. '{_COLUMNS}')")
    if not entries:
        missing.append("its lines do not all name depth/*.png in a depth/ folder")
    if not rgb and not marked:
        missing.append("no rgb.txt and rgb/ beside it")
    return False, "laid out partly as TUM RGB-D (5000 units per metre) but " + "; ".join(missing)
