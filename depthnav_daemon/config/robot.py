"""The robot's side of the configuration: its body ([robot]), the obstacle memory ([memory]), the
odometry ([odometry]) and several sensors ([[sensor]] tables). The loader (loader.py) reads them
like the other sections."""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Any

from depthnav_daemon.errors import ConfigError
from depthnav_daemon.pipeline.footprint import Footprint, checked_polygon
from depthnav_daemon.pipeline.geometry import Mount, check_range
from depthnav_daemon.pipeline.memory import MemoryParams
from drivers.values import short_repr


@dataclass(frozen=True, slots=True)
class RobotSettings:
    """The robot's own body ([robot]): readings inside it are ignored by every stage and the
    memory (pipeline/footprint.py).

    Attributes:
        footprint_m: the body's outline on the floor, a convex polygon of [x, y] vertices in the
            base frame (REP 103: x forward, y left, origin on the floor under the robot), metres;
            () = no footprint.
        height_m: the body's top above the floor, metres (needed with a footprint).
    """

    footprint_m: tuple[tuple[float, float], ...] = ()
    height_m: float = 0.0

    def __post_init__(self) -> None:
        given = self.footprint_m
        if isinstance(given, (list, tuple)) and len(given) == 0:
            object.__setattr__(self, "footprint_m", ())
            if self.height_m != 0.0:
                raise ConfigError(
                    f"robot.height_m={self.height_m!r} is set but robot.footprint_m is empty",
                    hint="give the body's outline too, e.g. robot.footprint_m = [[0.3, 0.25], "
                    "[-0.3, 0.25], [-0.3, -0.25], [0.3, -0.25]]",
                )
            return
        polygon = checked_polygon(given)  # one line on a bad outline
        if self.height_m == 0.0:
            raise ConfigError(
                "robot.footprint_m is set but robot.height_m is not",
                hint="robot.height_m: the body's top above the floor, metres",
            )
        object.__setattr__(self, "footprint_m", Footprint(polygon, self.height_m).polygon_m)

    def footprint(self) -> Footprint | None:
        """The body for the stages, or None when no footprint is configured."""
        return Footprint(self.footprint_m, self.height_m) if self.footprint_m else None


@dataclass(frozen=True, slots=True)
class MemorySettings:
    """The obstacle memory ([memory]); see pipeline/memory.py.

    Attributes:
        enabled: "auto" (on whenever odometry is available), true (on; says why not when there is
            no odometry), false (off).
        size_m, cell_m, max_age_s, scan_increment_deg: as pipeline.memory.MemoryParams.
    """

    enabled: str | bool = "auto"
    size_m: float = 8.0
    cell_m: float = 0.05
    max_age_s: float = 0.0
    scan_increment_deg: float = 1.0

    def __post_init__(self) -> None:
        e = self.enabled
        if isinstance(e, str) and e.strip().lower() in ("auto", "true", "false"):
            e = e.strip().lower()
            object.__setattr__(self, "enabled", "auto" if e == "auto" else e == "true")
        if not (self.enabled == "auto" or isinstance(self.enabled, bool)):
            raise ConfigError(
                f"memory.enabled={self.enabled!r} is not known (accepted: auto, true, false)"
            )
        self.params()  # checks the ranges

    def params(self) -> MemoryParams:
        """The memory stage's parameters."""
        return MemoryParams(self.size_m, self.cell_m, self.max_age_s, self.scan_increment_deg)


@dataclass(frozen=True, slots=True)
class OdometrySettings:
    """Where the robot's motion comes from ([odometry]); the memory needs it.

    Attributes:
        source: an odometry spec (drivers.odometry: odom+udp://127.0.0.1:PORT for JSON lines,
            mavlink+udp://HOST:PORT or mavlink:SERIALPORT for an autopilot), or "" for none; a
            recording whose frames carry odometry gives it without a source. Checked here: a
            bad spec is a ConfigError (exit 2).
        timeout_s: a source that has sent nothing for this long is reported (once) and the memory
            stays off until it speaks.
        stale_s: odometry older than this at a frame freezes the memory (reported).
        max_jump_m, max_jump_deg: odometry that moves more than this between two frames resets
            the memory (reported): a jump is a relocalisation, not motion.
    """

    source: str = ""
    timeout_s: float = 2.0
    stale_s: float = 0.5
    max_jump_m: float = 0.5
    max_jump_deg: float = 45.0

    def __post_init__(self) -> None:
        check_range("odometry.timeout_s", self.timeout_s, 0.05, 3600.0, " s")
        check_range("odometry.stale_s", self.stale_s, 0.01, 60.0, " s")
        check_range("odometry.max_jump_m", self.max_jump_m, 0.001, 100.0, " m")
        check_range("odometry.max_jump_deg", self.max_jump_deg, 0.1, 180.0, " deg")
        if self.source:  # "" is no source; any other text must be a spec (no I/O here)
            from drivers.errors import DeviceSpecError
            from drivers.odometry import create_odometry

            try:
                create_odometry(self.source)
            except DeviceSpecError as exc:
                raise ConfigError(str(exc), hint=exc.hint) from None


