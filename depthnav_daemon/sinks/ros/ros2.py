"""``ros2``: publish every frame's scans, cliff points, transforms and pose as live ROS 2 topics.

Spec: ``ros2[:][?domain=N&tf=0|1&image=0|1&<names>]``. The topics and messages are the
``rosbag`` sink's (sinks/ros/messages.py: ``/scan``, ``/cliff/scan``, ``/cliff/points``, ``/tf``,
``/depth_sensor_pose``, and with ``image=1`` the depth image and its CameraInfo), published
straight on DDS with Cyclone DDS (the ``cyclonedds`` package: ``pip install 'depthnav[ros2]'``),
so no ROS installation is needed and any ROS 2 node on the same domain subscribes as to another
ROS 2 node (``ros2 topic echo /scan``, Nav2, RViz), whatever its middleware (rmw_cyclonedds,
rmw_fastrtps).

What makes it ROS 2 on the wire (as rmw_cyclonedds and rmw_fastrtps do it):
    topic ``/scan`` is the DDS topic ``rt/scan``; type ``sensor_msgs/msg/LaserScan`` is the DDS
    type ``sensor_msgs::msg::dds_::LaserScan_`` (final structs: XTypes type information as
    rmw_cyclonedds gives it, peers without XTypes match on the name); samples are plain CDR
    (XCDR1, little-endian) serialised by ``rosbags`` from the same messages as the bags;
    each writer's USER_DATA holds ``typehash=RIHS01_<sha256>;`` (REP 2016, what Iron and later
    compare); QoS RELIABLE, VOLATILE, KEEP_LAST 5, so reliable subscribers (the ROS default) and
    best-effort ones (the sensor-data profile) both match.

Options:
    domain: the DDS domain, 0..232 (default: $ROS_DOMAIN_ID, else 0).
    tf, image, grid_rate, odom_tf, names: as the rosbag sink (``scan_topic=/depth/scan``,
        ``base_frame=base_footprint``; relative names resolve against ``/``). With the obstacle
        memory on, its topics (``/memory/grid``, ``/memory/scan``, ``/memory/cliff/points``) get
        their writers at its first frame.

    stamp: ``wall`` (default): each message is stamped with the wall clock when it is published
        (ROS time, which Nav2 compares against its transforms); ``recording``: with the frame's
        own time, the recording's stamps (a replay, an ``.oni`` or a ``file=`` recording only: a
        live device's clock is monotonic, not ROS time), for nodes run with ``use_sim_time``.
    clock: 1 publishes ``/clock`` (``rosgraph_msgs/msg/Clock``, the frame's time, once per frame
        before its messages) so ``use_sim_time`` nodes follow the replay; default 1 with
        ``stamp=recording``, refused with ``stamp=wall``.

The bags keep the frames' own times. Cyclone DDS reads its configuration from
``CYCLONEDDS_URI`` as for a ROS 2 node (network interface, peers). Publishing never waits for a
subscriber: a KEEP_LAST writer drops the oldest unacknowledged sample instead of blocking, and
``max_blocking_time`` is 0.
"""

from __future__ import annotations

import logging
import os
import re
import time
from typing import TYPE_CHECKING, Any

from depthnav_daemon.errors import ConfigError, SinkError
from depthnav_daemon.sinks.base import (
    RateLimitedLog,
    SinkContext,
    SinkSpec,
    bool_option,
    check_options,
    number_option,
)
from depthnav_daemon.sinks.ros.cdr import CdrEncoder
from depthnav_daemon.sinks.ros.memory_out import MemoryMessages
from depthnav_daemon.sinks.ros.messages import (
    NAME_OPTIONS,
    OPTIONS,
    MessageBuilder,
    RosNames,
    stamp_ns,
    typestore,
)
from drivers.values import short_repr

if TYPE_CHECKING:
    from depthnav_daemon.pipeline import Result
    from drivers.base import Frame

log = logging.getLogger(__name__)

