"""The error trees: every error the daemon defines derives from DaemonError, and no two error
classes anywhere in the code share a name (an ``except PullFailed`` must mean one thing)."""

from __future__ import annotations

import ast
import builtins
import importlib
import pkgutil
from collections import defaultdict
from pathlib import Path

import daemon
from daemon.errors import DaemonError

ROOT = Path(__file__).resolve().parent.parent
PACKAGES = ("planner", "drivers", "daemon", "sim", "analysis", "cli")
BUILTIN_ERRORS = {name for name, obj in vars(builtins).items()
                  if isinstance(obj, type) and issubclass(obj, BaseException)}


def error_classes(sources: dict[str, str]) -> dict[str, list[str]]:
    """Class name -> the files defining it, for every class that derives (through classes
    defined in ``sources``) from a built-in exception."""
    bases: dict[tuple[str, str], list[str]] = {}
    for label, text in sources.items():
        for node in ast.walk(ast.parse(text, label)):
            if isinstance(node, ast.ClassDef):
                bases[(node.name, label)] = [ast.unparse(b).rpartition(".")[2] for b in node.bases]
    errors = set(BUILTIN_ERRORS)
    changed = True
    while changed:
        found = {name for (name, _), names in bases.items() if errors.intersection(names)}
        changed = not found <= errors
        errors |= found
    where: dict[str, list[str]] = defaultdict(list)
    for name, label in bases:
        if name in errors:
            where[name].append(label)
    return where


def test_no_two_error_classes_share_a_name() -> None:
    sources = {str(p.relative_to(ROOT)): p.read_text()
               for package in PACKAGES for p in sorted((ROOT / package).rglob("*.py"))}
    twice = {name: files for name, files in error_classes(sources).items() if len(files) > 1}
    assert twice == {}


def test_the_name_check_itself() -> None:
    sources = {
        "a.py": "class PullFailed(OSError): pass\nclass Other(PullFailed): pass\nclass Plain: pass\n",
        "b.py": "class PullFailed(Exception): pass\nclass Plain: pass\n",
    }
    found = error_classes(sources)
    assert found["PullFailed"] == ["a.py", "b.py"] and found["Other"] == ["a.py"]
    assert "Plain" not in found


def test_every_daemon_error_derives_from_daemon_error() -> None:
    outside = []
    for info in pkgutil.walk_packages(daemon.__path__, "daemon."):
        module = importlib.import_module(info.name)
        for obj in vars(module).values():
            if (isinstance(obj, type) and issubclass(obj, BaseException)
                    and obj.__module__ == module.__name__ and not issubclass(obj, DaemonError)):
                outside.append(f"{module.__name__}.{obj.__name__}")
    assert outside == []
