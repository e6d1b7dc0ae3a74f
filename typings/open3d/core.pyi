# Read as untyped: typings/open3d/__init__.pyi says why.
from typing import Any

def __getattr__(name: str) -> Any: ...
