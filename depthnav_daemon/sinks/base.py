"""The Sink interface every output implements, the context handed to ``open()``, and spec parsing.

A sink spec is one string, ``scheme[://target][?key=value&...]`` (``scheme:target`` is shorthand),
the same grammar as device specs. Constructing a sink does no I/O; ``open()`` touches the network,
file or port; ``write()`` is called once per processed frame and must return quickly; ``close()``
flushes and is safe to call twice.
"""

from __future__ import annotations

import functools
import ipaddress
import logging
import math
import re
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Protocol, TypeVar, runtime_checkable

from depthnav_daemon.errors import ConfigError
from drivers.errors import DeviceSpecError
from drivers.spec import Spec, parse_spec
from drivers.spec import bool_option as spec_bool_option
from drivers.spec import check_options as spec_check_options
from drivers.spec import choice_option as spec_choice_option
from drivers.spec import number_option as spec_number_option
from drivers.values import short_repr, short_text

if TYPE_CHECKING:
    from depthnav_daemon.pipeline import Result
    from depthnav_daemon.pipeline.geometry import Mount
    from depthnav_daemon.pipeline.scan import ScanParams
    from drivers.base import DeviceInfo, Frame

log = logging.getLogger(__name__)

_SCHEME = re.compile(r"[a-z][a-z0-9+.-]*\Z")
MAX_PORT = 65535
_PORT = re.compile(r"[0-9]{1,5}\Z")  # ASCII digits only
_LABEL = re.compile(r"(?!-)[A-Za-z0-9_-]{1,63}(?<!-)\Z")
MAX_HOST_CHARS = 253
T = TypeVar("T")


@dataclass(frozen=True)
class SinkContext:
    """Everything a sink may need besides the per-frame data; handed to ``Sink.open()``.

    Attributes:
        device: what the opened driver says about its device.
        scan_params: the scan parameters in use (to draw the used rows and obstacle pixels).
        cliff_block_size: side of a cliff-detection block, pixels (to draw the blocks).
        version: the depthnav version string.
        mount: the configured mount (what the floor estimates are compared with), or None.
        body_m: the robot's outline on the floor ([robot] footprint_m, base frame, metres)
            whose readings the stages ignore, drawn by the viewers; () when none is configured.
    """

    device: DeviceInfo
    scan_params: ScanParams
    cliff_block_size: int
    version: str
    mount: Mount | None = None
    body_m: tuple[tuple[float, float], ...] = ()


@runtime_checkable
class Sink(Protocol):
    """Receives every processed frame.

    Attributes:
        name: the spec the sink was made from, for messages.

    A sink that draws the obstacle pixels sets ``needs_obstacle_mask = True`` (read once, after
    ``open``); the loop then asks the pipeline for ``Result.obstacle_mask``. Sinks never call
    stage code themselves.
    """

    name: str

    def open(self, context: SinkContext) -> None:
        """Connect, create the file or open the port.

        Raises:
            SinkError: the output cannot be opened; the message says which and ``hint`` what to do.
        """
        ...

    def write(self, frame: Frame, result: Result) -> None:
        """Send one processed frame. Must not block the frame loop for long.

        Raises:
            SinkError: the output failed for good; the daemon closes and drops this sink.
        """
        ...

    def close(self) -> None:
        """Flush and release the output. Safe to call twice, and after a failed ``open()``."""
        ...


# A sink spec has the grammar and shape of a device spec: one parser serves both.
SinkSpec = Spec


def parse_sink_spec(text: str) -> SinkSpec:
    """Split a sink spec into scheme, target and options.

    Raises:
        ConfigError: empty spec, bad scheme, malformed or repeated option.
    """
    try:
        return parse_spec(text, "sink", "stdout, rerun:run.rrd, udp://127.0.0.1:5600")
    except DeviceSpecError as exc:
        raise ConfigError(str(exc), hint=exc.hint) from None


def _config_errors(fn: Callable[..., T]) -> Callable[..., T]:
    """``fn`` from drivers.spec, raising ConfigError (the sinks' error) for a bad option."""

    @functools.wraps(fn)
    def wrapper(*args: Any, **kwargs: Any) -> T:
        try:
            return fn(*args, **kwargs)
        except DeviceSpecError as exc:
            raise ConfigError(str(exc), hint=exc.hint) from None

    return wrapper


# the device specs' option helpers, one family for both (sink messages say "sink")
check_options = _config_errors(functools.partial(spec_check_options, kind="sink "))
number_option = _config_errors(spec_number_option)
bool_option = _config_errors(spec_bool_option)
choice_option = _config_errors(spec_choice_option)


def check_host(host: str, spec: SinkSpec) -> str:
    """``host`` if it is an IP address or a valid host name, else one ConfigError line.

    A name must encode with IDNA and have labels of 1..63 letters, digits, '-' or '_' (at most
    253 characters): ``a..b`` or a 64-character label made the idna codec raise UnicodeError
    when the sink opened.
    """
    try:
        ipaddress.ip_address(host)
    except ValueError:
        pass
    else:
        return host
    try:
        ascii_name = host.encode("idna").decode("ascii")
    except UnicodeError:
        ascii_name = ""
    labels = ascii_name.removesuffix(".").split(".")
    if not ascii_name or len(ascii_name) > MAX_HOST_CHARS or not all(map(_LABEL.match, labels)):
        raise ConfigError(
            f"host {short_repr(host)} in sink spec {short_repr(spec.text)} is not a valid "
            "host name or IP address",
            hint="e.g. 127.0.0.1, ::1 or robot.local (labels of 1..63 letters, digits, '-')",
        )
    return host


