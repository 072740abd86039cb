"""``depthnav devices`` and ``depthnav info``: what can be opened here, and versions."""

from __future__ import annotations

import argparse
import sys

from depthnav_daemon import __version__
from depthnav_daemon.commands.common import EXIT_OK


def cmd_devices(_args: argparse.Namespace) -> int:
    from drivers import detect_devices

    found = detect_devices()
    if not found:
        print("no devices found (a recording plays with --device replay:PATH)")  # noqa: T201
    for spec, description in found:
        print(f"{spec:<28} {description}")  # noqa: T201
    return EXIT_OK


def cmd_info(_args: argparse.Namespace) -> int:
    import platform

    import numpy as np

    from drivers import describe_backends

    lines = [
        f"depthnav {__version__}",
        f"python {platform.python_version()} ({sys.executable})",
        f"numpy {np.__version__}",
    ]
    for mod in ("numba", "rerun", "pymavlink", "serial", "usb", "openni", "PIL"):
        try:
            m = __import__(mod)
            lines.append(f"{mod} {getattr(m, '__version__', getattr(m, 'VERSION', 'present'))}")
        except ImportError:
            lines.append(f"{mod} missing")
    lines += [f"driver {name}: {status}" for name, status in describe_backends()]
    print("\n".join(lines))  # noqa: T201
    return EXIT_OK
