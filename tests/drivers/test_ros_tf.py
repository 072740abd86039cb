"""The mount from a bag's ``/tf_static`` (issue 32 item 4): the depth camera's placement on the
robot, chained from the base frame through the URDF's links, in the project's conventions
(checked against pipeline.geometry, which the stages use), and used by the daemon when no mount
is configured (a configured one wins)."""

from __future__ import annotations

import json
import math
import subprocess
import sys

import numpy as np
import pytest

from depthnav_daemon.pipeline.geometry import M_CAM_TO_FLU, Mount, cam_to_level, rot_z
from depthnav_daemon.sim.synthetic import Box, Scene, render
from drivers.base import KINECT_V1, Frame
from drivers.formats import ros_tf
from drivers.formats.rosbag import DepthBag
from tests.drivers.bagkit import OPTICAL, BagSpec, write_bag
from tests.faults.kit import ROOT

INTR = KINECT_V1.scaled(160, 120)
# a camera on a mast, off centre, looking ahead-left and down, a little rolled
MOUNT = Mount(0.62, 22.0, -3.0, x_m=0.15, y_m=0.08, yaw_deg=12.0)


def quaternion(r: np.ndarray) -> tuple[float, float, float, float]:
    """(x, y, z, w) of a rotation matrix (Shepperd's method, the largest term first)."""
    t = np.trace(r)
    if t > 0:
        s = math.sqrt(t + 1.0) * 2
        return ((r[2, 1] - r[1, 2]) / s, (r[0, 2] - r[2, 0]) / s, (r[1, 0] - r[0, 1]) / s, s / 4)
    i = int(np.argmax(np.diag(r)))
    j, k = (i + 1) % 3, (i + 2) % 3
    s = math.sqrt(1.0 + r[i, i] - r[j, j] - r[k, k]) * 2
    q = [0.0, 0.0, 0.0, 0.0]
    q[i] = s / 4
    q[j] = (r[j, i] + r[i, j]) / s
    q[k] = (r[k, i] + r[i, k]) / s
    q[3] = (r[k, j] - r[j, k]) / s
    return (q[0], q[1], q[2], q[3])


def urdf_chain(m: Mount, base: str = "base_footprint") -> list[tuple]:
    """base -> camera_link (the camera's body, FLU, at the optical centre) -> the optical frame
    (REP 103's optical rotation), as a URDF publishes them."""
    body = rot_z(m.yaw_rad) @ cam_to_level(m.tilt_rad, m.roll_rad) @ M_CAM_TO_FLU.T
    return [
        (base, "camera_link", quaternion(body), (m.x_m, m.y_m, m.height_m)),
        ("camera_link", OPTICAL, quaternion(M_CAM_TO_FLU)),
    ]


@pytest.mark.parametrize("seed", range(20))
def test_a_transform_gives_back_the_mount_it_was_made_of(seed: int) -> None:
    rng = np.random.default_rng(seed)
    m = Mount(
        rng.uniform(0.1, 2.0), rng.uniform(-30, 85), rng.uniform(-30, 30),
        x_m=rng.uniform(-1, 1), y_m=rng.uniform(-1, 1), yaw_deg=rng.uniform(-180, 180),
    )  # fmt: skip
    t = np.eye(4)
    t[:3, :3] = rot_z(m.yaw_rad) @ cam_to_level(m.tilt_rad, m.roll_rad)  # as the stages do
    t[:3, 3] = (m.x_m, m.y_m, m.height_m)
    p = ros_tf.placement_of(t, "test")
    assert p is not None
    got = (p.height_m, p.tilt_deg, p.roll_deg, p.x_m, p.y_m, p.yaw_deg)
    want = (m.height_m, m.tilt_deg, m.roll_deg, m.x_m, m.y_m, m.yaw_deg)
    assert got == pytest.approx(want, abs=1e-9)


def test_what_cannot_be_a_placement_is_none() -> None:
    far = np.eye(4)
    far[0, 3] = 50.0
    mirror = np.diag([1.0, 1.0, -1.0, 1.0])
    assert ros_tf.placement_of(far, "x") is None and ros_tf.placement_of(mirror, "x") is None


def _bag(tmp_path, chain, kind: str = "ros1"):
    scene = Scene(boxes=(Box(1.6, 0.3, 0.3, 0.4, 0.5),))
    frames = [Frame(i, i / 10.0, render(scene, INTR, MOUNT).depth_mm, INTR) for i in range(3)]
    name = "bag.bag" if kind == "ros1" else "bag"
    return write_bag(tmp_path / name, frames, BagSpec(kind, tf_static=chain))


@pytest.mark.parametrize("kind", ["ros1", "mcap"])
def test_the_bag_places_the_camera_through_its_urdf_chain(tmp_path, kind: str) -> None:
    probe = DepthBag(_bag(tmp_path, urdf_chain(MOUNT), kind)).probe()
    p = probe.placement
    assert p is not None and p.source == f"/tf_static base_footprint -> {OPTICAL}"
    got = (p.height_m, p.tilt_deg, p.roll_deg, p.x_m, p.y_m, p.yaw_deg)
    want = (MOUNT.height_m, MOUNT.tilt_deg, MOUNT.roll_deg, MOUNT.x_m, MOUNT.y_m, MOUNT.yaw_deg)
    assert got == pytest.approx(want, abs=1e-6)


def test_a_bag_without_a_base_frame_places_nothing(tmp_path) -> None:
    bag = _bag(tmp_path, urdf_chain(MOUNT, base="chassis"))
    assert DepthBag(bag).probe().placement is None  # neither base_footprint nor base_link
    named = DepthBag(bag, base_frame="chassis").probe().placement  # ?base_frame=chassis
    assert named is not None and named.height_m == pytest.approx(0.62)


def _run(*argv: str) -> tuple[list[dict], str]:
    done = subprocess.run(
        [sys.executable, "-m", "depthnav_daemon", "run", "--sink", "stdout", *argv],
        capture_output=True, text=True, cwd=ROOT, timeout=300,
    )  # fmt: skip
    assert done.returncode == 0, done.stderr
    return [json.loads(line) for line in done.stdout.splitlines()], done.stderr


def test_the_daemon_takes_the_bags_mount_unless_one_is_configured(tmp_path) -> None:
    bag = _bag(tmp_path, urdf_chain(MOUNT))
    device = f"replay:{bag}?rate=max"
    msgs, err = _run("--device", device, "--max-frames", "3")
    assert "mount from the recording's /tf_static base_footprint" in err
    first = msgs[0]["pose"]
    got = [first[k] for k in ("height_m", "tilt_deg", "roll_deg", "x_m", "y_m", "yaw_deg")]
    assert got == pytest.approx([0.62, 22.0, -3.0, 0.15, 0.08, 12.0], abs=0.01)
    assert msgs[-1]["mount"]["trusted"] is True  # the floor agrees with the bag
    # a configured mount wins, and the log says the bag's differs
    argv = ("--device", device, "--max-frames", "1", "--height-m", "0.7", "--tilt-deg", "20")
    msgs, err = _run(*argv)
    assert "the configured mount is used" in err
    assert msgs[0]["pose"]["height_m"] == pytest.approx(0.7, abs=1e-3)
    assert msgs[0]["pose"]["x_m"] == 0.0  # the configured mount is all of it
