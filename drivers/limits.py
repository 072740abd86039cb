"""The largest image depthnav takes, set from the memory its processing needs.

Every image is at most MAX_IMAGE_SIDE pixels each way (drivers.base), and at most
``max_image_pixels()`` pixels in all: the daemon's per-image tables (the exact scan's geometry
and the cliff blocks, built once per image size and mount) take about TABLE_BYTES_PER_PIXEL bytes
a pixel (measured: 186 B/pixel at 1024x1024 and at 2048x2048, scan and cliff, tilt 10 deg), and
they may use at most MEMORY_SHARE of the machine's memory (its RAM, or the cgroup's limit when
lower). Readers check an image's size from its header, before decoding anything.
"""

from __future__ import annotations

import functools
import os
from pathlib import Path

from drivers.base import MAX_IMAGE_SIDE

TABLE_BYTES_PER_PIXEL = 200
MEMORY_SHARE = 0.5
_CGROUP_LIMIT = Path("/sys/fs/cgroup/memory.max")


def memory_bytes() -> int:
    """The memory this process may use: RAM, or the cgroup (v2) limit when that is lower."""
    ram = os.sysconf("SC_PHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
    try:
        text = _CGROUP_LIMIT.read_text().strip()
    except OSError:
        return ram
    return min(ram, int(text)) if text.isascii() and text.isdigit() else ram


@functools.cache
def max_image_pixels(memory: int | None = None) -> int:
    """Pixels of the largest image whose tables fit MEMORY_SHARE of ``memory`` bytes (default:
    this machine's), and never more than MAX_IMAGE_SIDE squared."""
    mem = memory_bytes() if memory is None else memory
    return max(1, min(MAX_IMAGE_SIDE**2, int(mem * MEMORY_SHARE) // TABLE_BYTES_PER_PIXEL))


def image_size_problem(width: int, height: int, memory: int | None = None) -> str | None:
    """Why a ``width`` x ``height`` image is too big for depthnav here, or None if it is not."""
    if not (1 <= width <= MAX_IMAGE_SIDE and 1 <= height <= MAX_IMAGE_SIDE):
        return (
            f"a {width}x{height} image is outside 1..{MAX_IMAGE_SIDE} pixels each way, "
            "the largest image depthnav takes"
        )
    limit = max_image_pixels(memory)
    if width * height > limit:
        mem = memory_bytes() if memory is None else memory
        return (
            f"a {width}x{height} image ({width * height} pixels) needs about "
            f"{width * height * TABLE_BYTES_PER_PIXEL / 1e9:.1f} GB for the scan and cliff "
            f"tables; this machine's {mem / 1e9:.1f} GB allow {limit} pixels"
        )
    return None