def parse_host_port(spec: SinkSpec, default_host: str, default_port: int | None) -> tuple[str, int]:
    """``HOST:PORT``, ``:PORT``, ``PORT``, ``HOST``, ``[v6addr]:PORT`` or "" from the spec's target.

    The port is ASCII digits only (Python's int() also reads '٥٦٠٠' as 5600); the host is
    checked by check_host.

    Args:
        spec: the parsed spec.
        default_host: used when the host part is empty.
        default_port: used when the port is absent; None makes the port required.

    Raises:
        ConfigError: a missing or invalid port, an invalid host.
    """
    target = spec.target.strip().rstrip("/")
    host, port_text = target, ""
    if target.startswith("["):  # [::1]:5600
        end = target.find("]")
        if end < 0:
            raise ConfigError(f"unclosed '[' in sink spec {short_repr(spec.text)}")
        host, rest = target[1:end], target[end + 1 :]
        if rest:
            if not rest.startswith(":"):
                raise ConfigError(
                    f"expected ':PORT' after ']' in sink spec {short_repr(spec.text)}"
                )
            port_text = rest[1:]
    elif target.count(":") == 1:
        host, port_text = target.split(":")
    elif _PORT.match(target):  # udp:5600
        host, port_text = "", target
    host = check_host(host.strip() or default_host, spec)
    if not port_text:
        if default_port is None:
            raise ConfigError(
                f"sink spec {short_repr(spec.text)} has no port",
                hint=f"write {spec.scheme}://HOST:PORT, e.g. {spec.scheme}://127.0.0.1:5600",
            )
        return host, default_port
    if not _PORT.match(port_text) or not 1 <= int(port_text) <= MAX_PORT:
        raise ConfigError(
            f"port {short_repr(port_text)} in sink spec {short_repr(spec.text)} is not 1..65535",
            hint="a port is ASCII digits, e.g. 5600",
        )
    return host, int(port_text)


class RateLimitedLog:
    """Counts repeated failures and logs them at most once per ``period_s`` (with the count).

    Used where a failure must never stop the frame loop (a UDP receiver that went away) but the
    user should still hear about it without a log line per frame.
    """

    def __init__(self, logger: logging.Logger, period_s: float = 10.0) -> None:
        self._log = logger
        self._period_s = period_s
        self._last = -math.inf
        self.count = 0  # failures since the sink opened
        self._unreported = 0

    def failed(self, message: str, *args: object) -> None:
        """Count one failure; log it (with how many happened since the last line) when due."""
        self.count += 1
        self._unreported += 1
        now = time.monotonic()
        if now - self._last >= self._period_s:
            self._log.warning(
                message + " (%d failure(s) since the last report, %d in total)",
                *args,
                self._unreported,
                self.count,
            )
            self._last = now
            self._unreported = 0


_ADDRESS = re.compile(r"\[?[0-9A-Fa-f:.]*[0-9][0-9A-Fa-f:.]*\]?(?::[0-9]+)?")
_SUMMARY_KEY_CHARS = 40  # a kind is named by the start of its message, addresses and numbers out


class RateLimitFilter(logging.Filter):
    """Lets through the first record of each kind, then one per ``period_s`` with the count of
    those held back; installed on a library's loggers (the foxglove server logs every invalid
    message a client sends: 20,000 lines for one client).

    A record's kind is its logger, level and message text up to its first address or number
    (``Invalid message from 127.0.0.1:5512: ...`` and ``... :5513: ...`` are one kind). Every
    message that passes is cut to 200 characters with control characters escaped (a client
    chooses what the error quotes). Thread-safe: the records come from the library's threads.
    """

    def __init__(self, period_s: float = 10.0) -> None:
        super().__init__()
        self.period_s = period_s
        self._lock = threading.Lock()
        self._last: dict[tuple[str, int, str], float] = {}
        self._held: dict[tuple[str, int, str], int] = {}

    @staticmethod
    def kind(record: logging.LogRecord, text: str) -> tuple[str, int, str]:
        found = _ADDRESS.search(text)
        head = text[: found.start()] if found else text
        return record.name, record.levelno, head[:_SUMMARY_KEY_CHARS].strip()

    def filter(self, record: logging.LogRecord) -> bool:
        text = record.getMessage().encode("unicode_escape").decode("ascii")
        key = self.kind(record, text)
        now = time.monotonic()
        with self._lock:
            if now - self._last.get(key, -math.inf) < self.period_s:
                self._held[key] = self._held.get(key, 0) + 1
                return False
            self._last[key] = now
            held = self._held.pop(key, 0)
        text = short_text(text, 200)
        if held:
            text += f" ({held} more like it in the last {self.period_s:g} s, not shown)"
        record.msg, record.args = text, None
        return True

    def held_back(self) -> dict[tuple[str, int, str], int]:
        """The records held back since each kind's last line: kind -> count (then cleared)."""
        with self._lock:
            held, self._held = self._held, {}
        return held
