"""Config: defaults file equals the code, precedence, unknown keys, types and ranges."""

from __future__ import annotations

from pathlib import Path

import pytest

from depthnav_daemon.config.loader import Config, build_config, config_to_dict, valid_keys
from depthnav_daemon.errors import ConfigError

ROOT = Path(__file__).resolve().parents[2]


def test_default_toml_equals_the_code_defaults() -> None:
    assert build_config([ROOT / "configs" / "default.toml"]) == Config()


def test_default_toml_documents_every_key() -> None:
    text = (ROOT / "configs" / "default.toml").read_text()
    for key in valid_keys():
        name = key.split(".")[-1]
        assert f"\n{name} = " in text, f"{key} is not in configs/default.toml"


def test_precedence_defaults_files_set_flags(tmp_path: Path) -> None:
    a = tmp_path / "a.toml"
    b = tmp_path / "b.toml"
    a.write_text(
        'device = "replay:a"\n[mount]\nheight_m = 0.7\ntilt_deg = 10.0\n[scan]\nrange_max_m = 4.0\n'
    )
    b.write_text("[mount]\ntilt_deg = 12.0\n")
    cfg = build_config(
        [a, b], ["mount.tilt_deg=14.5", "scan.method=paper"], {"mount": {"height_m": 0.9}}
    )
    assert cfg.device == "replay:a"
    assert cfg.mount.height_m == 0.9  # the flag wins over the file
    assert cfg.mount.tilt_deg == 14.5  # --set wins over both files
    assert cfg.scan.range_max_m == 4.0  # file value kept where nothing overrides it
    assert cfg.scan.method == "paper"
    assert cfg.cliff == Config().cliff


def test_unknown_keys_list_the_valid_ones(tmp_path: Path) -> None:
    bad = tmp_path / "bad.toml"
    bad.write_text("[scan]\nrange_maxx_m = 3\n")
    with pytest.raises(ConfigError, match=r"unknown key 'scan.range_maxx_m'") as info:
        build_config([bad])
    assert "range_max_m" in (info.value.hint or "")
    with pytest.raises(ConfigError, match="unknown key 'bogus'"):
        build_config([], [], {"bogus": {}})
    with pytest.raises(ConfigError, match="unknown key"):
        build_config([], ["nosuch.key=1"])


@pytest.mark.parametrize(
    ("item", "match"),
    [
        ("mount.height_m=-1", r"height_m=-1.0 is out of range \(accepted: 0.01..10 m\)"),
        ("mount.tilt_deg=abc", r"mount.tilt_deg='abc' has the wrong type \(accepted: float\)"),
        ("scan.ground_remove=3", "wrong type"),
        ("daemon.tilt_source=gps", "accepted: auto, config, accel, serial, floor"),
        ("noequals", "is not key=value"),
    ],
)
def test_bad_values_are_one_line_errors(item: str, match: str) -> None:
    with pytest.raises(ConfigError, match=match) as info:
        build_config([], [item])
    assert "\n" not in str(info.value)


def test_bad_files_are_one_line_errors(tmp_path: Path) -> None:
    broken = tmp_path / "broken.toml"
    broken.write_text("[scan\nrange_max_m = ")
    with pytest.raises(ConfigError, match="is not valid TOML"):
        build_config([broken])
    with pytest.raises(ConfigError, match="does not exist"):
        build_config([tmp_path / "missing.toml"])


def test_config_round_trips_through_a_dict() -> None:
    from depthnav_daemon.config.loader import config_from_dict

    cfg = build_config([], ["scan.method=paper", "mount.roll_deg=3"])
    assert config_from_dict(config_to_dict(cfg)) == cfg


@pytest.mark.parametrize(
    ("item", "text"),
    [
        ('memory.enabled="maybe"', r"memory.enabled='maybe' is not known \(accepted: auto, true"),
        ("memory.cell_m=0.0", r"memory.cell_m=0.0 is out of range"),
        ("memory.size_m=0.05", r"memory.size_m=0.05 is out of range"),
        ("odometry.stale_s=-1", r"odometry.stale_s=-1.0 is out of range"),
        ("odometry.max_jump_m=0", r"odometry.max_jump_m=0.0 is out of range"),
        ("daemon.sensor_max_age_s=0", r"daemon.sensor_max_age_s=0.0 is out of range"),
    ],
)
def test_bad_memory_and_odometry_settings_are_one_line(item: str, text: str) -> None:
    with pytest.raises(ConfigError, match=text) as info:
        build_config([], [item])
    assert "\n" not in str(info.value)


@pytest.mark.parametrize(("value", "want"), [("true", True), ("false", False), ('"auto"', "auto")])
def test_memory_enabled_takes_auto_or_a_boolean(value: str, want: object) -> None:
    assert build_config([], [f"memory.enabled={value}"]).memory.enabled == want
