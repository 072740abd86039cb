"""Static transforms of a ROS bag (``/tf_static``): the IMU's rotation to the depth frame, and the
depth camera's placement on the robot (issue: "the mount from the bag").

A robot's URDF publishes ``base_link`` -> ... -> the depth camera's optical frame on
``/tf_static``; chained, that is where the camera sits on the robot (x, y, height of its optical
centre over the floor under ``base_link``) and how it looks (yaw, tilt, roll), in the project's
conventions: the optical frame is RDF (x right, y down, z forward), the base frame REP 103 (x
forward, y left, z up, origin on the floor), tilt positive = pitched down, roll right-hand about
forward (left side up), yaw counter-clockwise. The camera-to-base rotation is then
``Rz(yaw) Ry(tilt) Rx(roll) M`` with ``M`` taking RDF to FLU (pipeline.geometry.cam_to_level,
which the tests check this against).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterable, Mapping
from typing import Any

import numpy as np
import numpy.typing as npt

from drivers.base import SensorPlacement
from drivers.formats.ros_decode import quat_matrix

F64 = npt.NDArray[np.float64]
TF_STATIC = "/tf_static"
# the base frames tried, in order, when the spec names none (REP 105: base_link; many robots put
# base_footprint on the floor below it)
BASE_FRAMES = ("base_footprint", "base_link")
# RDF (camera) vectors -> FLU (level): forward = z, left = -x, up = -y
_RDF_TO_FLU = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])
GIMBAL_COS = 1e-9
MAX_PLACEMENT_M = 10.0  # a camera further from base_link than this is not on a wheeled robot


def read_static(
    messages: Iterable[Any], deserialize: Callable[[Any], Any]
) -> dict[tuple[str, str], F64]:
    """(parent, child) -> (4, 4) homogeneous transform with p_parent = T p_child, from the
    ``tf2_msgs/TFMessage`` messages of ``/tf_static`` (``deserialize`` turns one into its
    message; a later transform of the same pair wins, as tf2 keeps the latest)."""
    static: dict[tuple[str, str], F64] = {}
    for raw in messages:
        for tf in deserialize(raw).transforms:
            t = np.eye(4)
            t[:3, :3] = quat_matrix(tf.transform.rotation)
            v = tf.transform.translation
            t[:3, 3] = (float(v.x), float(v.y), float(v.z))
            if np.isfinite(t).all():
                static[
                    (str(tf.header.frame_id).lstrip("/"), str(tf.child_frame_id).lstrip("/"))
                ] = t
    return static


def frame_transform(static: Mapping[tuple[str, str], F64], source: str, target: str) -> F64 | None:
    """(4, 4) taking ``source``-frame points to ``target`` through the static transforms; None
    when they do not join the two frames (a leading '/' ignored)."""
    source, target = source.lstrip("/"), target.lstrip("/")
    edges: dict[str, list[tuple[str, F64]]] = {}
    for (parent, child), t in static.items():
        edges.setdefault(child, []).append((parent, t))  # child -> parent: T
        edges.setdefault(parent, []).append((child, np.linalg.inv(t)))
    seen = {source: np.eye(4)}
    todo = [source]
    while todo:
        frame = todo.pop()
        for other, t in edges.get(frame, []):
            if other not in seen:
                seen[other] = t @ seen[frame]
                todo.append(other)
    return seen.get(target)


def placement_of(camera_to_base: F64, source: str) -> SensorPlacement | None:
    """The placement of a camera whose optical frame goes to the base frame by
    ``camera_to_base`` (4, 4); None when it is not one a floor robot can have (not a rotation,
    or further than MAX_PLACEMENT_M)."""
    rot = camera_to_base[:3, :3]
    if not np.allclose(rot @ rot.T, np.eye(3), atol=1e-6) or np.linalg.det(rot) < 0:
        return None
    x, y, z = (float(v) for v in camera_to_base[:3, 3])
    if max(abs(x), abs(y), abs(z)) > MAX_PLACEMENT_M:
        return None
    q = rot @ _RDF_TO_FLU.T  # Rz(yaw) Ry(tilt) Rx(roll)
    tilt = -math.asin(max(-1.0, min(1.0, float(q[2, 0]))))
    if abs(math.cos(tilt)) < GIMBAL_COS:  # straight up or down: yaw and roll are one angle
        yaw, roll = math.atan2(-float(q[0, 1]), float(q[1, 1])), 0.0
    else:
        yaw = math.atan2(float(q[1, 0]), float(q[0, 0]))
        roll = math.atan2(float(q[2, 1]), float(q[2, 2]))
    return SensorPlacement(
        height_m=z,
        tilt_deg=math.degrees(tilt),
        roll_deg=math.degrees(roll),
        x_m=x,
        y_m=y,
        yaw_deg=math.degrees(yaw),
        source=source,
    )


def camera_placement(
    static: Mapping[tuple[str, str], F64], camera_frame: str, base_frame: str | None
) -> SensorPlacement | None:
    """The depth camera's placement from the bag's static transforms: ``base_frame``, or the
    first of BASE_FRAMES the transforms join to ``camera_frame``; None when none does."""
    for base in (base_frame,) if base_frame else BASE_FRAMES:
        t = frame_transform(static, camera_frame, base)
        if t is not None and camera_frame.lstrip("/") != base.lstrip("/"):
            return placement_of(t, f"{TF_STATIC} {base} -> {camera_frame.lstrip('/')}")
    return None
