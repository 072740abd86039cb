"""What the service needs installed (issue 33 item 6): the kernels compiled into the unit's cache
and owned by the unit's user (``depthnav warmup``, scripts/install.sh), a cache that knows when
it is warm, the on-board UARTs allowed, and udev rules that win over Debian's own."""

from __future__ import annotations

import json
import os
import re
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from depthnav_daemon.daemon import kernel_cache
from depthnav_daemon.errors import DepthnavError

ROOT = Path(__file__).resolve().parents[2]
UNIT = ROOT / "configs" / "systemd" / "depthnav.service"
RULES = ROOT / "configs" / "udev" / "59-depthnav.rules"
INSTALL = ROOT / "scripts" / "install.sh"
WARMUP = (sys.executable, "-m", "depthnav_daemon", "warmup")


def _unit(key: str) -> list[str]:
    return [line.split("=", 1)[1] for line in UNIT.read_text().splitlines() if line.startswith(key)]


@pytest.fixture(scope="module")
def warm_cache() -> Path:
    """This user's kernel cache, warm (a second or two when scripts/install.sh ran)."""
    proc = subprocess.run([*WARMUP], capture_output=True, text=True, cwd=ROOT, timeout=900)
    assert proc.returncode == 0, proc.stderr
    return kernel_cache.cache_dir()


# --- the unit --------------------------------------------------------------------------------


def test_the_unit_caches_its_kernels_in_its_cache_directory_and_allows_the_usual_uarts() -> None:
    (cache,) = [e.split("=", 1)[1] for e in _unit("Environment=") if e.startswith("NUMBA_CACHE")]
    (directory,) = _unit("CacheDirectory=")
    assert cache.startswith(f"/var/cache/{directory}/")  # systemd makes it the unit user's
    allowed = set(_unit("DeviceAllow="))
    # USB adapters, a PC's UART, a Raspberry Pi's and a Jetson's: where flight controllers sit
    for group in ("ttyUSB", "ttyACM", "ttyS", "ttyAMA", "ttyTHS"):
        assert f"char-{group} rw" in allowed
    assert _unit("DevicePolicy=") == ["closed"]


# --- udev --------------------------------------------------------------------------------------

# Debian's libopenni2-0 (2.2.0.33+dfsg-15) /lib/udev/rules.d/60-libopenni2-0.rules, the lines for
# the devices depthnav opens (the package's file, when installed, is read instead)
DEBIAN_OPENNI2 = "\n".join(
    f'SUBSYSTEM=="usb", ATTR{{idProduct}}=="{product}", ATTR{{idVendor}}=="{vendor}", '
    'MODE:="0666", OWNER:="root", GROUP:="video"'
    for vendor, product in [
        *(("1d27", p) for p in ("0200", "0300", "0401", "0500", "0600", "0601", "0609")),
        *(("1d27", p) for p in ("1280", "2100", "2200", "f9db", "0400")),
        *(("045e", p) for p in ("02ae", "02ad", "02b0", "02be", "02bf", "02c2")),
    ]
)
# libfreenect0.5's 60-libfreenect0.5.rules (plain "=")
DEBIAN_FREENECT = "\n".join(
    f'SUBSYSTEM=="usb", ATTRS{{idVendor}}=="045e", ATTRS{{idProduct}}=="{p}", GROUP="plugdev", '
    'MODE="0666"'
    for p in ("02b0", "02ad", "02ae")
)
SYSTEM_RULES = Path("/lib/udev/rules.d")
_PAIR = re.compile(r'(\w+)(?:\{(\w+)\})?\s*(==|!=|:=|\+=|=)\s*"([^"]*)"')


def _apply(rules_dir: Path, device: dict[str, str]) -> dict[str, str]:
    """MODE, GROUP and OWNER of a USB device after every rule in ``rules_dir``, read the way
    udev reads them: files in lexical order of their names, a rule applies when all its
    matches do, "=" assigns unless an earlier ":=" made the key final, ":=" assigns and makes
    it final."""
    values: dict[str, str] = {}
    final: set[str] = set()
    for path in sorted(rules_dir.iterdir(), key=lambda p: p.name):
        for line in path.read_text().splitlines():
            if not line.strip() or line.lstrip().startswith("#"):
                continue
            pairs = _PAIR.findall(line)
            matches = [(k, a, v) for k, a, op, v in pairs if op == "=="]
            if not all(device.get(f"{k}{{{a}}}" if a else k) == v for k, a, v in matches):
                continue
            for key, _attr, op, value in pairs:
                if op in ("=", ":=") and key in ("MODE", "GROUP", "OWNER") and key not in final:
                    values[key] = value
                    if op == ":=":
                        final.add(key)
    return values


