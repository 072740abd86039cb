"""Load depth_nav_tools parameter files (laserscan_kinect, cliff_detector, depth_sensor_pose).

Reads ROS 1 flat YAML (``key: value`` at the top level, optionally under the node's name) and
ROS 2 YAML (``<node>: ros__parameters: {...}``) into depthnav's names and units, with a warning
for everything that does not carry over one to one:

* laserscan_kinect's ``sensor_tilt_angle``: laserscan_kinect >= 1.1.0 (Feb 2021, every ROS 2
  release) counts *negative* as pitched down, so its shipped ``-45.0`` is a sensor 45 deg down;
  depthnav counts positive as down. The file does not say which version it was written for, so
  the loader assumes the current one, emits ``tilt_deg = -value`` and says how to override.
  cliff_detector and depth_sensor_pose always counted positive as down: taken as is.
* the ROS 2 cliff_detector declares ``depth_img_row_step``/``depth_img_col_step`` but its shipped
  file says ``depth_img_step_row``/``depth_img_step_col``: that node ignored them and ran with
  strides 2. The loader applies the file's values (what its author meant) and warns.
* keys with no depthnav equivalent (frame ids, rates, debug switches, threads) and unknown keys.

Values are checked by building the depthnav parameter classes, so a bad value fails here with a
one-line ConfigError naming the file and key.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml

from depthnav_daemon.errors import ConfigError
from depthnav_daemon.pipeline.cliff import CliffParams
from depthnav_daemon.pipeline.geometry import Mount
from depthnav_daemon.pipeline.pose import PoseParams
from depthnav_daemon.pipeline.scan import ScanParams
from drivers.files import read_text
from drivers.values import NumberError, short_repr, short_text, to_number
from drivers.yaml_bounds import BoundedYamlLoader, YamlRefusedError

NODES = ("laserscan_kinect", "cliff_detector", "depth_sensor_pose")

# original key -> (depthnav section, field, kind); kind: "float", "int" or "bool"
_MAP: dict[str, dict[str, tuple[str, str, str]]] = {
    "laserscan_kinect": {
        "range_min": ("scan", "range_min_m", "float"),
        "range_max": ("scan", "range_max_m", "float"),
        "scan_height": ("scan", "scan_height", "int"),
        "depth_img_row_step": ("scan", "depth_img_row_step", "int"),
        "sensor_mount_height": ("mount", "height_m", "float"),
        "sensor_tilt_angle": ("mount", "tilt_deg", "float"),
        "ground_remove_en": ("scan", "ground_remove", "bool"),
        "ground_margin": ("scan", "ground_margin_m", "float"),
        "tilt_compensation_en": ("scan", "tilt_compensation", "bool"),
    },
    "cliff_detector": {
        "range_min": ("cliff", "range_min_m", "float"),
        "range_max": ("cliff", "range_max_m", "float"),
        "sensor_mount_height": ("mount", "height_m", "float"),
        "sensor_tilt_angle": ("mount", "tilt_deg", "float"),
        "used_depth_height": ("cliff", "used_depth_height", "int"),
        "block_size": ("cliff", "block_size", "int"),
        "block_points_thresh": ("cliff", "block_points_thresh", "int"),
        "depth_img_step_row": ("cliff", "row_step", "int"),  # ROS 1 name (and the shipped files)
        "depth_img_step_col": ("cliff", "col_step", "int"),
        "depth_img_row_step": ("cliff", "row_step", "int"),  # what the ROS 2 node declares
        "depth_img_col_step": ("cliff", "col_step", "int"),
        "ground_margin": ("cliff", "ground_margin_m", "float"),
    },
    "depth_sensor_pose": {
        "range_min": ("pose", "range_min_m", "float"),
        "range_max": ("pose", "range_max_m", "float"),
        "mount_height_min": ("pose", "height_min_m", "float"),
        "mount_height_max": ("pose", "height_max_m", "float"),
        "tilt_angle_min": ("pose", "tilt_min_deg", "float"),
        "tilt_angle_max": ("pose", "tilt_max_deg", "float"),
        "used_depth_height": ("pose", "used_depth_height", "int"),
        "depth_img_step_row": ("pose", "row_step", "int"),
        "depth_img_step_col": ("pose", "col_step", "int"),
        "ground_max_points": ("pose", "max_points", "int"),
        "ransac_max_iter": ("pose", "ransac_iterations", "int"),
        "ransac_dist_thresh": ("pose", "inlier_dist_m", "float"),
    },
}

# keys the original nodes have but depthnav does not use (ROS plumbing, debug output, threads)
_IGNORED = {
    "laserscan_kinect": {"output_frame_id", "cam_model_update", "publish_dbg_info", "threads_num"},
    "cliff_detector": {"output_frame_id", "rate", "publish_depth", "cam_model_update"},
    "depth_sensor_pose": {"output_frame_id", "rate", "publish_dbg_info", "cam_model_update"},
}
_ROS2_COMMON = {"use_sim_time"}  # every ROS 2 node has it

# keys that identify a node in a file that does not name it
_SIGNATURE = {
    "laserscan_kinect": {"scan_height", "ground_remove_en", "tilt_compensation_en", "threads_num"},
    "cliff_detector": {"block_size", "block_points_thresh", "publish_depth"},
    "depth_sensor_pose": {
        "mount_height_min",
        "mount_height_max",
        "tilt_angle_min",
        "tilt_angle_max",
        "ground_max_points",
        "ransac_max_iter",
        "ransac_dist_thresh",
    },
}

TIGHT_RANSAC_DIST_M = 0.005
ROS2 = 2  # a ROS 2 parameter file (ros__parameters)


@dataclass(frozen=True, slots=True)
class RosParams:
    """A depth_nav_tools parameter file in depthnav's terms.

    Attributes:
        values: section ("mount", "scan", "cliff", "pose") -> depthnav field name -> value, only
            for keys the file sets (e.g. ``values["mount"]["tilt_deg"]``, degrees, positive down).
        node: "laserscan_kinect", "cliff_detector" or "depth_sensor_pose".
        ros_version: 1 or 2 (the file's layout).
        warnings: one line each (without the file name), for everything that did not carry over
            one to one.
    """

    values: dict[str, dict[str, object]]
    node: str
    ros_version: int
    warnings: list[str] = field(default_factory=list)


def _node_of(name: str) -> str | None:
    last = name.strip("/").split("/")[-1]
    return last if last in NODES else None


def _infer(keys: set[str], where: str) -> str:
    score = {n: len(keys & sig) for n, sig in _SIGNATURE.items()}
    best = max(score.values())
    winners = [n for n, s in score.items() if s == best]
    if best == 0 or len(winners) > 1:
        raise ConfigError(
            f"{where}: cannot tell which depth_nav_tools node these parameters are for "
            f"(accepted: {', '.join(NODES)}; pass node=... to choose)"
        )
    return winners[0]


def _split(doc: Any, where: str, node: str | None) -> tuple[str, int, dict[str, Any]]:
    """(node, ROS version, flat parameter dict) of a parsed YAML document."""
    if not isinstance(doc, dict) or not doc:
        raise ConfigError(
            f"{where}: not a YAML mapping of parameters (accepted: ROS 1 or ROS 2 parameter YAML)"
        )
    sections = {k: v for k, v in doc.items() if isinstance(v, dict)}
    if sections and len(sections) == len(doc):
        # ROS 2 (<node>: ros__parameters: ...) or ROS 1 namespaced (<node>: {...})
        found = []
        for key, body in sections.items():
            params = body.get("ros__parameters", body)
            version = 2 if "ros__parameters" in body else 1
            if not isinstance(params, dict):
                raise ConfigError(f"{where}: {key}.ros__parameters is not a mapping")
            name = _node_of(str(key)) or (_infer(set(params), where) if str(key) == "/**" else None)
            if name is not None:
                found.append((name, version, params))
        if node is not None:
            found = [f for f in found if f[0] == node]
        if len(found) != 1:
            names = short_text(", ".join(short_text(str(k), 40) for k in list(sections)[:8]), 200)
            raise ConfigError(
                f"{where}: expected the parameters of one depth_nav_tools node, found sections: "
                f"{names} "
                f"(accepted: {', '.join(NODES)}; pass node=... to choose)"
            )
        return found[0]
    name = node if node is not None else _infer(set(doc), where)
    return name, 1, doc


def _convert(value: Any, kind: str, where: str, key: str) -> object:
    if kind == "bool":
        if not isinstance(value, bool):
            raise ConfigError(f"{where}: {key}={short_repr(value)} is not true/false")
        return value
    if isinstance(value, str):  # YAML text is not a number, even when it reads like one
        raise ConfigError(f"{where}: {key}={short_repr(value)} is not a number")
    try:
        return to_number(value, integer=kind == "int")
    except NumberError as exc:
        raise ConfigError(f"{where}: {key}={short_repr(value)} {exc}") from None


def _validate(values: dict[str, dict[str, object]], where: str) -> None:
    """Build the depthnav parameter classes so out-of-range values fail now, naming the file."""
    classes = {"mount": Mount, "scan": ScanParams, "cliff": CliffParams, "pose": PoseParams}
    for section, fields in values.items():
        try:
            classes[section](**fields)
        except ConfigError as e:
            raise ConfigError(f"{where}: {e}", hint=e.hint) from None


def load_ros_params(path: str | Path, node: str | None = None) -> RosParams:
    """Read one depth_nav_tools parameter file.

    Args:
        path: a ROS 1 or ROS 2 ``params.yaml`` of laserscan_kinect, cliff_detector or
            depth_sensor_pose.
        node: which node's parameters to take; None = the node the file names (ROS 2) or whose
            keys it holds (ROS 1).

    Returns:
        The parameters in depthnav's names and units, with warnings.

    Raises:
        ConfigError: unreadable file, bad YAML, unknown node, non-numeric or out-of-range values
            (one line naming the file and key).
    """
    p = Path(path)
    where = str(p)
    if node is not None and node not in NODES:
        raise ConfigError(
            f"node={short_repr(node)} is not a depth_nav_tools node (accepted: {', '.join(NODES)})"
        )
    name, version, params = _split(_read_yaml(p), where, node)
    mapping = _MAP[name]
    values: dict[str, dict[str, object]] = {}
    warnings: list[str] = []
    ignored, unknown = [], []
    for raw_key, raw in params.items():
        key = str(raw_key)
        if key not in mapping:
            (ignored if key in _IGNORED[name] | _ROS2_COMMON else unknown).append(key)
            continue
        section, fname, kind = mapping[key]
        values.setdefault(section, {})[fname] = _convert(raw, kind, where, key)

    warnings += _node_notes(name, version, params, values)
    if ignored:
        warnings.append(f"ignored (no depthnav equivalent): {', '.join(ignored)}")
    if unknown:
        warnings.append(f"unknown keys (not {name} parameters), ignored: {', '.join(unknown)}")
    _validate(values, where)
    return RosParams(values, name, version, warnings)


def _read_yaml(p: Path) -> object:
    """The parsed YAML document of ``p`` (ConfigError: unreadable, not UTF-8, not YAML, nested
    too deeply, a collection alias, a number over Python's 4300-digit limit)."""
    if not os.path.lexists(p):
        raise ConfigError(f"{p}: cannot read (no such file)", hint="check the path")
    text = read_text(p, what="parameter file", error=ConfigError)
    loader = None
    try:
        loader = BoundedYamlLoader(text)  # its reader refuses control characters already
        return loader.get_single_data()
    except YamlRefusedError as e:
        raise ConfigError(f"{p}: not accepted as YAML: {e}") from None
    except yaml.YAMLError as e:
        mark = getattr(e, "problem_mark", None)
        at = f" at line {mark.line + 1}" if mark is not None else ""
        raise ConfigError(f"{p}: not valid YAML{at}") from None
    except RecursionError:
        raise ConfigError(f"{p}: not valid YAML (nested too deeply)") from None
    except ValueError:  # a number over Python's 4300-digit limit, an impossible date
        raise ConfigError(f"{p}: not valid YAML (a value that cannot be read)") from None
    finally:
        if loader is not None:
            loader.dispose()


def _node_notes(
    name: str, version: int, params: dict, values: dict[str, dict[str, object]]
) -> list[str]:
    """What the user must know about this node's file: sign flips, mode switches, known bugs of
    the original nodes. Adjusts ``values`` where depthnav reads a value differently."""
    warnings: list[str] = []
    if name == "laserscan_kinect":
        tilt = values.get("mount", {}).get("tilt_deg")
        if isinstance(tilt, float) and tilt != 0.0:
            values["mount"]["tilt_deg"] = -tilt
            warnings.append(
                f"sensor_tilt_angle {tilt:g} read as tilt_deg {-tilt:g} ("
                f"{'down' if -tilt > 0 else 'up'}): laserscan_kinect >= 1.1.0 (and every ROS 2 "
                "release) "
                f"counts negative as pitched down, depthnav positive; if the file was written for "
                f"laserscan_kinect <= 1.0.x (positive = down), override with --tilt-deg {tilt:g}"
            )
        if {"scan_height", "depth_img_row_step", "ground_remove_en", "tilt_compensation_en"} & set(
            params
        ):
            values.setdefault("scan", {})["method"] = "paper"
            warnings.append(
                "scan.method set to 'paper' so scan_height, depth_img_row_step, ground_remove_en "
                "and tilt_compensation_en act as in laserscan_kinect; with method 'exact' "
                "(depthnav's "
                "level-frame scan) they are unused"
            )
    if name == "cliff_detector" and version == ROS2:
        odd = [k for k in ("depth_img_step_row", "depth_img_step_col") if k in params]
        if odd:
            warnings.append(
                f"{' and '.join(odd)} are not parameters of the ROS 2 cliff_detector (it declares "
                "depth_img_row_step/depth_img_col_step), so that node ran with strides 2; "
                "depthnav applies "
                f"the file's values, set cliff.row_step/col_step = 2 to match what the node did"
            )
    if name == "depth_sensor_pose":
        dist = values.get("pose", {}).get("inlier_dist_m")
        if isinstance(dist, float) and dist < TIGHT_RANSAC_DIST_M:
            warnings.append(
                f"ransac_dist_thresh {dist:g} m is far below Kinect-class depth noise (about 1 cm "
                "at 2 m); few points will count as floor inliers, consider pose.inlier_dist_m = "
                "0.02"
            )
        if version == ROS2 and "tilt_angle_max" in params:
            warnings.append(
                "the ROS 2 depth_sensor_pose applied tilt_angle_max to mount_height_max (a bug) "
                "and "
                "never ran its estimator; depthnav uses it as the upper bound of the tilt prior"
            )
    return warnings
