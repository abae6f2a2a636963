"""Settings files (camera, target, mount) read as YAML without what a settings file never
needs and a broken generator or an attacker could use: aliases that expand to more than
``MAX_VALUES`` values (a 1 kB "billion laughs" file expands to gigabytes once walked),
nesting deeper than ``MAX_DEPTH`` (a 100,000-deep file exhausts Python's recursion) and files
over ``MAX_BYTES``. Each is a ``yaml.YAMLError`` that says which, so the callers' own error
for a bad YAML file names the file."""

from __future__ import annotations

from typing import Any

import yaml
from yaml.composer import ComposerError

MAX_BYTES = 1_000_000
MAX_DEPTH = 64
MAX_VALUES = 100_000  # scalars, lists and mappings, each alias counted as what it repeats


class _SettingsLoader(yaml.SafeLoader):
    """``yaml.SafeLoader`` refusing deep nesting."""

    def __init__(self, stream: str) -> None:
        super().__init__(stream)
        self._depth = 0

    def _mark(self) -> Any:
        """Where the next event starts (line and column for the message)."""
        return self.peek_event().start_mark  # type: ignore[no-untyped-call]  # stubs lack it

    def compose_node(self, parent: Any, index: Any) -> Any:
        self._depth += 1
        try:
            if self._depth > MAX_DEPTH:
                raise ComposerError(None, None, f"nested over {MAX_DEPTH} levels", self._mark())
            return super().compose_node(parent, index)
        finally:
            self._depth -= 1


def _expanded(node: yaml.Node, sizes: dict[int, int]) -> int:
    """How many values ``node`` stands for with every alias written out (shared nodes are
    counted once per use, computed once)."""
    known = sizes.get(id(node))
    if known is not None:
        return known
    if isinstance(node, yaml.SequenceNode):
        size = 1 + sum(_expanded(child, sizes) for child in node.value)
    elif isinstance(node, yaml.MappingNode):
        size = 1 + sum(_expanded(k, sizes) + _expanded(v, sizes) for k, v in node.value)
    else:
        size = 1
    sizes[id(node)] = size
    return size


def load(text: str) -> Any:
    """The YAML document in ``text`` (safe types only), or a ``yaml.YAMLError``."""
    if len(text) > MAX_BYTES:
        raise yaml.YAMLError(f"over {MAX_BYTES // 1_000_000} MB: not a settings file")
    loader = _SettingsLoader(text)
    try:
        node = loader.get_single_node()
        if node is None:
            return None
        if _expanded(node, {}) > MAX_VALUES:
            raise yaml.YAMLError(
                f"its aliases expand to over {MAX_VALUES:,} values: not a settings file"
            )
        return loader.construct_document(node)
    finally:
        loader.dispose()
