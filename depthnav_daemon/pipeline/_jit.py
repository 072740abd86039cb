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

from llvmlite import ir
from numba import njit, types
from numba.core import cgutils
from numba.extending import intrinsic

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


@intrinsic
def prefetch(typingctx: Any, arr: Any, row: Any, col: Any) -> Any:
    """``prefetch(arr, row, col)`` in a kernel: ask the CPU to start loading the cache line of
    the 2-D array's element ``arr[row, col]`` (LLVM's prefetch: for reading, kept in every cache
    level), so that the loop finds it there a few rows later. A hint only: no value, no fault.

    For a row-by-row pass over a frame that is not in the cache (each new frame), whose work per
    row is too little for the CPU's own prefetcher to run far enough ahead.
    """
    if not (isinstance(arr, types.Array) and arr.ndim == 2):  # noqa: PLR2004 - 2-D only
        return None

    def codegen(context: Any, builder: Any, sig: Any, args: Any) -> Any:
        aty = sig.args[0]
        ary = context.make_array(aty)(context, builder, args[0])
        at = zip(args[1:], sig.args[1:], strict=True)
        inds = [context.cast(builder, v, t, types.intp) for v, t in at]
        ptr = cgutils.get_item_pointer2(
            context,
            builder,
            data=ary.data,
            shape=cgutils.unpack_tuple(builder, ary.shape),
            strides=cgutils.unpack_tuple(builder, ary.strides),
            layout=aty.layout,
            inds=inds,
            wraparound=False,
            boundscheck=False,
        )
        byte_ptr = builder.bitcast(ptr, ir.IntType(8).as_pointer())
        # the intrinsic's name carries its pointer type: "p0" with LLVM's opaque pointers
        # (llvmlite >= 0.45), "p0i8" before
        name = "llvm.prefetch.p0" if str(byte_ptr.type) == "ptr" else "llvm.prefetch.p0i8"
        i32 = ir.IntType(32)
        fnty = ir.FunctionType(ir.VoidType(), [byte_ptr.type, i32, i32, i32])
        fn = cgutils.get_or_insert_function(builder.module, fnty, name)
        # read (0), locality 3 (keep in every level), data cache (1)
        builder.call(fn, [byte_ptr, ir.Constant(i32, 0), ir.Constant(i32, 3), ir.Constant(i32, 1)])
        return context.get_dummy_value()

    return types.void(arr, row, col), codegen


__all__ = ["KERNELS", "helper", "inlined", "kernel", "prefetch"]
