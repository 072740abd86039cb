"""A YAML loader for untrusted files: nesting bounded and aliases of lists and mappings refused.

A billion-laughs document (each list nine aliases of the one before) is small on disk, cheap to
parse (aliases are shared nodes) and explodes in whatever walks it: an error message formatting
it took 8.4 GB and 160 s. Neither a ROS parameter file nor a ROS 2 bag's ``metadata.yaml`` needs
aliases of collections; aliases of single values (``*speed``) are still accepted. Used by the
parameter files' reader (depthnav_daemon/config/ros_params.py) and the bag reader
(drivers/formats/bag_limits.py).
"""

from __future__ import annotations

from typing import Any

import yaml

from drivers.values import short_text

MAX_YAML_DEPTH = 64  # nesting levels; a parameter file has three, a bag's metadata about six


class YamlRefusedError(Exception):
    """The document is refused (the message says why, in a few words)."""


class BoundedYamlLoader(yaml.SafeLoader):
    """yaml.SafeLoader that raises YamlRefusedError past MAX_YAML_DEPTH levels or on an alias
    of a list or mapping."""

    _depth = 0

    def compose_node(self, parent: Any, index: Any) -> Any:
        if self.check_event(yaml.AliasEvent):
            anchor = self.peek_event().anchor
            node = self.anchors.get(anchor)
            if isinstance(node, yaml.CollectionNode):
                raise YamlRefusedError(
                    f"alias *{short_text(anchor, 40)} repeats a list or mapping "
                    "(aliases of collections are not accepted)"
                )
            return super().compose_node(parent, index)
        self._depth += 1
        try:
            if self._depth > MAX_YAML_DEPTH:
                raise YamlRefusedError(f"nested deeper than {MAX_YAML_DEPTH} levels")
            return super().compose_node(parent, index)
        finally:
            self._depth -= 1
