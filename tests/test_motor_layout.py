"""Architecture rules for the motor area, checked on the source: runtime driver code never imports
the simulators or the daemon, and no asyncio code in the area reads the wall clock or sleeps
outside the event loop (virtual time must be able to drive all of it)."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
RUNTIME = sorted((ROOT / "drivers" / "motor").glob("*.py"))
SIMULATED = [
    ROOT / "drivers" / "sim" / name
    for name in ("drive.py", "canopen_node.py", "socketcand.py", "trapezoid.py")
]


def _imports(path: Path) -> list[str]:
    names = []
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            names += [alias.name for alias in node.names]
        elif isinstance(node, ast.ImportFrom) and node.module:
            names.append(node.module)
    return names


def _clock_calls(path: Path) -> list[str]:
    found = []
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Attribute) and isinstance(node.value, ast.Name) and node.value.id == "time":
            if node.attr in ("time", "monotonic", "sleep", "perf_counter"):
                found.append(f"time.{node.attr} at line {node.lineno}")
    return found


@pytest.mark.parametrize("path", RUNTIME, ids=lambda p: p.name)
def test_runtime_motor_code_never_imports_simulators_or_daemon(path: Path) -> None:
    bad = [name for name in _imports(path) if name.startswith(("drivers.sim", "daemon"))]
    assert not bad, f"{path.name} imports {bad}"


@pytest.mark.parametrize("path", RUNTIME + SIMULATED, ids=lambda p: p.name)
def test_motor_code_keeps_time_on_the_event_loop(path: Path) -> None:
    assert not _clock_calls(path), f"{path.name}: {_clock_calls(path)}"


def test_the_rules_can_see_a_violation(tmp_path: Path) -> None:
    sample = tmp_path / "bad.py"
    sample.write_text("import time\nfrom drivers.sim.drive import SimulatedDrive\ntime.sleep(1)\n")
    assert _imports(sample) == ["time", "drivers.sim.drive"]
    assert _clock_calls(sample) == ["time.sleep at line 3"]