GRAMMAR = (
    "ros2[?domain=0..232&stamp=wall|recording&clock=0|1&tf=0|1&image=0|1&cliff_z=-0.05"
    "&grid_rate=2&odom_tf=0|1&base_frame=..&scan_topic=..]"
)
STAMPS = ("wall", "recording")
CLOCK_TOPIC = "/clock"
CLOCK_TYPE = "rosgraph_msgs/msg/Clock"
TIME_TYPE = "builtin_interfaces/msg/Time"
MAX_DOMAIN = 232  # the highest domain whose RTPS ports (7400 + 250 * domain + ...) fit in 16 bits
HISTORY_DEPTH = 5
PIP_HINT = "pip install 'depthnav[ros2]'"
WHEELS = (
    "cyclonedds has wheels for x86_64 only; elsewhere build Cyclone DDS from source, set "
    "CYCLONEDDS_HOME and pip install cyclonedds"
)
# ROS 2 names (rcl): tokens of letters, digits and _, not starting with a digit, joined by /
_ROS_NAME = re.compile(r"/?[A-Za-z_][A-Za-z0-9_]*(/[A-Za-z_][A-Za-z0-9_]*)*\Z")
_BASE = {  # ROS 2 primitive -> cyclonedds.idl.types name (byte and char are uint8, as rmw does)
    "bool": "bool", "byte": "uint8", "char": "uint8", "int8": "int8", "uint8": "uint8",
    "int16": "int16", "uint16": "uint16", "int32": "int32", "uint32": "uint32",
    "int64": "int64", "uint64": "uint64", "float32": "float32", "float64": "float64",
}  # fmt: skip


def dds_topic(ros_name: str, spec_text: str) -> str:
    """The DDS topic of a ROS 2 topic name: ``/cliff/scan`` -> ``rt/cliff/scan``.

    Raises:
        ConfigError: not a valid ROS 2 topic name.
    """
    if not _ROS_NAME.match(ros_name):
        raise ConfigError(
            f"topic {ros_name!r} in sink spec {spec_text!r} is not a ROS 2 topic name",
            hint="letters, digits, _ and /, each part not starting with a digit, e.g. /depth/scan",
        )
    return "rt/" + ros_name.lstrip("/")


def dds_type_name(msgtype: str) -> str:
    """``sensor_msgs/msg/LaserScan`` -> ``sensor_msgs::msg::dds_::LaserScan_``."""
    package, kind, name = msgtype.split("/")
    return f"{package}::{kind}::dds_::{name}_"


class IdlTypes:
    """cyclonedds IdlStruct classes made from a rosbags typestore's definitions, one per message
    type (nested ones included), named and laid out as ROS 2's IDL: they give DDS the type name
    and XTypes type information; the samples themselves are rosbags' CDR."""

    def __init__(self, store: Any) -> None:
        from cyclonedds.idl import types

        self.store = store
        self.types = types
        self.classes: dict[str, Any] = {}

    def get(self, msgtype: str) -> Any:
        if msgtype not in self.classes:
            from cyclonedds.idl import make_idl_struct

            _, fields = self.store.fielddefs[msgtype]
            members = {name: self._field(desc) for name, desc in fields}
            name = msgtype.rsplit("/", 1)[-1] + "_"
            self.classes[msgtype] = make_idl_struct(name, dds_type_name(msgtype), members)
        return self.classes[msgtype]

    def _field(self, desc: tuple[Any, Any]) -> Any:
        from rosbags.typesys.store import Nodetype

        node, arg = desc
        t = self.types
        if node == Nodetype.BASE:
            name, bound = arg
            if name == "string":
                return t.bounded_str[bound] if bound else str
            return bool if name == "bool" else getattr(t, _BASE[name])
        if node == Nodetype.NAME:
            return self.get(arg)
        sub, size = arg
        if node == Nodetype.ARRAY:
            return t.array[self._field(sub), size]
        return t.sequence[self._field(sub), size] if size else t.sequence[self._field(sub)]


def plays_a_recording(device_spec: str) -> bool:
    """Whether a device spec plays a recording (its frames carry the recording's times): a
    ``replay:`` source, an ``openni:`` ``.oni`` file, or any device given ``file=``."""
    scheme, _, rest = device_spec.partition(":")
    if scheme == "replay":
        return True
    if scheme == "openni" and rest.split("?")[0].lower().endswith(".oni"):
        return True
    return "file=" in device_spec.partition("?")[2]


def _import_cyclonedds() -> Any:
    try:
        import cyclonedds.domain
        import cyclonedds.pub
        import cyclonedds.topic
    except ImportError as exc:
        if (exc.name or "cyclonedds").split(".")[0] == "cyclonedds":  # not installed
            raise SinkError(
                f"the ros2 sink needs the cyclonedds package, which is not installed: {PIP_HINT} "
                f"({WHEELS})",
                hint=PIP_HINT,
            ) from None
        raise SinkError(  # installed, but its C library or a dependency does not load
            f"the ros2 sink cannot load cyclonedds: {exc}", hint=f"reinstall it: {PIP_HINT}"
        ) from None
    return cyclonedds


