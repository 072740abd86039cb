"""Configuration: frozen dataclasses, TOML files, depth_nav_tools' ROS parameter files and --set.

Precedence, lowest to highest: dataclass defaults, config files in the order given (later wins),
``--set section.key=value``, then dedicated flags (``--device``, ``--sink``, ``--height-m``, ...).
Unknown keys are errors that list the valid ones. ``configs/default.toml`` documents every key; a
test keeps it equal to ``Config()``.
"""

from __future__ import annotations

import dataclasses
import logging
import os
import tomllib
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from depthnav_daemon.config.robot import (
    MemorySettings,
    OdometrySettings,
    RobotSettings,
    SensorConfig,
    parse_sensors,
)
from depthnav_daemon.errors import ConfigError
from depthnav_daemon.pipeline.cliff import CliffParams
from depthnav_daemon.pipeline.geometry import Mount, check_int, check_range
from depthnav_daemon.pipeline.pose import PoseParams
from depthnav_daemon.pipeline.scan import ScanParams
from depthnav_daemon.sinks import check_sink_set
from drivers.files import check_path_length, read_toml
from drivers.values import NumberError, short_repr, short_text, to_number

log = logging.getLogger(__name__)

TILT_SOURCES = ("auto", "config", "accel", "serial", "floor")


@dataclass(frozen=True, slots=True)
class DaemonParams:
    """How the frame loop runs.

    Attributes:
        cliff: run the cliff stage.
        pose_every_frames: estimate the mount from the floor every N frames (0 = never).
        pose_every_s: ... or every N seconds of sensor time, whichever comes first (0 = off).
        pose_smoothing: weight of a new floor estimate in the running mount (0..1, 1 = no
            smoothing).
        max_jump_m, max_jump_deg: an estimate further than this from the running mount is not
            applied until ``jump_confirmations`` consecutive estimates agree with each other.
        jump_confirmations: consecutive agreeing estimates that make a jump real (the robot was
            moved).
        tilt_source: where the first mount and the prior come from: "auto" (accelerometer if the
            device has one, else the serial source if given, else the config), "config", "accel",
            "serial", or "floor" (config until the first confident floor estimate).
        serial_tilt: a serial tilt source spec (see drivers.tilt), or "" for none.
        frame_timeout_s: wait this long for one frame.
        max_consecutive_timeouts: then treat the device as lost and reconnect.
        reconnect_attempts: give up after this many reconnects in a row (0 = never give up).
        reconnect_backoff_s, reconnect_backoff_max_s: first wait between reconnects, and its cap.
        wait_for_device_s: at start, wait up to this long for a device that cannot be opened yet
            (not enumerated at boot), retrying with the reconnect backoff; 0 = fail at once.
        seed: seed of the random generator that RANSAC uses (runs are reproducible).
        sensor_max_age_s: several sensors ([[sensor]]): a sensor whose latest frame is older
            than this is left out of the merged scan (and reported) until it delivers again.
    """

    cliff: bool = True
    pose_every_frames: int = 30
    pose_every_s: float = 0.0
    pose_smoothing: float = 0.3
    max_jump_m: float = 0.05
    max_jump_deg: float = 3.0
    jump_confirmations: int = 3
    tilt_source: str = "auto"
    serial_tilt: str = ""
    frame_timeout_s: float = 1.0
    max_consecutive_timeouts: int = 5
    reconnect_attempts: int = 10
    reconnect_backoff_s: float = 0.5
    reconnect_backoff_max_s: float = 8.0
    wait_for_device_s: float = 0.0
    seed: int = 0
    sensor_max_age_s: float = 0.5

    def __post_init__(self) -> None:
        check_int("daemon.pose_every_frames", self.pose_every_frames, 0, 1_000_000)
        check_range("daemon.pose_every_s", self.pose_every_s, 0.0, 86400.0, " s")
        check_range("daemon.pose_smoothing", self.pose_smoothing, 0.01, 1.0)
        check_range("daemon.max_jump_m", self.max_jump_m, 0.001, 10.0, " m")
        check_range("daemon.max_jump_deg", self.max_jump_deg, 0.01, 90.0, " deg")
        check_int("daemon.jump_confirmations", self.jump_confirmations, 1, 1000)
        if self.tilt_source not in TILT_SOURCES:
            raise ConfigError(
                f"daemon.tilt_source={short_repr(self.tilt_source)} is not known "
                f"(accepted: {', '.join(TILT_SOURCES)})"
            )
        check_range("daemon.frame_timeout_s", self.frame_timeout_s, 0.01, 60.0, " s")
        check_int("daemon.max_consecutive_timeouts", self.max_consecutive_timeouts, 1, 10_000)
        check_int("daemon.reconnect_attempts", self.reconnect_attempts, 0, 1_000_000)
        check_range("daemon.reconnect_backoff_s", self.reconnect_backoff_s, 0.0, 60.0, " s")
        check_range(
            "daemon.reconnect_backoff_max_s", self.reconnect_backoff_max_s, 0.0, 3600.0, " s"
        )
        check_range("daemon.wait_for_device_s", self.wait_for_device_s, 0.0, 1e9, " s")
        check_int("daemon.seed", self.seed, 0, 2**63 - 1)
        check_range("daemon.sensor_max_age_s", self.sensor_max_age_s, 0.01, 3600.0, " s")


