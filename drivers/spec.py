"""Device specs: one string names a device, ``scheme[://target][?key=value&...]``.

``scheme:target`` is accepted as shorthand for ``scheme://target``. Each driver checks its own
options with :func:`check_options`, which rejects unknown keys and lists the valid ones.
"""

from __future__ import annotations

import re
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field, replace
from urllib.parse import quote, unquote, urlencode

from drivers.base import (
    DISTORTION_KEYS,
    MAX_FOCAL_PX,
    MAX_IMAGE_SIDE,
    MAX_RADIAL_COEFF,
    MAX_TANGENTIAL_COEFF,
    Intrinsics,
)
from drivers.errors import DeviceSpecError
from drivers.values import NumberError, short_repr, to_number

_SCHEME = re.compile(r"[a-z][a-z0-9+.-]*\Z")


@dataclass(frozen=True, slots=True)
class Spec:
    """A parsed device spec.

    Attributes:
        text: the spec as given.
        scheme: lower-case backend key, e.g. "kinect".
        target: what follows ``scheme:`` or ``scheme://`` up to ``?``; "" when absent.
        options: query options in the order given.
    """

    text: str
    scheme: str
    target: str = ""
    options: Mapping[str, str] = field(default_factory=dict)


def parse_spec(
    text: str, kind: str = "device", examples: str = "kinect, openni://, replay:fixtures/x?rate=max"
) -> Spec:
    """Split a spec into scheme, target and options (device specs here; sink specs use it too).

    Args:
        text: the spec.
        kind: what the spec names, for messages ("device", "sink").
        examples: a few valid specs of that kind, for hints.

    Raises:
        DeviceSpecError: empty spec, bad scheme, malformed or repeated option.
    """
    if not isinstance(text, str) or not text.strip():
        raise DeviceSpecError(f"empty {kind} spec", hint=f"e.g. {examples}")
    text = text.strip()
    body, sep, query = text.partition("?")
    scheme, colon, target = body.partition(":")
    scheme = scheme.lower()
    if not _SCHEME.match(scheme):
        raise DeviceSpecError(
            f"{kind} spec {short_repr(text)} does not start with a scheme",
            hint="write scheme[://target][?key=value&...], "
            f"e.g. {examples.rsplit(', ', maxsplit=1)[-1]}",
        )
    if colon and target.startswith("//"):
        target = target[2:]
    options: dict[str, str] = {}
    if sep:
        for part in query.split("&"):
            if not part:
                continue
            key, eq, value = part.partition("=")
            key = unquote(key).strip().lower()
            if not key or not eq:
                raise DeviceSpecError(
                    f"option {short_repr(part)} in {kind} spec {short_repr(text)} is not key=value",
                    hint="separate options with '&', e.g. ?key=value&other=value",
                )
            if key in options:
                raise DeviceSpecError(
                    f"option {short_repr(key)} is given twice in {kind} spec {short_repr(text)}"
                )
            options[key] = unquote(value)
    return Spec(text=text, scheme=scheme, target=unquote(target), options=options)


def format_spec(scheme: str, target: str, options: Mapping[str, str]) -> str:
    """The spec text that :func:`parse_spec` reads back as ``scheme``, ``target`` and ``options``
    (percent-encoded where a character would end the target or an option)."""
    # "scheme:" + a target that starts with "//" would read as "scheme://" plus the rest
    head = f"{scheme}://" if target.startswith("//") else f"{scheme}:"
    text = head + quote(target, safe="/:@,+~")
    if options:
        text += "?" + urlencode(options, quote_via=quote, safe="/:@,")
    return text


def check_options(spec: Spec, valid: Iterable[str], grammar: str, kind: str = "") -> None:
    """Reject options the driver (or sink) does not know.

    Args:
        spec: the parsed spec.
        valid: option names the driver accepts.
        grammar: the driver's spec grammar, quoted in the hint.
        kind: "" for devices, "sink " for sinks (the word before the scheme in messages).

    Raises:
        DeviceSpecError: naming the unknown option and listing the valid ones.
    """
    allowed = set(valid)
    for key in spec.options:
        if key not in allowed:
            names = ", ".join(sorted(allowed)) or "none"
            raise DeviceSpecError(
                f"unknown option {short_repr(key)} for {kind}{short_repr(spec.scheme)} in "
                f"{short_repr(spec.text)}; "
                f"valid options: {names}",
                hint=f"the {spec.scheme} spec is {grammar}",
            )


