"""docs/configuration.md from the tables: every file, its keys, their allowed values and defaults.

tests/test_config_docs.py holds the page equal to :func:`reference` of every file's table
(``python -m tests.test_config_docs`` writes it), so the page cannot drift from what is read.
"""

from __future__ import annotations

from collections.abc import Iterator, Sequence
from typing import Any

from planner.schema.config_file import ConfigFile
from planner.schema.nodes import Id, Kinds, ListOf, MapOf, Node, Nullable, Section, child

HEADER = """# Configuration files

Every configuration file the rig reads, its keys, what each allows and its default (generated from
the tables in `planner/schema/tables.py` by `planner/schema/docs.py`; `python -m
tests.test_config_docs` rewrites this page). A file is refused, before anything uses it, when a key
is unknown, a required key is missing or a value is outside its range or form; the message names
the file, the key path (`phones[2].height_mm`) and what is allowed. Every file is read with its
size bounded, flow lists and mappings nested at most 32 deep and YAML aliases counted as the
values they stand for (docs/hardening.md). A key path `a[].b` is key `b` of every entry of the list
`a`; `a.<id>` is every key of the mapping `a`.
"""


def _size(n: int) -> str:
    for unit, scale in (("MiB", 1024**2), ("KiB", 1024)):
        if n % scale == 0:
            return f"{n // scale} {unit}"
    return f"{n} bytes"


def _default(node: Node) -> str:
    if isinstance(node, Section) and node.optional:
        return "optional"
    value = node.default
    if node.required:
        return "required"
    if value is None:
        return "none"
    if isinstance(value, bool):
        return f"`{str(value).lower()}`"
    if isinstance(value, float):
        return f"`{value:g}`"
    return f"`{value}`"


def rows(node: Node, key: str, field: bool = True) -> Iterator[tuple[str, str, str, str]]:
    """(key path, allowed, default, meaning) of ``node`` at ``key`` and of everything inside it;
    field: ``node`` is a named field (an entry of a mapping of ids has no default)."""
    yield key, node.form(), _default(node) if field else "", node.doc
    yield from _inside(node, key)


def _inside(node: Node, key: str) -> Iterator[tuple[str, str, str, str]]:
    if isinstance(node, Nullable):
        yield from _inside(node.inner, key)
    elif isinstance(node, Section):
        for name, field in node.fields.items():
            yield from rows(field, child(key, name))
    elif isinstance(node, ListOf):
        yield from _inside(node.item, f"{key}[]")
    elif isinstance(node, MapOf):
        yield from rows(node.values, f"{key}.<{'id' if isinstance(node.keys, Id) else 'key'}>", field=False)
    elif isinstance(node, Kinds):
        for name, kind in node.kinds.items():
            alone = f"; or `{name}` alone" if kind.bare else ""
            yield f"{key}.{name}", kind.value.form() + alone, "", kind.doc


def _cell(text: Any) -> str:
    return str(text).replace("|", "\\|")


def section(config: ConfigFile) -> str:
    """The page's section of one file."""
    about = f"{config.table.doc[0].upper()}{config.table.doc[1:]}. Where: {config.where}."
    lines = [f"## {config.what[0].upper()}{config.what[1:]}", "", f"{about} At most {_size(config.max_bytes)}.", "",
             "| key | allowed | default | meaning |", "| --- | --- | --- | --- |"]
    for name, field in config.table.fields.items():
        for key, allowed, default, doc in rows(field, name):
            lines.append(f"| `{key}` | {_cell(allowed)} | {default} | {_cell(doc)} |")
    if config.rules:
        lines += ["", "Checked between keys:", ""] + [f"- {rule}" for rule in config.rules]
    return "\n".join(lines) + "\n"


def reference(files: Sequence[ConfigFile]) -> str:
    """The whole page: the header, then one section a file."""
    return "\n".join([HEADER, *(section(f) for f in files)])
