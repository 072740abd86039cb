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

from depthnav_daemon.errors import ConfigError
from depthnav_daemon.sinks.base import Sink, SinkContext, SinkSpec, parse_sink_spec

__all__ = ["SINKS", "Sink", "SinkContext", "SinkSpec", "create_sink", "parse_sink_spec"]

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
