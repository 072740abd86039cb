"""create_sink(): grammar, registry, lazy imports, error messages; the null sink."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from depthnav_daemon.errors import ConfigError
from depthnav_daemon.sinks import SINKS, Sink, create_sink, parse_sink_spec
from depthnav_daemon.sinks.null import NullSink

ROOT = Path(__file__).resolve().parents[2]
EXAMPLES = {
    "stdout": "stdout",
    "text": "text?every=2",
    "udp": "udp://127.0.0.1:5600",
    "null": "null",
    "rerun": "rerun",
    "rerun+grpc": "rerun+grpc://127.0.0.1:9876",
    "mavlink": "mavlink:/dev/ttyUSB0?baud=921600",
    "mavlink+udp": "mavlink+udp://127.0.0.1:14550",
    "rosbag": "rosbag:run.mcap?compression=none",
    "foxglove": "foxglove://127.0.0.1:8765?image=0",
    "ros2": "ros2:?domain=7&tf=0",
}


def test_every_registered_sink_builds_and_follows_the_protocol():
    assert set(SINKS) == set(EXAMPLES)
    for scheme, spec in EXAMPLES.items():
        sink = create_sink(spec)
        assert isinstance(sink, Sink) and sink.name == spec
        module, cls = SINKS[scheme]
        assert (
            module.rsplit(".", 1)[1] == scheme.split("+")[0]
        )  # one module per sink, named after its key
        assert type(sink).__name__ == cls


def test_unknown_scheme_lists_valid_ones():
    with pytest.raises(ConfigError, match="unknown sink 'tcp://x:1'") as info:
        create_sink("tcp://x:1")
    for scheme in SINKS:
        assert scheme in info.value.hint
    assert info.value.exit_code == 2


def test_unknown_option_lists_valid_ones():
    with pytest.raises(ConfigError, match=r"valid options: .*\bmax_bytes\b"):
        create_sink("udp://127.0.0.1:1?maxbytes=3")


@pytest.mark.parametrize("text", ["", "  ", "://x", "udp://h:1?a", "udp://h:1?a=1&a=2", "1udp:x"])
def test_malformed(text):
    with pytest.raises(ConfigError):
        create_sink(text)


def test_grammar_forms():
    spec = parse_sink_spec("MAVLINK:///dev/ttyS0?Baud=57600&rate=%32%30")
    assert (spec.scheme, spec.target, dict(spec.options)) == (
        "mavlink",
        "/dev/ttyS0",
        {"baud": "57600", "rate": "20"},
    )
    assert parse_sink_spec("rerun:run.rrd").target == "run.rrd"
    assert parse_sink_spec("udp:5600").target == "5600"
    assert create_sink("udp:5600").port == 5600


def test_creating_sinks_does_no_heavy_imports_or_io():
    code = (
        "import sys, json; from depthnav_daemon.sinks import create_sink\n"
        f"specs = {list(EXAMPLES.values())!r}\n"
        "[create_sink(s) for s in specs]\n"
        "print(json.dumps(sorted(m for m in ('rerun', 'pymavlink', 'serial') if m in sys.modules)))"
    )
    out = subprocess.run(
        [sys.executable, "-c", code],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=60,
        check=True,
    )
    assert json.loads(out.stdout) == []


def test_null_sink(pairs, context):
    sink = create_sink("null")
    assert isinstance(sink, NullSink)
    sink.open(context)
    for frame, result in pairs:
        sink.write(frame, result)
    sink.close()
    sink.close()
    assert sink.frames == len(pairs)
    with pytest.raises(ConfigError):
        create_sink("null:x")
