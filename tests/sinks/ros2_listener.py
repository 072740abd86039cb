"""A DDS subscriber that knows nothing of depthnav: it learns the topics, type names, QoS and
types from DDS discovery alone (the builtin DCPSPublication topic and XTypes type lookup, as
``cyclonedds subscribe`` does) and prints what it receives as JSON lines.

usage: python ros2_listener.py DOMAIN COUNT TIMEOUT_S DDS_TOPIC[@best_effort]...

Prints one ``{"event": "endpoint", ...}`` line per writer of a wanted topic (topic, type name,
reliability, durability, history, user data), then ``{"event": "sample", ...}`` lines (COUNT per
topic, read with a RELIABLE reader, or BEST_EFFORT for a topic given with ``@best_effort``): the
sample as a dict (floats exact, NaN and infinities as Python's json writes them), byte sequences
as their length. Exits 0 when done, 2 after TIMEOUT_S.
"""

from __future__ import annotations

import dataclasses
import json
import sys
import time
from typing import Any


def plain(value: Any) -> Any:
    """A received sample as JSON-able data (NaN and infinities as Python's json writes them)."""
    if dataclasses.is_dataclass(value):
        return {f.name: plain(getattr(value, f.name)) for f in dataclasses.fields(value)}
    if isinstance(value, (bytes, bytearray)):
        return {"bytes": len(value)}
    if isinstance(value, list):
        if len(value) > 64 and all(isinstance(v, int) for v in value):
            return {"bytes": len(value)}
        return [plain(v) for v in value]
    return value


def emit(**fields: Any) -> None:
    sys.stdout.write(json.dumps(fields) + "\n")
    sys.stdout.flush()


def main(argv: list[str]) -> int:
    from cyclonedds.builtin import BuiltinDataReader, BuiltinTopicDcpsPublication
    from cyclonedds.core import Qos
    from cyclonedds.domain import DomainParticipant
    from cyclonedds.dynamic import get_types_for_typeid
    from cyclonedds.qos import Policy
    from cyclonedds.sub import DataReader
    from cyclonedds.topic import Topic
    from cyclonedds.util import duration

    domain, count, timeout_s = int(argv[0]), int(argv[1]), float(argv[2])
    wanted = [arg.split("@")[0] for arg in argv[3:]]
    best_effort = {arg.split("@")[0] for arg in argv[3:] if arg.endswith("@best_effort")}
    deadline = time.monotonic() + timeout_s
    dp = DomainParticipant(domain)
    builtin = BuiltinDataReader(dp, BuiltinTopicDcpsPublication)
    emit(event="ready")
    endpoints: dict[str, Any] = {}
    while len(endpoints) < len(wanted):
        if time.monotonic() > deadline:
            sys.stderr.write(f"timeout: saw writers of {sorted(endpoints)} only\n")
            return 2
        for ep in builtin.take(N=100):
            if ep.topic_name in wanted and ep.topic_name not in endpoints:
                endpoints[ep.topic_name] = ep
                q = ep.qos
                emit(
                    event="endpoint",
                    topic=ep.topic_name,
                    type=ep.type_name,
                    reliability=type(q[Policy.Reliability]).__name__,
                    durability=str(q[Policy.Durability]),
                    history=str(q[Policy.History]),
                    user_data=q[Policy.Userdata].data.decode() if Policy.Userdata in q else "",
                    has_type_information=ep.type_id is not None,
                )
        time.sleep(0.05)
    readers = {}
    for name in wanted:
        ep = endpoints[name]
        datatype, _ = get_types_for_typeid(dp, ep.type_id, duration(seconds=max(1, timeout_s)))
        reliability = (
            Policy.Reliability.BestEffort
            if name in best_effort
            else Policy.Reliability.Reliable(duration(seconds=1))
        )
        qos = Qos(reliability, Policy.Durability.Volatile, Policy.History.KeepLast(10))
        readers[name] = DataReader(dp, Topic(dp, name, datatype), qos=qos)
    got = dict.fromkeys(wanted, 0)
    while min(got.values()) < count:
        if time.monotonic() > deadline:
            sys.stderr.write(f"timeout: samples received {got}\n")
            return 2
        for name, reader in readers.items():
            for sample in reader.take(N=10):
                if got[name] < count:
                    got[name] += 1
                    emit(event="sample", topic=name, data=plain(sample), t_wall=time.time())
        time.sleep(0.02)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