def _usb(vendor: str, product: str) -> dict[str, str]:
    # the device node: its own ATTR and, walking up, ATTRS (itself included)
    return {
        "SUBSYSTEM": "usb",
        "ATTR{idVendor}": vendor,
        "ATTR{idProduct}": product,
        "ATTRS{idVendor}": vendor,
        "ATTRS{idProduct}": product,
    }


def test_our_udev_rules_win_over_debians_libopenni2_and_libfreenect_rules(tmp_path: Path) -> None:
    rules = tmp_path / "rules.d"
    rules.mkdir()
    for name, text in (
        ("60-libopenni2-0.rules", DEBIAN_OPENNI2),
        ("60-libfreenect0.5.rules", DEBIAN_FREENECT),
    ):
        installed = SYSTEM_RULES / name
        (rules / name).write_text(installed.read_text() if installed.exists() else text)
    # without ours, Debian's gives every sensor to anyone (0666), the video group
    assert _apply(rules, _usb("045e", "02c2"))["MODE"] == "0666"
    shutil.copy(RULES, rules / RULES.name)  # as the README installs it
    ours = {"MODE": "0660", "GROUP": "plugdev"}
    devices = [("045e", p) for p in ("02ae", "02b0", "02ad", "02bf", "02be", "02c2")] + [
        ("1d27", "0600"),
        ("1d27", "0601"),
        ("2bc5", "0401"),
    ]
    for vendor, product in devices:
        got = _apply(rules, _usb(vendor, product))
        assert {k: got.get(k) for k in ours} == ours, (vendor, product, got)
    assert _apply(rules, _usb("1234", "5678")) == {}  # nothing else is touched
    # the old name lost to Debian's final assignments: the merged result proves the order counts
    old = rules / "60-depthnav.rules"
    old.write_text(RULES.read_text().replace(":=", "="))
    (rules / RULES.name).unlink()
    assert _apply(rules, _usb("045e", "02ae"))["MODE"] == "0666"


def test_the_readme_installs_the_rules_under_their_name() -> None:
    readme = (ROOT / "README.md").read_text()
    assert f"configs/udev/{RULES.name} /etc/udev/rules.d/{RULES.name}" in readme
    assert not (ROOT / "configs" / "udev" / "60-depthnav.rules").exists()


# --- the kernel cache ----------------------------------------------------------------------------


def test_the_cache_folder_is_the_one_the_kernels_use(tmp_path: Path) -> None:
    probe = (
        "import os, depthnav_daemon.pipeline._jit as j\n"
        "from depthnav_daemon.daemon.kernel_cache import cache_dir\n"
        "print(os.environ['NUMBA_CACHE_DIR'] == str(cache_dir()))"
    )
    base = {k: v for k, v in os.environ.items() if k not in ("NUMBA_CACHE_DIR", "XDG_CACHE_HOME")}
    for extra in ({}, {"XDG_CACHE_HOME": str(tmp_path)}, {"NUMBA_CACHE_DIR": str(tmp_path / "n")}):
        out = subprocess.run(
            [sys.executable, "-c", probe],
            capture_output=True,
            text=True,
            env={**base, **extra},
            cwd=ROOT,
            timeout=120,
        )
        assert out.stdout.strip() == "True", (extra, out.stderr)


