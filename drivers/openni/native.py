"""libOpenNI2 for the ``openni`` backend: found in the system's library folders (Debian:
``apt-get install libopenni2-0``) or ``DEPTHNAV_OPENNI2_REDIST``, and initialised once per process.

``openni2.initialize()`` wants ``libOpenNI2.so`` and the library looks for its drivers relative
to itself, so a private folder of two symlinks is built next to the system library.
"""

from __future__ import annotations

import logging
import os
import tempfile
import threading
from pathlib import Path
from typing import Any

from drivers.errors import DriverNotAvailable
from drivers.native import NATIVE_LIB_DIRS

log = logging.getLogger(__name__)

LIB_NAME = "libOpenNI2.so.0"

_init_lock = threading.Lock()
_state: dict[str, str] = {}  # "library": path once initialised in this process


def find_library() -> tuple[Path, Path] | None:
    """(libOpenNI2 path, its OpenNI2 folder with Drivers/), or None if not installed."""
    redist = os.environ.get("DEPTHNAV_OPENNI2_REDIST")
    if redist:
        lib = Path(redist) / "libOpenNI2.so"
        return (lib, Path(redist) / "OpenNI2") if lib.exists() else None
    for folder in NATIVE_LIB_DIRS:
        lib = Path(folder) / LIB_NAME
        if lib.exists() and (Path(folder) / "OpenNI2" / "Drivers").is_dir():
            return lib, Path(folder) / "OpenNI2"
    return None


def _private_dir(lib: Path, drivers_dir: Path) -> str:
    """A folder where ``libOpenNI2.so`` and ``OpenNI2`` point at the system copies."""
    folder = Path(tempfile.gettempdir()) / f"depthnav-openni2-{os.getuid()}"
    folder.mkdir(mode=0o700, exist_ok=True)
    for name, target in (("libOpenNI2.so", lib), ("OpenNI2", drivers_dir)):
        link = folder / name
        if link.is_symlink() and os.readlink(link) == str(target):
            continue
        tmp = folder / f".{name}.{os.getpid()}"
        tmp.unlink(missing_ok=True)
        os.symlink(target, tmp)
        os.replace(tmp, link)  # atomic, so two processes starting at once both succeed
    return str(folder)


def initialize() -> Any:
    """Load libOpenNI2 once per process and return the ``openni2`` module.

    Raises:
        DriverNotAvailable: the library or the ``openni`` package is missing or fails to load.
    """
    try:
        from openni import openni2
    except ImportError as exc:
        raise DriverNotAvailable(
            "the Python package 'openni' is not installed", hint="pip install openni"
        ) from exc
    with _init_lock:
        if "library" in _state:
            return openni2
        found = find_library()
        if found is None:
            raise DriverNotAvailable(
                f"libOpenNI2 not found (looked for {LIB_NAME} in {', '.join(NATIVE_LIB_DIRS)})",
                hint="apt-get install libopenni2-0, or set DEPTHNAV_OPENNI2_REDIST to an OpenNI2 "
                "Redist folder",
            )
        lib, drivers_dir = found
        folder = (
            str(lib.parent)
            if os.environ.get("DEPTHNAV_OPENNI2_REDIST")
            else _private_dir(lib, drivers_dir)
        )
        try:
            openni2.initialize(folder)  # note: chdir()s while loading; done once, under the lock
        except Exception as exc:  # ctypes/OpenNI raise several types here
            raise DriverNotAvailable(
                f"libOpenNI2 at {lib} failed to initialise: {exc}", hint="reinstall libopenni2-0"
            ) from exc
        _state["library"] = str(lib)
        log.debug("OpenNI2 initialised from %s", lib)
    return openni2
