"""Reading a configuration YAML file with every size bounded.

Rig files, hardware files, calibration files, target files and focus tables are read the same
way: at most ``max_bytes`` bytes, flow collections ([ ], { }) nested at most 32 deep (PyYAML's
scanner is quadratic in that depth), the safe loader only, and any failure (unreadable, too large,
not YAML, a 5000-digit number, nesting thousands deep) turned into the caller's typed error naming
the file.

Aliases are counted as what they stand for: a document whose nodes, each alias expanded, number
more than ``max_bytes`` (more than a file of the allowed size can hold without aliases) is refused
while it is composed, naming the key where the count passed the bound. Loaded, an alias is a
shared reference, but merging mappings (``<<``), ``str()`` or walking the value expands it: nine
aliases of nine aliases, twelve deep, are 9**12 values.
"""

from __future__ import annotations

import re
from collections.abc import Callable
from pathlib import Path
from typing import Any

import yaml

from planner.files import read_at_most

MAX_FLOW_NESTING = 32
_FLOW_SYNTAX = re.compile(rb"[\[\]{}'\"#\n]")


def flow_nesting(text: bytes) -> int:
    """Deepest nesting of YAML flow collections ([ ] and { }) outside quotes and comments."""
    depth = deepest = 0
    quote: bytes | None = None
    comment = False
    for match in _FLOW_SYNTAX.finditer(text):
        char = match.group()
        if comment:
            comment = char != b"\n"
        elif quote is not None:
            quote = None if char == quote else quote
        elif char in (b"'", b'"'):
            quote = char
        elif char == b"#":
            comment = True
        elif char in (b"[", b"{"):
            depth += 1
            deepest = max(deepest, depth)
        elif char in (b"]", b"}"):
            depth -= 1
    return deepest


class ExpansionTooLarge(ValueError):
    """A YAML document stands for more nodes than allowed once its aliases are expanded."""

    def __init__(self, key: str, nodes: int, limit: int) -> None:
        self.key = key
        self.nodes = nodes
        self.limit = limit
        super().__init__(f"{key}: aliases make it {nodes} values, more than the {limit} a file of "
                         f"the allowed size holds without aliases")


class _BoundedLoader(yaml.SafeLoader):
    """The safe loader, counting each node as the nodes it stands for (an alias: its anchor's)."""

    def __init__(self, text: bytes, max_nodes: int) -> None:
        super().__init__(text)
        self.max_nodes = max_nodes
        self._expanded: dict[int, int] = {}  # id(node) -> nodes it stands for; every node stays referenced
        self._path: list[str] = []

    def compose_node(self, parent: yaml.Node | None, index: Any) -> yaml.Node:
        step = _step(parent, index)
        if step is not None:
            self._path.append(step)
        try:
            alias = self.check_event(yaml.AliasEvent)
            node = super().compose_node(parent, index)
            if node is None:  # PyYAML composes a node or raises; its stub allows None
                raise yaml.YAMLError(f"no node composed at {''.join(self._path).lstrip('.') or '<document>'}")
            if alias:  # its anchor, counted once composed; one still being composed (a cycle) counts once
                size = self._expanded.get(id(node), 1)
            else:
                size = self._expanded[id(node)] = self._count(node)
            if size > self.max_nodes:
                raise ExpansionTooLarge("".join(self._path).lstrip(".") or "<document>", size, self.max_nodes)
            return node
        finally:
            if step is not None:
                self._path.pop()

    def _count(self, node: yaml.Node) -> int:
        if isinstance(node, yaml.SequenceNode):
            children: list[yaml.Node] = list(node.value)
        elif isinstance(node, yaml.MappingNode):
            children = [part for pair in node.value for part in pair]
        else:
            return 1
        return 1 + sum(self._expanded.get(id(child), 1) for child in children)


def _step(parent: yaml.Node | None, index: Any) -> str | None:
    """The path step of a child: ".key" for a mapping's value, "[i]" for a list item, None for a key."""
    if isinstance(parent, yaml.SequenceNode):
        return f"[{index}]"
    if isinstance(parent, yaml.MappingNode) and index is not None:
        key = index.value if isinstance(index, yaml.ScalarNode) else "<key>"
        return f".{key[:40]}"
    return None


def load_bounded(text: bytes, max_nodes: int) -> Any:
    """``yaml.safe_load(text)`` of a document of at most max_nodes, aliases expanded
    (:class:`ExpansionTooLarge` otherwise)."""
    loader = _BoundedLoader(text, max_nodes)
    try:
        return loader.get_single_data()
    finally:
        loader.dispose()


def read_yaml(path: Path, *, max_bytes: int, what: str,
              error: Callable[[str, str], Exception]) -> tuple[Any, bytes]:
    """(parsed document, raw bytes) of a YAML file; ``error(key, problem)`` builds the exception
    raised, the key ``<file>`` for the file as a whole, the alias's path when aliases expand too far.

    what: the kind of file, for messages ("rig file", "focus table").
    """
    try:
        text = read_at_most(path, max_bytes, what, lambda problem: error("<file>", problem))
    except OSError as exc:
        raise error("<file>", f"cannot read: {exc.strerror or exc}") from exc
    if flow_nesting(text) > MAX_FLOW_NESTING:
        raise error("<file>", f"lists or mappings nested more than {MAX_FLOW_NESTING} deep: not a {what}")
    try:
        return load_bounded(text, max_bytes), text
    except ExpansionTooLarge as exc:
        raise error(exc.key, f"aliases make it {exc.nodes} values, more than the {exc.limit} a {what} "
                             "holds without aliases") from None
    except yaml.YAMLError as exc:
        raise error("<file>", f"not valid YAML: {str(exc)[:300]}") from exc
    except (ValueError, RecursionError) as exc:
        raise error("<file>", f"not a {what}: {type(exc).__name__}: {str(exc)[:200]}") from exc
