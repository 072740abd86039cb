"""numba's ``njit`` with an on-disk cache in the user's cache folder.

The default cache lives in ``__pycache__`` beside the source, which an installed package may not be
allowed to write; compiled kernels are then rebuilt in every process (about a second). Setting the
folder before numba is imported keeps the cache per user and across runs (``scripts/install.sh``
fills it, so the daemon's first frame compiles nothing).
"""

from __future__ import annotations

import os
from collections.abc import Callable
from pathlib import Path
from typing import Any

os.environ.setdefault(
    "NUMBA_CACHE_DIR",
    str(Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache") / "depthnav" / "numba"),
)

from numba import njit

# Every kernel: compiled once, cached on disk, releases the GIL, no bounds checks in the hot loops.
_OPTIONS: dict[str, Any] = {
    "cache": True,
    "nogil": True,
    "boundscheck": False,
    "error_model": "numpy",
}
_njit = njit(**_OPTIONS)

KERNELS: list[Any] = []  # every kernel's dispatcher, so a first run can report its compiling


def kernel(fn: Callable[..., Any]) -> Any:
    """``fn`` compiled by numba (see above), registered in KERNELS."""
    dispatcher = _njit(fn)
    KERNELS.append(dispatcher)
    return dispatcher


def helper(fn: Callable[..., Any]) -> Any:
    """``fn`` compiled as above, for kernels to call (compiled into each caller, so not
    registered: the warm-up reaches it through them)."""
    return _njit(fn)


def inlined(fn: Callable[..., Any]) -> Any:
    """A helper that numba inlines into every caller before LLVM sees it: for small functions
    called per block of a row, where a call (its arrays passed field by field on the stack)
    costs as much as the work, and where the caller's loops vectorise better with it inline."""
    return njit(**_OPTIONS, inline="always")(fn)


__all__ = ["KERNELS", "helper", "inlined", "kernel"]
