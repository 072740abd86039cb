"""Configuration: frozen dataclasses built from TOML files, ``--set`` and flags (``loader``), and
depth_nav_tools ROS parameter files translated to them (``ros_params``)."""
