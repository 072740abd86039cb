"""The ``realsense`` device spec: its grammar, options and the parsing of the compound ones."""

from __future__ import annotations

from drivers.errors import DeviceSpecError
from drivers.realsense import sdk
from drivers.spec import INTRINSICS_OPTIONS, Spec, mode_option
from drivers.values import short_repr

GRAMMAR = (
    "realsense[://SERIAL][?mode=WxH@FPS&preset=NAME&emitter=0|1&laser_power=MW&filters=..&accel=0|1]"
    " or realsense?file=REC.db3|REC.bag[&rate=max|realtime&filters=..&accel=0|1]"
)
LIVE_OPTIONS = ("mode", "preset", "emitter", "laser_power", "filters", "accel", *INTRINSICS_OPTIONS)
FILE_OPTIONS = ("file", "rate", "filters", "accel", *INTRINSICS_OPTIONS)
DEFAULT_MODE = (640, 480, 30)
DEFAULT_PRESET = "high_accuracy"


def parse_mode(spec: Spec) -> tuple[int, int, int]:
    """``mode=WxH@FPS`` as (width, height, fps), DEFAULT_MODE when absent."""
    return mode_option(spec) or DEFAULT_MODE


def parse_filters(spec: Spec) -> tuple[str, ...]:
    """``filters=a,b`` as filter names, in the SDK's recommended order."""
    text = spec.options.get("filters", "")
    names = tuple(n.strip().lower() for n in text.split(",") if n.strip())
    for name in names:
        if name not in sdk.FILTERS:
            raise DeviceSpecError(
                f"filters={short_repr(text)} in {short_repr(spec.text)}: {short_repr(name)} is "
                f"not one of {', '.join(sdk.FILTERS)}"
            )
    if len(set(names)) != len(names):
        raise DeviceSpecError(f"filters={short_repr(text)} names a filter twice")
    return tuple(n for n in sdk.FILTERS if n in names)  # the SDK's recommended order
