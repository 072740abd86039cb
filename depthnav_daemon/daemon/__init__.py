"""The frame loop and what it keeps between frames (driver -> pose -> stages -> sinks).

- ``loop``: the one-sensor loop; ``multi``: several sensors, one thread each, merged;
- ``frames``, ``outputs``, ``report``: what both loops share (reading frames, opening and feeding
  the sinks, the run's report);
- ``frame_step``: one frame through the floor estimate and the stages, with the mount to use;
- ``source``: the device with reconnect; ``mount_tracker``: the mount and its trust;
  ``stage_tables``: the stages' tables built off the loop for a new mount;
- ``memory_keeper``: the obstacle memory moved by odometry; ``notify``: systemd's notify
  protocol and watchdog.
"""
