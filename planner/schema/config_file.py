"""One kind of configuration file: its size bound, its table, and how it is read."""

from __future__ import annotations

import hashlib
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from planner.schema.nodes import ErrorFactory, Reader, Section
from planner.schema.yaml_files import read_yaml


@dataclass(frozen=True)
class ConfigFile:
    """what: the kind of file in messages ("rig file"); where: where it lives, for the reference
    page; max_bytes: its size bound (and the bound of its values once aliases are expanded);
    table: its keys; rules: the relations between keys the reading module checks, in words."""

    what: str
    where: str
    max_bytes: int
    table: Section
    rules: tuple[str, ...] = ()

    def load(self, path: Path | str, error: ErrorFactory) -> tuple[dict[str, Any], str]:
        """(validated values, SHA-256 of the file's bytes); every refusal is ``error(path, key, problem)``."""
        path = str(path)
        raw, text = read_yaml(Path(path), max_bytes=self.max_bytes, what=self.what,
                              error=lambda key, problem: error(path, key, problem))
        return self.check(raw, path, error), hashlib.sha256(text).hexdigest()

    def check(self, raw: Any, path: Path | str, error: ErrorFactory) -> dict[str, Any]:
        """The validated values of an already-parsed document."""
        return self.table.read(raw, "", Reader(str(path), error))