class Ros2Sink:
    """Publishes each frame's messages on ROS 2 DDS topics (see the module docstring)."""

    def __init__(
        self, name: str, domain: int, names: RosNames, stamp: str = "wall", clock: bool = False
    ) -> None:
        self.name = name
        self.domain = domain
        self.names = names
        self.stamp = stamp
        self.clock = clock
        self.topics = {  # ROS topic -> DDS topic, checked now so a bad name fails before open
            names[key]: dds_topic(names[key], name)
            for key in NAME_OPTIONS
            if key.endswith("_topic")
        }
        if clock:
            if CLOCK_TOPIC in self.topics:
                raise ConfigError(
                    f"sink spec {name!r} names a topic {CLOCK_TOPIC}, which clock=1 publishes",
                    hint="give that topic another name, or clock=0",
                )
            self.topics[CLOCK_TOPIC] = dds_topic(CLOCK_TOPIC, name)
        seen: dict[str, str] = {}
        for ros_topic, dds in self.topics.items():
            if dds in seen:
                raise ConfigError(
                    f"topics {seen[dds]!r} and {ros_topic!r} in sink spec {name!r} "
                    "are the same ROS 2 topic",
                    hint="give each topic its own name",
                )
            seen[dds] = ros_topic
        self._participant: Any = None
        self._writers: dict[str, Any] = {}  # ROS topic -> DataWriter
        self._builder: MessageBuilder | None = None
        self._encoder: CdrEncoder | None = None
        self._write: Any = None
        self._memory: MemoryMessages | None = None
        self._memory_types: dict[str, str] = {}
        self._add_writer: Any = None
        self._clock_msg: tuple[Any, Any] | None = None  # (Clock, Time) classes with clock=1
        self.failures = RateLimitedLog(log)
        self.samples = 0

    @classmethod
    def from_spec(cls, spec: SinkSpec) -> Ros2Sink:
        """Build from a parsed spec (no I/O). Raises ConfigError for a bad option or name."""
        check_options(spec, ("domain", "stamp", "clock", *OPTIONS), GRAMMAR)
        if spec.target.strip("/"):
            raise ConfigError(
                f"sink spec {spec.text!r}: ros2 takes no target, only options",
                hint="e.g. ros2 or ros2:?domain=7",
            )
        env = "" if "domain" in spec.options else os.environ.get("ROS_DOMAIN_ID", "").strip()
        if env and not (env.isdigit() and int(env) <= MAX_DOMAIN):
            raise ConfigError(
                f"ROS_DOMAIN_ID={env!r} is not a domain id 0..{MAX_DOMAIN}",
                hint="fix or unset ROS_DOMAIN_ID, or give the sink domain=N",
            )
        default = int(env) if env else 0
        domain = int(number_option(spec, "domain", default, 0, MAX_DOMAIN, integer=True))
        stamp = spec.options.get("stamp", "wall").strip()
        if stamp not in STAMPS:
            raise ConfigError(
                f"sink spec {spec.text!r}: stamp={short_repr(stamp)} is not one of "
                f"{', '.join(STAMPS)}",
                hint="stamp=wall (live, the default) or stamp=recording (a replay's own times)",
            )
        recording = stamp == "recording"
        clock = bool_option(spec, "clock", recording)
        if clock and not recording:
            raise ConfigError(
                f"sink spec {spec.text!r}: clock=1 publishes the frames' own time, which only "
                "stamp=recording uses",
                hint="add stamp=recording (replay with use_sim_time), or leave clock out",
            )
        return cls(spec.text, domain, RosNames.from_spec(spec), stamp, clock)

    def open(self, context: SinkContext) -> None:
        """Join the domain and create one writer per topic.

        Raises:
            SinkError: cyclonedds is not installed, or DDS cannot start (its configuration in
                CYCLONEDDS_URI, no usable network interface).
        """
        if self.stamp == "recording" and not plays_a_recording(context.device.spec):
            raise ConfigError(
                f"sink {self.name!r}: stamp=recording needs a recording, and "
                f"{short_repr(context.device.spec)} is a live device (its clock is monotonic "
                "time, not ROS time)",
                hint="use stamp=wall (the default) with a live device",
            )
        cdds = _import_cyclonedds()
        from cyclonedds._clayer import ddspy_write
        from cyclonedds.core import DDSException
        from cyclonedds.qos import Policy, Qos
        from cyclonedds.util import duration

        store = typestore(ros1=False)
        self._builder = MessageBuilder(store, self.names)
        self._memory = MemoryMessages(self._builder)
        idl = IdlTypes(store)

        def add_writer(ros_topic: str, msgtype: str) -> None:
            topic = cdds.topic.Topic(self._participant, self.topics[ros_topic], idl.get(msgtype))
            qos = Qos(
                Policy.Reliability.Reliable(duration(seconds=0)),
                Policy.Durability.Volatile,
                Policy.History.KeepLast(HISTORY_DEPTH),
                Policy.DataRepresentation(use_cdrv0_representation=True),
                Policy.Userdata(f"typehash={store.hash_rihs01(msgtype)};".encode()),
            )
            self._writers[ros_topic] = cdds.pub.DataWriter(publisher, topic, qos=qos)
            store.get_msgdef(msgtype)  # generates its serializer now, not at the first frame

        try:
            self._participant = cdds.domain.DomainParticipant(
                self.domain, qos=Qos(Policy.Userdata(b"enclave=/;"))
            )
            publisher = cdds.pub.Publisher(self._participant)
            for ros_topic, msgtype in self._builder.msgtypes().items():
                add_writer(ros_topic, msgtype)
            if self.clock:
                add_writer(CLOCK_TOPIC, CLOCK_TYPE)
                self._clock_msg = (store.types[CLOCK_TYPE], store.types[TIME_TYPE])
        except DDSException as exc:
            self.close()
            code = str(exc).split("]")[0].lstrip("[") if str(exc).startswith("[") else "error"
            raise SinkError(
                f"ros2 sink: Cyclone DDS could not join domain {self.domain} ({code}; its own "
                "message, if any, is above)",
                hint="check CYCLONEDDS_URI (network interface, peers) and the domain",
            ) from None
        self._encoder = CdrEncoder(self._builder)
        self._write = ddspy_write
        self._add_writer = add_writer  # the memory's writers come with its first frame
        self._memory_types = self._memory.msgtypes()
        log.info(
            "ros2 sink publishing %s on DDS domain %d",
            ", ".join(sorted(self._writers)),
            self.domain,
        )

    def write(self, frame: Frame, result: Result) -> None:
        """Serialise and publish the frame's messages; never waits for a subscriber."""
        if self._encoder is None or self._write is None or self._memory is None:
            raise SinkError(f"sink {self.name!r} is not open")
        t_ns = stamp_ns(result.timestamp_s) if self.stamp == "recording" else time.time_ns()
        # rosbags' CDR of the messages, padded to whole 4-byte words (sinks/ros/cdr.py)
        out = self._encoder.encode(frame, result, t_ns=t_ns)
        if self._clock_msg is not None:  # first: a use_sim_time node's clock is there already
            clock, stamp = self._clock_msg
            now = clock(clock=stamp(sec=t_ns // 10**9, nanosec=t_ns % 10**9))
            out.insert(0, (CLOCK_TOPIC, self._encoder.serialize(now)))
        for topic, msg in self._memory.messages(result, t_ns):
            if topic not in self._writers:
                self._new_writer(topic)
            out.append((topic, self._encoder.serialize(msg)))
        for topic, data in out:
            # cyclonedds' DataWriter.write serialises a sample in Python and hands the bytes to
            # this call: we hand it rosbags' CDR of the same layout (checked in the tests)
            rc = self._write(self._writers[topic]._ref, data)
            if rc < 0:
                self.failures.failed("ros2 sink: publishing %s failed (DDS code %d)", topic, rc)
            else:
                self.samples += 1

    def _new_writer(self, topic: str) -> None:
        """A writer for a memory topic, at its first message (a DDS error: the sink fails)."""
        from cyclonedds.core import DDSException

        try:
            self._add_writer(topic, self._memory_types[topic])
        except DDSException as exc:
            raise SinkError(f"ros2 sink: cannot create a writer for {topic} ({exc})") from None
        log.info("ros2 sink publishing %s (the obstacle memory)", topic)

    def close(self) -> None:
        """Leave the domain (subscribers see the writers go). Safe to call twice."""
        participant, self._participant = self._participant, None
        self._writers = {}
        self._write = None
        self._encoder = None
        self._add_writer = None
        if participant is not None:
            # cyclonedds deletes an entity (and what it contains) in its finaliser: run it now,
            # so the other side hears the participant leave at close, not at garbage collection
            participant.__del__()
            log.info("ros2 sink: %d samples published", self.samples)
