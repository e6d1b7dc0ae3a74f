"""Reading and validating every configuration file: one table per file, one set of messages.

:mod:`planner.schema.nodes` holds the forms a value may take, :mod:`planner.schema.tables` the table
of every file, :mod:`planner.schema.yaml_files` the bounded YAML reading, and
:mod:`planner.schema.docs` renders the tables as docs/configuration.md.
"""

from planner.schema.config_file import ConfigFile
from planner.schema.nodes import (
    ID_PATTERN,
    MAX_STRING,
    REQUIRED,
    Choice,
    ConfigError,
    Flag,
    Id,
    Integer,
    Kind,
    Kinds,
    ListOf,
    MapOf,
    Node,
    Note,
    Nullable,
    Number,
    Section,
    Serial,
    Text,
    Tuple,
    key_name,
    show,
)

__all__ = ["ID_PATTERN", "MAX_STRING", "REQUIRED", "Choice", "ConfigError", "ConfigFile", "Flag", "Id", "Integer",
           "Kind", "Kinds", "ListOf", "MapOf", "Node", "Note", "Nullable", "Number", "Section", "Serial", "Text",
           "Tuple", "key_name", "show"]