def choice_option(spec: Spec, key: str, choices: Iterable[str], default: str) -> str:
    """An option whose value must be one of ``choices``."""
    value = spec.options.get(key, default).lower()
    allowed = list(choices)
    if value not in allowed:
        raise DeviceSpecError(
            f"option {key}={short_repr(value)} in {short_repr(spec.text)} is not one of "
            f"{', '.join(allowed)}"
        )
    return value


def bool_option(spec: Spec, key: str, default: bool) -> bool:
    """An on/off option: 1/0, true/false, yes/no, on/off."""
    if key not in spec.options:
        return default
    value = spec.options[key].strip().lower()
    if value in ("1", "true", "yes", "on"):
        return True
    if value in ("0", "false", "no", "off"):
        return False
    raise DeviceSpecError(
        f"option {key}={short_repr(value)} in {short_repr(spec.text)} is not 0 or 1"
    )


def number_option(
    spec: Spec, key: str, default: float, low: float, high: float, *, integer: bool = False
) -> float:
    """A finite numeric option within [low, high] (an integer when ``integer``), or ``default``.

    The value must be plain ASCII digits (drivers.values.to_number): ``5²``, ``٥٦٠٠``, ``1_000``,
    ``nan``, ``inf`` and a 400-digit number are refused with one line.

    Raises:
        DeviceSpecError: not a number, not finite, not an integer when required, or out of range.
    """
    if key not in spec.options:
        return default
    raw = spec.options[key]
    try:
        return to_number(raw, integer=integer, low=low, high=high)
    except NumberError as exc:
        raise DeviceSpecError(
            f"option {key}={short_repr(raw)} in {short_repr(spec.text)} {exc}"
            + ("" if "accepted" in str(exc) else f" (accepted: {low:g}..{high:g})")
        ) from None


def float_option(
    spec: Spec, key: str, default: float | None, low: float = -1e12, high: float = 1e12
) -> float | None:
    """A finite number option within [low, high]."""
    if key not in spec.options:
        return default
    return float(number_option(spec, key, 0.0, low, high))


def int_option(spec: Spec, key: str, default: int, low: int = 0, high: int = 2**31) -> int:
    """An integer option within [low, high]."""
    if key not in spec.options:
        return default
    return int(number_option(spec, key, 0, low, high, integer=True))


PINHOLE_OPTIONS = ("fx", "fy", "cx", "cy")
INTRINSICS_OPTIONS = (*PINHOLE_OPTIONS, *DISTORTION_KEYS)


def intrinsics_options(spec: Spec) -> dict[str, float]:
    """The ``fx, fy, cx, cy`` (pixels) and lens ``k1, k2, p1, p2, k3`` (plumb_bob) options that
    override a device's own intrinsics."""
    out = {}
    for key in INTRINSICS_OPTIONS:
        if key in PINHOLE_OPTIONS:
            value = float_option(spec, key, None, -0.5, MAX_FOCAL_PX)
        else:
            limit = MAX_TANGENTIAL_COEFF if key.startswith("p") else MAX_RADIAL_COEFF
            value = float_option(spec, key, None, -limit, limit)
        if value is not None:
            out[key] = value
    return out


def with_overrides(base: Intrinsics, overrides: Mapping[str, float], what: str) -> Intrinsics:
    """``base`` with some of fx, fy, cx, cy, k1, k2, p1, p2, k3 replaced.

    Raises:
        DeviceSpecError: the result is not valid for the image size.
    """
    if not overrides:
        return base
    try:  # the rest of base (its lens model too) as it is
        return replace(base, **dict(overrides))
    except ValueError as exc:
        raise DeviceSpecError(f"{what}: intrinsics options do not fit the image: {exc}") from None


def mode_option(spec: Spec) -> tuple[int, int, int] | None:
    """``mode=WxH@FPS`` (a device's stream mode) as (width, height, fps); None when absent.

    Raises:
        DeviceSpecError: not WxH@FPS with sizes depthnav takes.
    """
    text = spec.options.get("mode")
    if text is None:
        return None
    size, _, fps = text.partition("@")
    width, _, height = size.lower().partition("x")
    try:  # ASCII digits, sizes within what depthnav takes (drivers.values.to_number)
        return (
            int(to_number(width, integer=True, low=1, high=MAX_IMAGE_SIDE)),
            int(to_number(height, integer=True, low=1, high=MAX_IMAGE_SIDE)),
            int(to_number(fps or "30", integer=True, low=1, high=1000)),
        )
    except NumberError:
        raise DeviceSpecError(
            f"mode={short_repr(text)} in {short_repr(spec.text)} is not WxH@FPS, e.g. 640x480@30 "
            f"(1..{MAX_IMAGE_SIDE} pixels each way)"
        ) from None
