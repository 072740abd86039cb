"""The device spec options, one table: the replay driver takes its option names from it, the
kinect and openni drivers' option tuples are checked against it (tests/drivers/test_spec_help.py),
and ``depthnav run/record/calibrate --help`` prints it (:func:`help_text`).

Imports no driver: the help must not load libfreenect or OpenNI2.
"""

from __future__ import annotations

from drivers.spec import INTRINSICS_OPTIONS

# what each intrinsics option means; a lens option added to INTRINSICS_OPTIONS without a line here
# still shows in the help, with the generic text
_INTRINSICS_HELP = {
    "fx": "focal length along x, pixels (replaces the device's or file's)",
    "fy": "focal length along y, pixels",
    "cx": "principal point x, pixels (0 = centre of the left pixel)",
    "cy": "principal point y, pixels (0 = centre of the top pixel)",
    "k1": "lens distortion, plumb_bob (OpenCV/ROS order k1 k2 p1 p2 k3): radial k1",
    "k2": "radial k2",
    "p1": "tangential p1",
    "p2": "tangential p2",
    "k3": "radial k3 (each 0 unless given)",
}


def _intrinsics() -> tuple[tuple[str, str], ...]:
    return tuple(
        (name, _INTRINSICS_HELP.get(name, "lens parameter, as in camera.toml [intrinsics]"))
        for name in INTRINSICS_OPTIONS
    )


# scheme -> (spec forms, ((option, what it does), ...))
DEVICE_OPTIONS: dict[str, tuple[str, tuple[tuple[str, str], ...]]] = {
    "replay": (
        "replay:PATH[?OPTION=VALUE&...]  (PATH: recording folder, .npz, .npy, folder of 16-bit\n"
        "    PNG/PGM depth images, fakenect folder, .oni, ROS bag)",
        (
            ("rate", "realtime (default: sleep to the recorded timestamps) or max"),
            ("loop", "1: start again at the end (time goes on from the last frame)"),
            ("fps", "frame rate of sources without timestamps (default 30)"),
            ("start", "skip this many frames when opening"),
            *_intrinsics(),
            ("scale", "image folders: depth units per metre (1000 = mm; TUM RGB-D 5000)"),
            ("glob", "image folders: which files are depth, relative to PATH, e.g. *_depth.png"),
            ("const_shift", "fakenect: disparity zero-plane constant (default 200)"),
            ("topic", "ROS bags: the depth image topic"),
            ("info_topic", "ROS bags: its CameraInfo topic"),
            ("base_frame", "ROS bags: the robot frame /tf_static places the camera in"),
        ),
    ),
    "kinect": (
        "kinect[://INDEX][?OPTION=VALUE&...]  (Kinect 360 via libfreenect)",
        (
            ("accel", "usb (default), freenect or none: where the accelerometer is read"),
            ("tilt_deg", "drive the tilt motor to this angle when opening (positive = up)"),
            ("led", "off, green, red, yellow, blink_green, blink_red_yellow"),
            ("lib", "a libfreenect.so to load instead of the system's"),
            ("fakenect", "replay this fakenect folder through Debian's fakenect library"),
            ("const_shift", "disparity zero-plane constant when only disparity comes (200)"),
            *_intrinsics(),
        ),
    ),
    "openni": (
        "openni://[URI][?mode=WxH@FPS&...] (live) or openni:FILE.oni[?rate=..&loop=..&...]",
        (
            ("mode", "live: WIDTHxHEIGHT@FPS, e.g. 640x480@30"),
            ("rate", ".oni: realtime or max (default)"),
            ("loop", ".oni: 1 to start again at the end"),
            *_intrinsics(),
        ),
    ),
    "realsense": (
        "realsense[://SERIAL][?OPTION=VALUE&...] (live) or realsense?file=REC.db3|REC.bag[&...]",
        (
            ("mode", "live: WIDTHxHEIGHT@FPS of the depth stream (default 640x480@30)"),
            ("preset", "live: visual preset, default high_accuracy (high_density, ...)"),
            ("emitter", "live: 1/0 the IR projector on/off"),
            ("laser_power", "live: projector power, mW"),
            ("filters", "SDK post-processing: decimation,spatial,temporal,hole_filling"),
            ("accel", "1 (default): the IMU's accelerometer as the tilt prior; 0: not used"),
            ("file", "play this RealSense recording through the SDK instead of a camera"),
            ("rate", "file: max (default, every frame) or realtime"),
            *_intrinsics(),
        ),
    ),
}


def option_names(scheme: str) -> tuple[str, ...]:
    """The option names a scheme's spec takes, in the table's order."""
    return tuple(name for name, _ in DEVICE_OPTIONS[scheme][1])


def help_text() -> str:
    """The device spec options as plain text for ``--help`` (an argparse epilog)."""
    lines = ["device specs and their options (join with ?key=value&key=value):"]
    for form, options in DEVICE_OPTIONS.values():
        lines.append(f"  {form}")
        width = max(len(name) for name, _ in options)
        lines += [f"    {name:<{width}}  {text}" for name, text in options]
    return "\n".join(lines)
