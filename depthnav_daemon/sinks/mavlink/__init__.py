"""The MAVLink family: ``mavlink:SERIALPORT`` and ``mavlink+udp://HOST:PORT`` for ArduPilot / PX4.

mavlink.py   the sink: connection, HEARTBEAT, sending OBSTACLE_DISTANCE
sectors.py   the pure part: the 72 sectors from the scans, and when to send them
"""