def test_a_cache_is_warm_once_the_warm_up_finished_and_cold_again_when_a_kernel_changes(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    sources = tmp_path / "pipeline"
    sources.mkdir()
    kernel = sources / "scan_kernels.py"
    kernel.write_text("x = 1\n")
    monkeypatch.setattr(kernel_cache, "PIPELINE", sources)
    folder = tmp_path / "cache"
    folder.mkdir()
    assert not kernel_cache.is_warm(folder)  # nothing finished into it (or a killed warm-up)
    kernel_cache.mark_warm(folder)
    assert kernel_cache.is_warm(folder)
    fp = json.loads((folder / kernel_cache.MARKER).read_text())
    assert fp["cpu"] and fp["numba"] and fp["sources"] == [[kernel.name, *_stamp(kernel)]]
    kernel.write_text("x = 22\n")  # an upgrade or an edit: numba compiles again, so must we
    assert not kernel_cache.is_warm(folder)
    (folder / kernel_cache.MARKER).write_text("{not json")
    assert not kernel_cache.is_warm(folder)


def _stamp(p: Path) -> list[int]:
    st = p.stat()
    return [st.st_mtime_ns, st.st_size]


def test_an_unwritable_cache_is_one_line_with_a_hint(tmp_path: Path) -> None:
    blocked = tmp_path / "a-file"
    blocked.write_text("")
    with pytest.raises(DepthnavError) as info:
        kernel_cache.check_writable(blocked / "numba")
    assert "cannot write the kernel cache" in str(info.value) and "\n" not in str(info.value)
    assert "depthnav warmup --cache-dir" in (info.value.hint or "")


# --- depthnav warmup and the installer ---------------------------------------------------------


@pytest.mark.parametrize(
    ("args", "code", "needle"),
    [
        (["--owner", "no-such-user-here"], 2, "--owner no-such-user-here: no such user"),
        (["--cache-dir", "{file}/numba"], 1, "cannot write the kernel cache"),
    ],
)
def test_warmup_bad_input_is_one_clear_line(
    tmp_path: Path, args: list[str], code: int, needle: str
) -> None:
    (tmp_path / "f").write_text("")
    args = [a.replace("{file}", str(tmp_path / "f")) for a in args]
    proc = subprocess.run([*WARMUP, *args], capture_output=True, text=True, cwd=ROOT, timeout=120)
    lines = proc.stderr.strip().splitlines()
    assert proc.returncode == code, proc.stderr
    assert len(lines) == 2 and needle in lines[0] and lines[1].startswith("depthnav: hint: ")


@pytest.mark.skipif(os.geteuid() != 0, reason="gives files to another user: root only")
def test_the_installer_compiles_the_services_kernels_owned_by_the_units_user(
    tmp_path: Path, warm_cache: Path
) -> None:
    """scripts/install.sh's last part, as root, in a scratch copy: the unit's NUMBA_CACHE_DIR
    (here under tmp) is filled from this user's warm cache and given to the unit's User=."""
    import pwd

    nobody = pwd.getpwnam("nobody")
    work = tmp_path / "opt-depthnav"
    (work / "configs" / "systemd").mkdir(parents=True)
    service_cache = tmp_path / "var-cache" / "depthnav" / "numba"  # var-cache/depthnav is new
    unit = UNIT.read_text().replace("/var/cache/depthnav/numba", str(service_cache))
    (work / "configs" / "systemd" / "depthnav.service").write_text(
        unit.replace("User=depthnav", "User=nobody")
    )
    (work / ".venv" / "bin").mkdir(parents=True)
    for tool in ("python", "depthnav"):  # this venv's, called by their path there
        wrapper = work / ".venv" / "bin" / tool
        wrapper.write_text(f'#!/bin/sh\nexec "{Path(sys.executable).with_name(tool)}" "$@"\n')
        wrapper.chmod(0o755)
    text = INSTALL.read_text()
    tail = text[text.index("# compile the numeric kernels now") :]
    proc = subprocess.run(
        ["bash", "-euo", "pipefail", "-c", tail],
        capture_output=True,
        text=True,
        cwd=work,
        env={**os.environ, "NUMBA_CACHE_DIR": str(warm_cache)},
        timeout=900,
    )
    assert proc.returncode == 0, proc.stderr
    assert f"kernels ready in {service_cache}" in proc.stdout
    assert kernel_cache.is_warm(service_cache)
    owned = [service_cache.parent, *service_cache.rglob("*"), service_cache]
    assert len(owned) > 20 and all(p.lstat().st_uid == nobody.pw_uid for p in owned)
    assert (tmp_path / "var-cache").stat().st_uid == 0  # what existed stays as it was


def test_warmup_stops_at_once_mid_compile_and_the_next_one_goes_on(tmp_path: Path) -> None:
    cache = tmp_path / "numba"
    proc = subprocess.Popen(
        [*WARMUP, "--cache-dir", str(cache)], stderr=subprocess.PIPE, text=True, cwd=ROOT
    )
    assert proc.stderr is not None
    for line in proc.stderr:  # compiling now (the first kernel done, the next one under way)
        if "compiling kernels: 1/" in line:
            break
    t0 = time.monotonic()
    proc.send_signal(signal.SIGTERM)
    code = proc.wait(30)
    took = time.monotonic() - t0
    assert code == 0 and took < 1.0, took  # SIGTERM: a clean stop, as for every command
    assert not kernel_cache.is_warm(cache)  # not finished: the next start warms up again
    assert any(cache.rglob("*.nbi"))  # what was compiled stays, whole
