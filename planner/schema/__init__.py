"""Reading and validating every configuration file: one table per file, one set of messages.

:mod:`planner.schema.nodes` holds the forms a value may take, :mod:`planner.schema.tables` the table
of every file, :mod:`planner.schema.yaml_files` the bounded YAML reading, and
:mod:`planner.schema.docs` renders the tables as docs/configuration.md.
"""

from planner.schema.config_file import ConfigFile
from planner.schema.nodes import ConfigError, Kind, Nullable, Serial, Text, key_name, show

__all__ = ["ConfigError", "ConfigFile", "Kind", "Nullable", "Serial", "Text", "key_name", "show"]
