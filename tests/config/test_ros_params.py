"""Loading depth_nav_tools' parameter files (the shipped ones from ../shared and hand-made ones)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from depthnav_daemon.config.ros_params import load_ros_params
from depthnav_daemon.errors import ConfigError
from depthnav_daemon.pipeline.cliff import CliffParams
from depthnav_daemon.pipeline.geometry import Mount
from depthnav_daemon.pipeline.pose import PoseParams
from depthnav_daemon.pipeline.scan import ScanParams, depth_to_scan
from depthnav_daemon.sim.synthetic import Scene, render
from drivers.base import KINECT_V1

SHARED = Path(__file__).resolve().parents[2].parent / "shared"
SHIPPED = SHARED / "reference" / "original_params"

# what each shipped file says, in depthnav's names (copied by hand from the YAML files)
EXPECTED = {
    "laserscan_kinect": {
        "scan": {
            "range_min_m": 0.4,
            "range_max_m": 5.0,
            "scan_height": 400,
            "depth_img_row_step": 1,
            "ground_remove": True,
            "ground_margin_m": 0.05,
            "tilt_compensation": True,
            "method": "paper",
        },
        "mount": {
            "height_m": 0.8,
            "tilt_deg": 45.0,
        },  # -45.0 in laserscan_kinect >= 1.1.0 = 45 down
    },
    "cliff_detector": {
        "cliff": {
            "range_min_m": 0.5,
            "range_max_m": 5.0,
            "used_depth_height": 400,
            "block_size": 16,
            "block_points_thresh": 3,
            "row_step": 8,
            "col_step": 8,
            "ground_margin_m": 0.05,
        },
        "mount": {"height_m": 0.55, "tilt_deg": 15.0},
    },
    "depth_sensor_pose": {
        "pose": {
            "range_min_m": 0.5,
            "range_max_m": 8.0,
            "height_min_m": 0.7,
            "height_max_m": 1.0,
            "tilt_min_deg": 30.0,
            "tilt_max_deg": 35.0,
            "used_depth_height": 400,
            "row_step": 8,
            "col_step": 8,
            "max_points": 2500,
            "ransac_iterations": 2000,
            "inlier_dist_m": 0.001,
        },
    },
}


def shipped(ros: str, node: str) -> Path:
    if not SHARED.is_dir():
        pytest.skip(f"{SHARED} is absent: the shipped depth_nav_tools parameter files live there")
    return SHIPPED / ros / f"{node}.yaml"


@pytest.mark.parametrize("ros", ["ros1_noetic", "ros2_master"])
@pytest.mark.parametrize("node", list(EXPECTED))
def test_each_shipped_file_loads_with_the_expected_warnings(ros: str, node: str) -> None:
    r = load_ros_params(shipped(ros, node))
    assert r.node == node and r.ros_version == (1 if ros.startswith("ros1") else 2)
    assert r.values == EXPECTED[node]
    text = "\n".join(r.warnings)
    assert all("\n" not in w for w in r.warnings)
    # the tilt sign: only laserscan_kinect flipped it, and the warning says how to override
    assert ("sensor_tilt_angle -45 read as tilt_deg 45" in text) == (node == "laserscan_kinect")
    if node == "laserscan_kinect":
        assert "--tilt-deg -45" in text and "scan.method set to 'paper'" in text
    # the ROS 2 cliff_detector never declared the stride names its own file uses
    assert ("depth_img_step_row and depth_img_step_col are not parameters" in text) == (
        node == "cliff_detector" and ros == "ros2_master"
    )
    assert ("ransac_dist_thresh 0.001 m" in text) == (node == "depth_sensor_pose")
    assert ("applied tilt_angle_max to mount_height_max" in text) == (
        node == "depth_sensor_pose" and ros == "ros2_master"
    )
    assert "ignored (no depthnav equivalent): " in text and "cam_model_update" in text
    assert "unknown keys" not in text
    # every section builds its depthnav parameters
    classes = {"mount": Mount, "scan": ScanParams, "cliff": CliffParams, "pose": PoseParams}
    for section, fields in r.values.items():
        classes[section](**fields)


def test_laserscan_tilt_as_emitted_removes_the_floor() -> None:
    """The sign decision, end to end: 45 deg down removes the floor; the literal -45 would not."""
    r = load_ros_params(shipped("ros1_noetic", "laserscan_kinect"))
    params = ScanParams(**r.values["scan"])
    mount = Mount(**r.values["mount"])
    view = render(Scene(), KINECT_V1, mount)
    assert not np.isfinite(depth_to_scan(view.depth_mm, KINECT_V1, mount, params).ranges).any()
    literal = Mount(mount.height_m, -mount.tilt_deg)
    assert np.isfinite(depth_to_scan(view.depth_mm, KINECT_V1, literal, params).ranges).sum() > 100


def write(tmp_path: Path, text: str) -> Path:
    p = tmp_path / "params.yaml"
    p.write_text(text)
    return p


def test_non_numeric_value_is_a_one_line_error_naming_file_and_key(tmp_path: Path) -> None:
    p = write(tmp_path, "cliff_detector:\n  ros__parameters:\n    block_size: sixteen\n")
    with pytest.raises(ConfigError) as e:
        load_ros_params(p)
    assert str(e.value) == f"{p}: block_size='sixteen' is not a number"
    p = write(tmp_path, "scan_height: 400\nground_remove_en: 1\n")
    with pytest.raises(ConfigError, match="ground_remove_en=1 is not true/false"):
        load_ros_params(p)
    p = write(tmp_path, "block_size: 16.5\n")
    with pytest.raises(ConfigError, match=r"block_size=16\.5 is not an integer"):
        load_ros_params(p)


def test_out_of_range_value_names_file_and_depthnav_field(tmp_path: Path) -> None:
    p = write(tmp_path, "block_size: 16\nblock_points_thresh: 0\n")
    with pytest.raises(ConfigError) as e:
        load_ros_params(p)
    assert str(e.value).startswith(
        f"{p}: cliff.block_points_thresh=0 is out of range (accepted: integers 1..4)"
    )


def test_unknown_keys_and_positive_laserscan_tilt(tmp_path: Path) -> None:
    p = write(
        tmp_path,
        "laserscan_kinect:\n  ros__parameters:\n    sensor_tilt_angle: 10.0\n    foo_bar: 3\n",
    )
    r = load_ros_params(p)
    assert r.values == {"mount": {"tilt_deg": -10.0}}  # positive = up in laserscan_kinect >= 1.1.0
    assert any("read as tilt_deg -10 (up)" in w and "--tilt-deg 10" in w for w in r.warnings)
    assert any(
        "unknown keys (not laserscan_kinect parameters), ignored: foo_bar" in w for w in r.warnings
    )
    r = load_ros_params(write(tmp_path, "sensor_tilt_angle: 0.0\nscan_height: 300\n"))
    assert r.values["mount"] == {"tilt_deg": 0.0} and not any(
        "sensor_tilt_angle" in w for w in r.warnings
    )


def test_multi_node_files_and_namespaces(tmp_path: Path) -> None:
    text = (
        "/robot/cliff_detector:\n  ros__parameters:\n    block_size: 8\n    depth_img_row_step: 2\n"
        "    depth_img_col_step: 2\n"
        "depth_sensor_pose:\n  ros__parameters:\n    ransac_max_iter: 100\n"
    )
    p = write(tmp_path, text)
    with pytest.raises(
        ConfigError, match="found sections: /robot/cliff_detector, depth_sensor_pose"
    ):
        load_ros_params(p)
    r = load_ros_params(p, node="cliff_detector")
    # the names the ROS 2 node really declares: no stride warning
    assert r.values == {"cliff": {"block_size": 8, "row_step": 2, "col_step": 2}} and not r.warnings
    assert load_ros_params(p, node="depth_sensor_pose").values == {
        "pose": {"ransac_iterations": 100}
    }
    wild = load_ros_params(
        write(tmp_path, "/**:\n  ros__parameters:\n    block_size: 16\n    publish_depth: true\n")
    )
    assert wild.node == "cliff_detector" and wild.ros_version == 2


@pytest.mark.parametrize(
    ("text", "match"),
    [
        ("range_min: 0.5\n", "cannot tell which depth_nav_tools node"),
        ("- 1\n- 2\n", "not a YAML mapping"),
        ("a: [1,\n", "not valid YAML at line"),
        ("", "not a YAML mapping"),
    ],
)
def test_unusable_files(tmp_path: Path, text: str, match: str) -> None:
    with pytest.raises(ConfigError, match=match):
        load_ros_params(write(tmp_path, text))


def test_missing_file_and_bad_node(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match="cannot read"):
        load_ros_params(tmp_path / "nope.yaml")
    with pytest.raises(ConfigError, match="node='scan' is not a depth_nav_tools node"):
        load_ros_params(write(tmp_path, "block_size: 8\n"), node="scan")