SENSOR_KEYS = ("name", "device", "mount")
MAX_SENSORS = 16
MAX_SENSOR_NAME_CHARS = 60  # a name goes into every log line and JSON line about its sensor


@dataclass(frozen=True, slots=True)
class SensorConfig:
    """One of several sensors in one daemon (a ``[[sensor]]`` table).

    Attributes:
        name: unique name, for messages and the JSON ``sensors`` list.
        device: its device spec.
        mount: its mount and placement on the robot ([sensor.mount], as [mount]).
    """

    name: str
    device: str
    mount: Mount = field(default_factory=Mount)


def check_sensor_name(name: str, where: str) -> None:
    """Refuse a sensor name that would not fit a log line: over MAX_SENSOR_NAME_CHARS
    characters, or holding a control or other unprintable character (a newline, NUL or ESC
    would split or colour the log lines that name it).

    Raises:
        ConfigError: naming it as ``short_repr`` shows it (cut and escaped).
    """
    hint = "a short name of letters, digits and punctuation, e.g. front or rear_left"
    if len(name) > MAX_SENSOR_NAME_CHARS:
        raise ConfigError(
            f"{where}: name {short_repr(name)} is {len(name)} characters long "
            f"(accepted: up to {MAX_SENSOR_NAME_CHARS})",
            hint=hint,
        )
    bad = next((c for c in name if not c.isprintable()), None)
    if bad is not None:
        raise ConfigError(
            f"{where}: name {short_repr(name)} holds the unprintable character {bad!r}",
            hint=hint,
        )


def parse_sensors(
    value: Any, coerce: Callable[[str, Any, Any], Any], origin: str = "config"
) -> tuple[SensorConfig, ...]:
    """``[[sensor]]`` tables -> SensorConfigs, checked: unique names, devices, mounts in range.

    Args:
        value: the tables.
        coerce: the loader's value check (key, value, default) -> value.
        origin: where they come from, for messages.
    """
    if not isinstance(value, (list, tuple)) or not all(isinstance(v, Mapping) for v in value):
        raise ConfigError(
            f"{origin}: sensor must be a list of [[sensor]] tables, got {short_repr(value)}"
        )
    if len(value) > MAX_SENSORS:
        raise ConfigError(f"{origin}: {len(value)} sensors (accepted: up to {MAX_SENSORS})")
    out: list[SensorConfig] = []
    for i, table in enumerate(value):
        where = f"sensor {i + 1}"
        unknown = [k for k in table if k not in SENSOR_KEYS]
        if unknown:
            raise ConfigError(
                f"{where}: unknown key {short_repr(unknown[0])}",
                hint=f"valid keys: {', '.join(SENSOR_KEYS)}",
            )
        name, device = table.get("name"), table.get("device")
        if not isinstance(name, str) or not name.strip():
            raise ConfigError(f"{where}: needs a name (a non-empty string)")
        check_sensor_name(name, where)
        where = f"sensor {name!r}"
        if not isinstance(device, str) or not device.strip():
            raise ConfigError(f"{where}: needs a device spec")
        if any(s.name == name for s in out):
            raise ConfigError(
                f"two sensors are named {name!r}", hint="give every [[sensor]] its own name"
            )
        mount_table = table.get("mount", {})
        if not isinstance(mount_table, Mapping):
            raise ConfigError(f"{where}: mount must be a table of keys")
        defaults = {f.name: f.default for f in dataclasses.fields(Mount)}
        for k in mount_table:
            if k not in defaults:
                raise ConfigError(
                    f"{where}: unknown key {short_repr('mount.' + str(k))}",
                    hint=f"valid keys: {', '.join(defaults)}",
                )
        checked = {k: coerce(f"{where} mount.{k}", v, defaults[k]) for k, v in mount_table.items()}
        try:
            mount = Mount(**checked)
        except ConfigError as exc:
            raise ConfigError(f"{where}: {exc}") from None
        out.append(SensorConfig(name, device, mount))
    return tuple(out)
