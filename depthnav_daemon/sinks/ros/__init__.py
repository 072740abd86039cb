"""The ROS family: ``rosbag:FILE.mcap|FILE.bag`` and live ``ros2`` topics, built from one set of
messages (the ``foxglove`` sink beside this package shares their names and frames).

messages.py  the ROS messages of a processed frame (rosbags' classes), names and frames
cdr.py       the per-frame CDR from templates, byte for byte rosbags' serialisation
memory_out.py  the obstacle memory out (grid, memory scan, odom -> base, remembered drop-offs),
             read from Result.memory; shared with the foxglove sink
rosbag.py    the ``rosbag`` sink (ROS 2 MCAP or ROS 1 bag)
ros2.py      the ``ros2`` sink (Cyclone DDS)
"""
