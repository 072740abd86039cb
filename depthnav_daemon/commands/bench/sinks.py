"""What ``depthnav bench`` times of the outputs: each sink's per-frame work on the recording's real
results, as the sink does it (building the messages, encoding them, writing a file where the sink
writes one).

- the JSON line of the stdout and udp sinks (made once a frame and shared by both);
- the rosbag sink writing a ROS 2 ``.mcap`` and a ROS 1 ``.bag`` (issue 13's budget: ~1 ms);
- the ros2 sink's encoding: its messages' CDR (sinks/ros/cdr.py), padded as it hands them to DDS
  (issue 13's budget: 0.22 ms; the DDS write itself is cyclonedds' and left out);
- the foxglove sink writing its channels to an ``.mcap``, without and with the depth image.

The files go to a temporary folder removed at the end.
"""

from __future__ import annotations

import contextlib
import logging
import tempfile
import time
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path

import orjson

from depthnav_daemon import __version__
from depthnav_daemon.commands.bench.stages import Work
from depthnav_daemon.config.loader import Config
from depthnav_daemon.errors import SinkError
from depthnav_daemon.pipeline import Result, StageParams, process
from depthnav_daemon.pipeline.geometry import Mount
from depthnav_daemon.sinks import create_sink
from depthnav_daemon.sinks.base import Sink, SinkContext
from depthnav_daemon.sinks.json import message as jsonmsg
from depthnav_daemon.sinks.ros.cdr import CdrEncoder
from depthnav_daemon.sinks.ros.messages import NAME_OPTIONS, MessageBuilder, RosNames, typestore
from drivers.base import DeviceInfo, Frame

BUDGETS_MS = {"rosbag": 1.0, "ros2": 0.22}  # issue 13


def frame_results(frames: Sequence[Frame], mount: Mount) -> list[tuple[Frame, Result]]:
    """Each frame with its Result as the daemon makes it (scan, cliff, obstacle pixels)."""
    cfg = Config()
    params = StageParams(scan=cfg.scan, cliff=cfg.cliff, obstacle_mask=True)
    return [(frame, process(frame, mount, params, clock=time.perf_counter)) for frame in frames]


@contextlib.contextmanager
def sink_work(frames: Sequence[Frame], mount: Mount) -> Iterator[list[Work]]:
    """The outputs' per-frame work over the frames in turn (see the module docstring); the sinks
    are open while the context lasts. An output whose library is missing is left out."""
    quiet = logging.getLogger("depthnav_daemon")
    level = quiet.level
    quiet.setLevel(logging.WARNING)  # the sinks' info lines are not the bench's output
    try:
        with _open_work(frames, mount) as work:
            yield work
    finally:
        quiet.setLevel(level)


@contextlib.contextmanager
def _open_work(frames: Sequence[Frame], mount: Mount) -> Iterator[list[Work]]:
    pairs = frame_results(frames, mount)
    context = SinkContext(
        DeviceInfo("bench", None, "bench", frames[0].intrinsics),
        Config().scan,
        16,
        __version__,
        mount,
    )
    with tempfile.TemporaryDirectory(prefix="depthnav-bench-") as tmp:
        folder = Path(tmp)
        opened: list[Sink] = []
        work = [Work("stdout/udp JSON line (as frame_line makes it)", _json_line(pairs))]
        for name, spec in (
            ("rosbag sink, ROS 2 .mcap (messages, CDR, write)", f"rosbag:{folder / 'b.mcap'}"),
            ("rosbag sink, ROS 1 .bag (messages, serialise, write)", f"rosbag:{folder / 'b.bag'}"),
            ("ros2 sink encoding (messages, CDR; no DDS write)", None),  # no sink: its encoder
            ("foxglove sink to .mcap, image=0", f"foxglove:{folder / 'f.mcap'}?image=0"),
            ("foxglove sink to .mcap, with the depth image", f"foxglove:{folder / 'g.mcap'}"),
        ):
            if spec is None:
                work.append(Work(name, _ros2_encode(pairs)))
                continue
            sink = _open(spec, context)
            if sink is not None:
                opened.append(sink)
                work.append(Work(name, _writes(sink, pairs)))
        try:
            yield work
        finally:
            for sink in opened:
                with contextlib.suppress(Exception):
                    sink.close()


def _open(spec: str, context: SinkContext) -> Sink | None:
    try:
        sink = create_sink(spec)
        sink.open(context)
    except (SinkError, ImportError):
        return None
    return sink


def _cycle(pairs: Sequence[tuple[Frame, Result]]) -> Callable[[], tuple[Frame, Result]]:
    i = [0]

    def nxt() -> tuple[Frame, Result]:
        i[0] = (i[0] + 1) % len(pairs)
        return pairs[i[0]]

    return nxt


def _json_line(pairs: Sequence[tuple[Frame, Result]]) -> Callable[[], object]:
    """How frame_line makes a frame's line (the message's dicts, orjson), made anew each call:
    frame_line itself returns the line it made for a Result."""
    nxt = _cycle(pairs)

    def line() -> bytes:
        frame, result = nxt()
        data = orjson.dumps(jsonmsg.frame_message(frame, result, __version__, time.time()))
        return data + b"\n"

    return line


def _writes(sink: Sink, pairs: Sequence[tuple[Frame, Result]]) -> Callable[[], object]:
    nxt = _cycle(pairs)
    return lambda: sink.write(*nxt())


def _ros2_encode(pairs: Sequence[tuple[Frame, Result]]) -> Callable[[], object]:
    """What sinks/ros/ros2.py does per frame before cyclonedds' write: its CdrEncoder (templates
    made on the first frame, as the sink makes them)."""
    builder = MessageBuilder(typestore(ros1=False), RosNames(dict(NAME_OPTIONS)))
    store = builder.store
    for msgtype in builder.msgtypes().values():
        store.get_msgdef(msgtype)  # as the sink does at open
    encoder = CdrEncoder(builder)
    nxt = _cycle(pairs)
    return lambda: encoder.encode(*nxt(), t_ns=time.time_ns())
