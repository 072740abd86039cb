"""The RealSense SDK (``pyrealsense2``) as the driver uses it: import, intrinsics, options, IMU.

Kept apart from the driver so a missing SDK is one line with what to install, and so the
conversions (stream profile -> Intrinsics, extrinsic -> rotation) have one home.

IMU axes: the SDK reports accelerometer samples in the depth camera's axes (x right, y down,
z forward, the same as depthnav's camera frame) as specific force (m/s^2): a camera at rest and
level reads about (0, -9.81, 0). Intel's D435i notes say the SDK multiplies each IMU sample by
the IMU-to-depth extrinsic itself. The driver still applies the rotation of
``accel_profile.get_extrinsics_to(depth_profile)`` (an ``rs2_extrinsics``: p_depth = R p_accel + t,
R stored column-major), which is the identity on D435i/D455; when the SDK cannot say (a
recording that lacks it), the samples are taken as they are.
"""

from __future__ import annotations

import platform
from typing import Any

import numpy as np
import numpy.typing as npt

from drivers.base import Intrinsics
from drivers.errors import DeviceOpenError, DriverNotAvailable, OpenFailure, RecordingError
from drivers.formats.realsense_layout import intrinsics_of

WHEEL_MACHINES = ("x86_64", "amd64")  # where PyPI has pyrealsense2 wheels
# the ArduPilot/Intel recommendation for obstacle avoidance is High Accuracy
PRESETS = ("custom", "default", "hand", "high_accuracy", "high_density", "medium_density")
FILTERS = ("decimation", "spatial", "temporal", "hole_filling")


def install_hint(machine: str | None = None) -> str:
    """What to install for the SDK on this machine, one line."""
    machine = (machine or platform.machine()).lower()
    if machine in WHEEL_MACHINES:
        return "pip install 'depthnav[realsense]' (or: pip install pyrealsense2)"
    return (
        f"PyPI has no pyrealsense2 wheel for {machine}: build librealsense with "
        "-DBUILD_PYTHON_BINDINGS=ON (or install the vendor's packages, e.g. JetPack's "
        "librealsense) into this Python; replay:REC.db3 works without it"
    )


def import_sdk() -> Any:
    """``pyrealsense2``, or DriverNotAvailable naming what to install."""
    try:
        import pyrealsense2 as rs
    except ImportError as exc:
        raise DriverNotAvailable(
            f"the realsense driver needs the RealSense SDK's Python binding pyrealsense2 ({exc})",
            hint=install_hint(),
        ) from None
    return rs


def sdk_version(rs: Any) -> str:
    """The SDK's version string, e.g. '2.59.1'."""
    return str(getattr(rs, "__version__", "?"))


def profile_intrinsics(
    profile: Any, where: str, lost: type[Exception] = RecordingError
) -> Intrinsics:
    """The Intrinsics of a video stream profile (the depth stream's, or a filter's output).

    Raises:
        ``lost`` (RecordingError for a file, DeviceOpenError live): a lens model depthnav does
        not model, or values that do not fit.
    """
    i = profile.as_video_stream_profile().get_intrinsics()
    model = str(i.model).rsplit(".", 1)[-1]  # "distortion.brown_conrady" -> "brown_conrady"
    try:
        return intrinsics_of(
            int(i.width), int(i.height), i.fx, i.fy, i.ppx, i.ppy, model, tuple(i.coeffs), where
        )
    except RecordingError as exc:
        if lost is RecordingError:
            raise
        raise DeviceOpenError(str(exc), hint=exc.hint, reason=OpenFailure.UNSUPPORTED) from None


def accel_rotation(accel_profile: Any, depth_profile: Any) -> npt.NDArray[np.float64]:
    """(3, 3) rotation taking accelerometer-stream vectors to the depth stream's axes: the SDK's
    extrinsic when it has one (column-major in rs2_extrinsics), else the identity."""
    try:
        ext = accel_profile.get_extrinsics_to(depth_profile)
    except RuntimeError:  # "Requested extrinsics are not available!" (recordings)
        return np.eye(3)
    rot = np.asarray(list(ext.rotation), dtype=np.float64)
    if rot.shape != (9,) or not np.all(np.isfinite(rot)):
        return np.eye(3)
    return rot.reshape(3, 3).T  # column-major: element (i, j) is rotation[j * 3 + i]


def device_info(rs: Any, dev: Any) -> tuple[str, str, str]:
    """(name, serial, firmware) of a device, "" for what it does not say."""
    out = []
    for key in ("name", "serial_number", "firmware_version"):
        info = getattr(rs.camera_info, key)
        out.append(str(dev.get_info(info)) if dev.supports(info) else "")
    return out[0], out[1], out[2]


def make_filters(rs: Any, names: tuple[str, ...]) -> list[Any]:
    """The SDK's post-processing filters, in the order given (each with the SDK's defaults)."""
    kinds = {
        "decimation": rs.decimation_filter,
        "spatial": rs.spatial_filter,
        "temporal": rs.temporal_filter,
        "hole_filling": rs.hole_filling_filter,
    }
    return [kinds[name]() for name in names]
