"""The JSON family: ``stdout`` (one line per frame) and ``udp`` (one datagram per frame) carry the
same object (docs/json_schema.md).

message.py   the frame's JSON object as dicts (the reference, and the REP 117 range codes)
line.py      the line as bytes, made once a frame and shared by both sinks
stdout.py    the ``stdout`` sink
udp.py       the ``udp://HOST:PORT`` sink
"""
