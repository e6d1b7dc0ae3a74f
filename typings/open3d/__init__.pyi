# open3d ships stubs generated from its bindings that mark optional arguments required
# (open3d.core.Tensor(array) takes dtype and device as optional); mypy reads open3d through
# this stub instead, as untyped.
from typing import Any

def __getattr__(name: str) -> Any: ...
