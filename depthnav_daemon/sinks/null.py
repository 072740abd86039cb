"""``null``: discards every frame (to measure the pipeline's throughput without output cost).

Spec: ``null`` (no target, no options).
"""

from __future__ import annotations

import logging
from typing import TYPE_CHECKING

from depthnav_daemon.errors import ConfigError
from depthnav_daemon.sinks.base import SinkContext, SinkSpec, check_options

if TYPE_CHECKING:
    from depthnav_daemon.pipeline import Result
    from drivers.base import Frame

log = logging.getLogger(__name__)

GRAMMAR = "null"


class NullSink:
    """Counts frames and drops them."""

    def __init__(self, name: str = "null") -> None:
        self.name = name
        self.frames = 0

    @classmethod
    def from_spec(cls, spec: SinkSpec) -> NullSink:
        """Build from a parsed spec. Raises ConfigError for a target or any option."""
        check_options(spec, (), GRAMMAR)
        if spec.target:
            raise ConfigError(
                f"the null sink takes no target, got {spec.text!r}", hint=f"write {GRAMMAR}"
            )
        return cls(spec.text)

    def open(self, context: SinkContext) -> None:
        """Nothing to open."""

    def write(self, frame: Frame, result: Result) -> None:
        """Count the frame."""
        self.frames += 1

    def close(self) -> None:
        """Nothing to flush."""
        log.debug("null sink discarded %d frames", self.frames)
