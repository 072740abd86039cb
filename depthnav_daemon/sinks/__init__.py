"""Output sinks: ``create_sink(spec)`` builds one from a spec string; ``SINKS`` names them all.

    stdout                               one JSON line per frame (docs/json_schema.md)
    text[?every=N]                       one human-readable summary line per frame
    udp://HOST:PORT                      the same JSON, one datagram per frame
    null                                 discard (throughput measurement)
    rerun | rerun+grpc://HOST:PORT | rerun:FILE.rrd    viewer / remote viewer / file
    mavlink:SERIALPORT?baud=N | mavlink+udp://HOST:PORT  OBSTACLE_DISTANCE + HEARTBEAT
    rosbag:FILE.mcap | rosbag:FILE.bag   ROS 2 / ROS 1 bag: /scan, /cliff/*, /tf, pose
    foxglove://HOST:PORT | foxglove:FILE.mcap   Foxglove live view (127.0.0.1:8765) / file
    ros2[?domain=N]                      live ROS 2 topics (DDS): /scan, /cliff/*, /tf, pose

Families with several modules have a subpackage: ``json/`` (stdout, udp and the line they
share), ``rerun/``, ``ros/`` (rosbag, ros2 and their messages), ``mavlink/``; a sink of one module
sits here (``text``, ``null``, ``foxglove``), beside ``base`` (the Sink protocol, spec parsing).

The grammar is ``scheme[://target][?key=value&...]`` (``scheme:target`` is shorthand); each sink
module's docstring gives its options. Modules are imported only when their sink is made, so
rerun and pymavlink load only when asked for.
"""

from __future__ import annotations

import importlib
import os
from collections.abc import Sequence

from depthnav_daemon.errors import ConfigError
from depthnav_daemon.sinks.base import Sink, SinkContext, SinkSpec, parse_sink_spec
from drivers.values import short_repr

__all__ = [
    "SINKS",
    "Sink",
    "SinkContext",
    "SinkSpec",
    "check_sink_set",
    "create_sink",
    "parse_sink_spec",
]

SINKS: dict[str, tuple[str, str]] = {  # scheme -> (module, class); imported only when used
    "stdout": ("depthnav_daemon.sinks.json.stdout", "StdoutSink"),
    "text": ("depthnav_daemon.sinks.text", "TextSink"),
    "udp": ("depthnav_daemon.sinks.json.udp", "UdpSink"),
    "null": ("depthnav_daemon.sinks.null", "NullSink"),
    "rerun": ("depthnav_daemon.sinks.rerun.rerun", "RerunSink"),
    "rerun+grpc": ("depthnav_daemon.sinks.rerun.rerun", "RerunSink"),
    "mavlink": ("depthnav_daemon.sinks.mavlink.mavlink", "MavlinkSink"),
    "mavlink+udp": ("depthnav_daemon.sinks.mavlink.mavlink", "MavlinkSink"),
    "rosbag": ("depthnav_daemon.sinks.ros.rosbag", "RosbagSink"),
    "foxglove": ("depthnav_daemon.sinks.foxglove", "FoxgloveSink"),
    "ros2": ("depthnav_daemon.sinks.ros.ros2", "Ros2Sink"),
}


def create_sink(text: str) -> Sink:
    """Build (but do not open) the sink named by a spec.

    Args:
        text: e.g. "stdout", "udp://127.0.0.1:5600", "rerun:run.rrd",
            "mavlink:/dev/ttyUSB0?baud=921600".

    Raises:
        ConfigError: unknown scheme (listing the valid ones), unknown option (listing the sink's
            valid ones) or a bad value.
    """
    spec = parse_sink_spec(text)
    if spec.scheme not in SINKS:
        known = ", ".join(sorted(SINKS))
        raise ConfigError(f"unknown sink {text!r}", hint=f"use one of: {known}")
    module_name, class_name = SINKS[spec.scheme]
    # the sink modules import their third-party packages lazily in open(), so this import is cheap
    module = importlib.import_module(module_name)
    sink: Sink = getattr(module, class_name).from_spec(spec)
    return sink


ONE_PER_PROCESS = {  # scheme -> why a second one is useless
    "ros2": "publishes the same topics again",
    "stdout": "writes every line twice into the one JSON stream",
}
FILE_SCHEMES = {"rerun": "file", "rosbag": "file", "foxglove": "file", "mavlink": "serial port"}


def check_sink_set(specs: Sequence[str]) -> None:
    """Refuse sink lists that would be quietly useless or fight: a second ``stdout`` or ``ros2``
    sink, or two sinks writing one file or serial port (a second writer of an ``.rrd`` is only
    refused once the first holds it; two writers on one serial port garble each other). Specs
    that do not parse are left to ``create_sink`` (its message names the problem); harmless
    repeats (``null``, ``text``, two ``udp`` sinks) are accepted.

    Raises:
        ConfigError: naming both specs (as ``short_repr`` shows them), with a hint.
    """
    seen: dict[tuple[str, str], str] = {}
    for text in specs:
        try:
            spec = parse_sink_spec(text)
        except ConfigError:
            continue
        if spec.scheme in ONE_PER_PROCESS:
            key, why = (
                (spec.scheme, ""),
                f"is a second {spec.scheme} sink: it would " + (ONE_PER_PROCESS[spec.scheme]),
            )
            hint = _HINTS[spec.scheme]
        elif spec.scheme in FILE_SCHEMES and spec.target and "://" not in text:
            what = FILE_SCHEMES[spec.scheme]
            key = (what, os.path.abspath(os.path.expanduser(spec.target)))
            why, hint = f"writes the same {what} as another sink", f"give each sink its own {what}"
        else:
            continue
        if key in seen:
            first = seen[key]
            raise ConfigError(f"sink {short_repr(text)} {why} ({short_repr(first)})", hint=hint)
        seen[key] = text


_HINTS = {
    "ros2": "one ros2 sink publishes every topic; its options rename them (e.g. scan_topic=)",
    "stdout": "give stdout once; udp:// or a file sink for a second copy",
}