@dataclass(frozen=True, slots=True)
class Config:
    """Everything ``depthnav run`` needs. Each stage owns its parameter class."""

    device: str = ""
    sinks: tuple[str, ...] = ("stdout",)
    mount: Mount = field(default_factory=Mount)
    scan: ScanParams = field(default_factory=ScanParams)
    cliff: CliffParams = field(default_factory=CliffParams)
    pose: PoseParams = field(default_factory=PoseParams)
    daemon: DaemonParams = field(default_factory=DaemonParams)
    memory: MemorySettings = field(default_factory=MemorySettings)
    odometry: OdometrySettings = field(default_factory=OdometrySettings)
    robot: RobotSettings = field(default_factory=RobotSettings)
    sensors: tuple[SensorConfig, ...] = ()


SECTIONS: dict[str, type] = {
    "mount": Mount,
    "scan": ScanParams,
    "cliff": CliffParams,
    "pose": PoseParams,
    "daemon": DaemonParams,
    "memory": MemorySettings,
    "odometry": OdometrySettings,
    "robot": RobotSettings,
}
TOP_LEVEL = ("device", "sinks", "sensor")
# keys whose values are checked by their section's class rather than by the default's type
FREE_TYPED = {("memory", "enabled"), ("cliff", "depth_noise")}  # depth_noise: a name or a number


def valid_keys() -> list[str]:
    """Every dotted key a config file or --set accepts."""
    keys = list(TOP_LEVEL)
    for name, cls in SECTIONS.items():
        keys += [f"{name}.{f.name}" for f in dataclasses.fields(cls)]
    return keys


def _field_types(cls: type) -> dict[str, Any]:
    return {f.name: f.default for f in dataclasses.fields(cls)}


MAX_TEXT_CHARS = 4096  # a device spec, sink spec or name; longer text is not one


def _coerce(key: str, value: Any, default: Any) -> Any:
    """Check a value against the type of the field's default; ints are accepted for floats.

    Numbers go through drivers.values.to_number: finite, and at most 1e300 (floats) or 2**63
    (integers) in size, so a 400-digit integer is one ConfigError line, not an OverflowError from
    the range checks that follow.
    """
    if isinstance(default, bool):
        if isinstance(value, bool):
            return value
    elif isinstance(default, (int, float)):
        wanted_int = isinstance(default, int)
        if isinstance(value, int if wanted_int else (int, float)) and not isinstance(value, bool):
            try:
                return to_number(value, integer=wanted_int)
            except NumberError as exc:
                raise ConfigError(f"{key}={short_repr(value)} {exc}") from None
    elif isinstance(default, str):
        if isinstance(value, str):
            if len(value) > MAX_TEXT_CHARS:
                raise ConfigError(
                    f"{key}={short_repr(value)} is longer than {MAX_TEXT_CHARS} characters"
                )
            return value
    else:
        return value
    raise ConfigError(
        f"{key}={short_repr(value)} has the wrong type (accepted: {type(default).__name__})"
    )


def _merge(base: dict[str, Any], overlay: Mapping[str, Any], origin: str) -> None:
    """Merge one source's nested dict into ``base``, rejecting unknown keys."""
    for key, value in overlay.items():
        if key in TOP_LEVEL:
            base[key] = value
            continue
        if key not in SECTIONS:
            raise ConfigError(
                f"{short_text(origin)}: unknown key {short_repr(key)}",
                hint=f"valid top-level keys and sections: {', '.join([*TOP_LEVEL, *SECTIONS])}",
            )
        if not isinstance(value, Mapping):
            raise ConfigError(
                f"{short_text(origin)}: {key!r} must be a table of keys, got {short_repr(value)}"
            )
        known = _field_types(SECTIONS[key])
        for sub, v in value.items():
            if sub not in known:
                raise ConfigError(
                    f"{short_text(origin)}: unknown key {short_repr(f'{key}.{sub}')}",
                    hint=f"valid keys in [{key}]: {', '.join(known)}",
                )
            base.setdefault(key, {})[sub] = v


