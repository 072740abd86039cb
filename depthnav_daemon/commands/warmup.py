"""``depthnav warmup [--cache-dir DIR] [--owner USER]``: compile every kernel the daemon can use
into a cache, so the daemon's first start compiles nothing (tools/warmup.py says what is run).

scripts/install.sh runs it for the service's cache (the unit's ``NUMBA_CACHE_DIR``, owned by the
unit's user); the daemon runs it in a child process when it finds its cache cold
(daemon/kernel_cache.py). A stop signal ends it at once (exit 0, 130 for Ctrl-C): numba writes
each cache file whole, and the next warm-up goes on from what is there.
"""

from __future__ import annotations

import argparse
import contextlib
import logging
import os
import signal
import sys
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path

from depthnav_daemon.commands.common import (
    EXIT_OK,
    STOP_SIGNALS,
    stop_signal_received,
    stopped_code,
)
from depthnav_daemon.errors import ConfigError, DepthnavError

log = logging.getLogger(__name__)

LOCK = "depthnav-warm.lock"


def cmd_warmup(args: argparse.Namespace) -> int:
    # a stop signal ends the process at once, compile or not: numba writes every cache file
    # whole (a temporary file renamed), so nothing half-written is left
    for sig in STOP_SIGNALS:
        signal.signal(sig, _stop_now)
    early = stop_signal_received()
    if early is not None:
        return stopped_code({"signal": early})
    owner = _owner(args.owner) if args.owner else None
    if args.cache_dir is not None:
        os.environ["NUMBA_CACHE_DIR"] = str(args.cache_dir.absolute())  # before numba's import
    from depthnav_daemon.daemon.kernel_cache import cache_dir, check_writable, is_warm, mark_warm

    folder = cache_dir()
    created = _missing_parents(folder)
    check_writable(folder)
    if owner is None and os.getuid() == 0 and args.cache_dir is not None:
        log.warning(
            "the kernels in %s belong to root: a service running as another user cannot use "
            "them (--owner USER gives them to it)",
            folder,
        )
    t0 = time.perf_counter()
    with _locked(folder):  # daemons started at once: one compiles, the others then find it warm
        if not is_warm(folder):
            _off_the_main_thread(lambda: (_compile(folder), mark_warm(folder)))
    if owner is not None:
        _give(folder, created, *owner)
    sys.stdout.write(f"kernels ready in {folder} ({time.perf_counter() - t0:.1f} s)\n")
    return EXIT_OK


def _stop_now(signum: int, _frame: object) -> None:
    sys.stderr.flush()
    os._exit(stopped_code({"signal": signum}))


def _off_the_main_thread(work: Callable[[], object]) -> None:
    """Run ``work`` on a thread while the main thread waits: numba's compile holds the
    interpreter for long stretches, which a signal handler on the compiling thread would wait
    for; the waiting main thread runs it within milliseconds (the compiling thread gives the
    interpreter up every switch interval, and inside LLVM)."""
    done = threading.Event()
    failed: list[BaseException] = []

    def run() -> None:
        try:
            work()
        except BaseException as exc:  # re-raised below, on the main thread
            failed.append(exc)
        finally:
            done.set()

    threading.Thread(target=run, name="warm-up", daemon=True).start()
    while not done.wait(0.1):
        pass
    if failed:
        raise failed[0]


def _compile(folder: Path) -> None:
    """Every kernel into ``folder`` (the tools/warm-up run), its progress said as it goes."""
    import importlib
    import pkgutil

    from depthnav_daemon import pipeline
    from depthnav_daemon.commands.common import progress_bar
    from depthnav_daemon.tools.warmup import warm_up, watch_compiles

    for mod in pkgutil.iter_modules(pipeline.__path__):  # every kernel counted from the start
        importlib.import_module(f"{pipeline.__name__}.{mod.name}")
    bar = progress_bar("compiling kernels", unit="kernels") if sys.stderr.isatty() else None

    def progress(done: int, total: int) -> None:
        if done == 0:
            log.info("compiling kernels into %s (tens of seconds per core, once)", folder)
        elif bar is not None:
            bar(done, total)
        else:
            log.info("compiling kernels: %d/%d", done, total)

    watch_compiles(progress)
    warm_up()


@contextlib.contextmanager
def _locked(folder: Path) -> Iterator[None]:
    """Hold the cache's warm-up lock (waiting for another warm-up to finish)."""
    import fcntl

    with open(folder / LOCK, "a") as fh:
        fcntl.flock(fh, fcntl.LOCK_EX)
        yield


def _owner(name: str) -> tuple[int, int]:
    """(uid, gid) of the user ``name`` (its own group).

    Raises:
        ConfigError: no such user, or this process cannot give files away (not root).
    """
    import pwd

    try:
        entry = pwd.getpwnam(name)
    except KeyError:
        raise ConfigError(
            f"--owner {name}: no such user on this system",
            hint="create the service's user first: sudo systemd-sysusers "
            "configs/systemd/depthnav.sysusers.conf",
        ) from None
    if os.getuid() not in (0, entry.pw_uid):
        raise ConfigError(
            f"--owner {name} needs root (this is user {os.getuid()})",
            hint=f"sudo depthnav warmup --cache-dir DIR --owner {name}",
        )
    return entry.pw_uid, entry.pw_gid


def _missing_parents(folder: Path) -> list[Path]:
    """``folder`` and those of its parents that do not exist yet (the warm-up creates them)."""
    out = []
    for p in (folder, *folder.parents):
        if p.exists():
            break
        out.append(p)
    return out


def _give(folder: Path, created: list[Path], uid: int, gid: int) -> None:
    """Every file and folder of the cache, and the folders made for it, to ``uid``:``gid``."""
    try:
        for p in created:
            os.chown(p, uid, gid)
        for root, dirs, files in os.walk(folder):
            os.chown(root, uid, gid)
            for name in dirs + files:
                os.lchown(os.path.join(root, name), uid, gid)
    except OSError as exc:
        raise DepthnavError(
            f"cannot give {folder} to uid {uid}: {exc.strerror or exc}",
            hint="run it as root (sudo)",
        ) from exc
