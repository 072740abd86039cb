"""The Intel RealSense backend (``realsense`` specs): the driver for D4xx cameras and their
recordings played through the SDK (``driver``), and the SDK itself: import, intrinsics, options,
IMU axes (``sdk``). Replay without the SDK is drivers/formats/realsense_layout.py's."""
