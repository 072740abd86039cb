"""Device spec grammar, aliases and the unknown scheme/option messages."""

from __future__ import annotations

import pytest

import drivers
from drivers.errors import DeviceSpecError, DriverError
from drivers.spec import parse_spec


@pytest.mark.parametrize(
    ("text", "scheme", "target", "options"),
    [
        ("kinect", "kinect", "", {}),
        ("kinect://1", "kinect", "1", {}),
        ("openni://", "openni", "", {}),
        ("openni:recording.oni", "openni", "recording.oni", {}),
        ("openni://Dummy?mode=320x240@30", "openni", "Dummy", {"mode": "320x240@30"}),
        ("replay:/data/x?rate=max&loop=1", "replay", "/data/x", {"rate": "max", "loop": "1"}),
        ("REPLAY:rel/path", "replay", "rel/path", {}),
    ],
)
def test_parse_spec_splits_scheme_target_and_options(text, scheme, target, options):
    spec = parse_spec(text)
    assert (spec.scheme, spec.target, dict(spec.options)) == (scheme, target, options)


@pytest.mark.parametrize(
    "text", ["", "  ", "1abc:x", "replay:x?rate", "replay:x?rate=max&rate=realtime"]
)
def test_malformed_specs_are_rejected_with_a_message(text):
    with pytest.raises(DeviceSpecError) as info:
        parse_spec(text)
    assert "\n" not in str(info.value)


def test_unknown_scheme_lists_the_valid_ones():
    with pytest.raises(DeviceSpecError) as info:
        drivers.create_driver("zed://")
    assert "zed" in str(info.value)
    for scheme in ("kinect", "openni", "replay", "realsense"):
        assert scheme in info.value.hint


@pytest.mark.parametrize("text", ["replay:x?speed=2", "kinect?mode=1", "openni://?bogus=1"])
def test_unknown_option_lists_the_valid_ones(text):
    with pytest.raises(DeviceSpecError) as info:
        drivers.create_driver(text)
    message = str(info.value)
    assert "unknown option" in message and "valid options:" in message
    assert info.value.hint


@pytest.mark.parametrize(
    "text",
    [
        "replay:x?rate=fast",
        "replay:x?loop=maybe",
        "replay:x?fx=abc",
        "replay:x?fps=0",
        "kinect://x",
        "kinect?accel=gps",
    ],
)
def test_bad_option_values_are_rejected(text):
    with pytest.raises(DriverError) as info:
        drivers.create_driver(text)
    assert "\n" not in str(info.value)


def test_create_driver_does_no_io(tmp_path):
    missing = tmp_path / "nothing-here"
    driver = drivers.create_driver(f"replay:{missing}?rate=max")
    with pytest.raises(DriverError) as info:
        driver.open()
    assert str(missing) in str(info.value)


def test_xtion_alias_is_openni():
    assert type(drivers.create_driver("xtion")).__name__ == "OpenNIDriver"


def test_describe_backends_names_every_backend():
    names = [name for name, _ in drivers.describe_backends()]
    for scheme in ("kinect", "openni", "replay"):
        assert any(n.startswith(scheme) for n in names), names


def test_kinect_intrinsics_options_are_checked_without_io():
    driver = drivers.create_driver("kinect://0?fx=590&cx=320.5")
    assert (driver.intrinsics.fx, driver.intrinsics.fy, driver.intrinsics.cx) == (
        590.0,
        580.0,
        320.5,
    )
    with pytest.raises(DeviceSpecError, match="cx"):
        drivers.create_driver("kinect?cx=700")
