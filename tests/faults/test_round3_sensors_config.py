"""Round 3, part 2 (issue 35 items 4 and 7): several sensors whose device cannot open, and
sensor names that would reach the log raw. Through the CLI in a child process: the one line, the
exit code, the peak memory against a clean run, a prompt stop."""

from __future__ import annotations

import json
import signal
import time
from pathlib import Path

import pytest

from tests.faults import hostile
from tests.faults.kit import (
    FAST,
    depthnav_measured,
    finish,
    one_error_line,
    start,
    wait_until_ours,
)

MORE_MB = 50  # what a refused start-up may take beyond a clean run of the same sensors


def _config(tmp_path: Path, devices: list[str], extra: str = "") -> Path:
    text = extra + "".join(
        f'[[sensor]]\nname = "s{i}"\ndevice = "{d}"\n'
        f"[sensor.mount]\nyaw_deg = {i * 20 % 360 - 180}\n"
        for i, d in enumerate(devices)
    )
    path = tmp_path / "robot.toml"
    path.write_text(text)
    return path


@pytest.fixture(scope="module")
def clean_peak_mb(tmp_path_factory: pytest.TempPathFactory) -> float:
    """A clean run of two sensors (3 merged frames): the reference peak."""
    cfg = _config(tmp_path_factory.mktemp("clean"), [FAST, FAST])
    done = depthnav_measured("run", "--config", str(cfg), "--sink", "null", "--max-frames", "3")
    assert done.returncode == 0, done.stderr
    return done.peak_mb


@pytest.mark.parametrize(
    ("devices", "bad"),
    [
        ([FAST, "replay:/nonexistent"], "s1"),
        (["kinect://99", FAST], "s0"),
        ([FAST] * 7 + ["replay:/nonexistent/rec"] + [FAST] * 8, "s7"),  # 1 bad of 16
    ],
    ids=["missing recording", "kinect 99", "1 bad of 16"],
)
def test_a_sensor_that_cannot_open_ends_the_start_up_in_one_line(
    tmp_path: Path, clean_peak_mb: float, devices: list[str], bad: str
) -> None:
    """Before: the others delivered every frame, then 'internal error: RuntimeError: cannot join
    thread before it is started', exit 1. Now: one line naming the sensor, exit 1, nothing out."""
    cfg = _config(tmp_path, devices)
    done = depthnav_measured("run", "--config", str(cfg), "--sink", "stdout", "--max-frames", "3")
    assert done.returncode == 1, done.stderr
    line = one_error_line(done.stderr)
    assert f"sensor '{bad}'" in line, line
    assert "internal error" not in done.stderr and "depthnav: hint:" in done.stderr
    assert done.stdout == ""  # refused before any output: no merged scan without its bearings
    assert done.peak_mb < clean_peak_mb + MORE_MB, (done.peak_mb, clean_peak_mb)


def test_a_stop_while_waiting_for_a_sensor_is_prompt(tmp_path: Path) -> None:
    cfg = _config(tmp_path, [FAST, "kinect://99"], "[daemon]\nwait_for_device_s = 600\n")
    proc = start("run", "--config", str(cfg), "--sink", "stdout")
    wait_until_ours(proc)
    deadline = time.monotonic() + 60
    while "waiting for device kinect://99" not in Path(proc.stderr_path).read_text():  # type: ignore[attr-defined]
        assert proc.poll() is None and time.monotonic() < deadline, "never waited"
        time.sleep(0.05)
    t0 = time.monotonic()
    code, out, err = finish(proc, signal.SIGTERM)
    assert time.monotonic() - t0 < 1.0, err
    assert code == 0 and out == "" and "Traceback" not in err, err


@pytest.mark.parametrize("kind", sorted(hostile.HOSTILE_NAMES))
def test_a_sensor_name_is_refused_bounded_and_escaped(tmp_path: Path, kind: str) -> None:
    """Before: a newline, NUL or ESC in a name went raw into log lines, a 10 KB name in full."""
    name = hostile.HOSTILE_NAMES[kind]
    path = tmp_path / "robot.toml"
    path.write_text(
        f'[[sensor]]\nname = {json.dumps(name)}\ndevice = "{FAST}"\n'
        f'[[sensor]]\nname = "other"\ndevice = "{FAST}"\n'
    )
    done = depthnav_measured("run", "--config", str(path), "--sink", "null", "--max-frames", "1")
    assert done.returncode == 2, done.stderr
    line = one_error_line(done.stderr)
    assert "sensor 1: name" in line and len(line) < 200, line
    assert not any(c in done.stderr for c in "\x00\x1b\x07\x08\u202e"), repr(done.stderr)
    assert "\nERROR: forged" not in done.stderr  # the newline stayed escaped
    assert done.stderr.count("\n") == 2  # the error and its hint, nothing else


# --- [[sensor]] in the fuzz registry's classes: hostile numbers, nesting, names, encodings ------
from hypothesis import HealthCheck, given, settings  # noqa: E402
from hypothesis import strategies as st  # noqa: E402

from depthnav_daemon.config.loader import build_config  # noqa: E402
from depthnav_daemon.errors import ConfigError  # noqa: E402

MOUNT_KEYS = ("height_m", "tilt_deg", "roll_deg", "x_m", "y_m", "yaw_deg")
VALUES = st.one_of(
    st.sampled_from(hostile.HOSTILE_NUMBERS),
    st.sampled_from(hostile.NOT_ASCII_NUMBERS).map(json.dumps),
    st.integers(1, 3000).map(hostile.nested),
    st.floats(allow_nan=True, allow_infinity=True).map(repr),
)
NAMES = st.one_of(st.sampled_from(sorted(hostile.HOSTILE_NAMES.values())), st.text(max_size=80))


@settings(max_examples=120, derandomize=True, deadline=None,
          suppress_health_check=[HealthCheck.function_scoped_fixture])  # fmt: skip
@given(name=NAMES, key=st.sampled_from(MOUNT_KEYS), value=VALUES, utf16=st.booleans())
def test_hostile_sensor_tables_are_one_bounded_line(
    tmp_path: Path, name: str, key: str, value: str, utf16: bool
) -> None:
    text = (
        f'[[sensor]]\nname = {json.dumps(name)}\ndevice = "{FAST}"\n'
        f"[sensor.mount]\n{key} = {value}\n"
    )
    path = tmp_path / "robot.toml"
    path.write_bytes(text.encode("utf-16") if utf16 else text.encode("utf-8", "surrogatepass"))
    try:
        cfg = build_config([path])
    except ConfigError as exc:
        message = str(exc)
        assert "\n" not in message and len(message) < 400, message
        assert not any(not c.isprintable() for c in message), repr(message)
        return
    assert len(cfg.sensors) == 1 and len(cfg.sensors[0].name) <= 60
    assert cfg.sensors[0].name.isprintable()