def read_config_file(path: Path) -> dict[str, Any]:
    """One config file as a nested dict: TOML, or a depth_nav_tools ROS parameter file (.yaml).

    Read through drivers.files: a regular UTF-8 file of at most 1 MiB (a FIFO, a device, a folder
    or a 300-byte name is one ConfigError line), parsed with its nesting and numbers bounded.
    """
    check_path_length(path, _config_file_error)
    if not os.path.lexists(path):
        raise ConfigError(
            f"config file {path} does not exist", hint="check the path given to --config"
        )
    if path.suffix in (".yaml", ".yml"):
        from depthnav_daemon.config.ros_params import load_ros_params

        ros = load_ros_params(path)
        for warning in ros.warnings:
            log.warning("%s: %s", path, warning)
        return {section: dict(values) for section, values in ros.values.items() if values}
    return read_toml(path, what="config file", error=_config_file_error)


def _config_file_error(message: str, hint: str | None = None) -> ConfigError:
    return ConfigError(f"config file {message}", hint=hint)


def parse_set(item: str) -> dict[str, Any]:
    """``section.key=value`` (value as a TOML literal, else a plain string) -> nested dict."""
    key, sep, text = item.partition("=")
    key = key.strip()
    if not sep or not key:
        raise ConfigError(
            f"--set {short_repr(item)} is not key=value", hint="e.g. --set scan.range_max_m=4.0"
        )
    try:
        value = tomllib.loads(f"v = {text.strip()}")["v"]
    except tomllib.TOMLDecodeError:
        value = text.strip()
    except RecursionError:
        raise ConfigError(f"--set {short_repr(key)}: the value is nested too deeply") from None
    except ValueError:  # an integer over Python's 4300-digit limit (tomllib's int() raises)
        raise ConfigError(f"--set {short_repr(key)}: the value has too many digits") from None
    if key in TOP_LEVEL:
        return {key: value}
    section, dot, sub = key.partition(".")
    if not dot or section not in SECTIONS:
        raise ConfigError(
            f"--set {short_repr(key)}: unknown key", hint=f"valid keys: {', '.join(valid_keys())}"
        )
    return {section: {sub: value}}


def build_config(
    files: Sequence[Path] = (),
    sets: Iterable[str] = (),
    overrides: Mapping[str, Any] | None = None,
) -> Config:
    """Merge defaults, files, --set items and flag overrides (nested dict) into a checked Config."""
    merged: dict[str, Any] = {}
    for path in files:
        _merge(merged, read_config_file(Path(path)), str(path))
    for item in sets:
        _merge(merged, parse_set(item), f"--set {item}")
    if overrides:
        _merge(merged, overrides, "command line")
    return config_from_dict(merged)


def config_from_dict(data: Mapping[str, Any]) -> Config:
    """Build a Config from a nested dict of known keys, checking types and ranges."""
    kwargs: dict[str, Any] = {}
    if "device" in data:
        kwargs["device"] = _coerce("device", data["device"], "")
    if "sinks" in data:
        sinks = data["sinks"]
        if isinstance(sinks, str):
            sinks = [sinks]
        if not isinstance(sinks, (list, tuple)) or not all(isinstance(s, str) for s in sinks):
            raise ConfigError(f"sinks={short_repr(sinks)} must be a list of sink specs")
        kwargs["sinks"] = tuple(_coerce("sinks", s, "") for s in sinks)
        check_sink_set(kwargs["sinks"])
    if "sensor" in data:
        kwargs["sensors"] = parse_sensors(data["sensor"], _coerce)
        if kwargs["sensors"] and data.get("device"):
            raise ConfigError(
                "both device and [[sensor]] tables are given",
                hint="one sensor: device (or --device); several: [[sensor]] tables only",
            )
    for section, cls in SECTIONS.items():
        values = data.get(section, {})
        defaults = _field_types(cls)
        checked = {
            k: v if (section, k) in FREE_TYPED else _coerce(f"{section}.{k}", v, defaults[k])
            for k, v in values.items()
        }
        try:
            kwargs[section] = cls(**checked)
        except ConfigError:
            raise
        except (TypeError, ValueError) as exc:
            raise ConfigError(f"[{section}]: {exc}") from None
    return Config(**kwargs)


def config_to_dict(cfg: Config) -> dict[str, Any]:
    """A Config as a nested dict of plain values (for --write and for showing the effective
    config)."""
    out: dict[str, Any] = {"device": cfg.device, "sinks": list(cfg.sinks)}
    for section in SECTIONS:
        out[section] = dataclasses.asdict(getattr(cfg, section))
    if cfg.sensors:
        out["sensor"] = [
            {"name": sc.name, "device": sc.device, "mount": dataclasses.asdict(sc.mount)}
            for sc in cfg.sensors
        ]
    return out
