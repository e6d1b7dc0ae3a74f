"""The layout is the architecture: imports only go downward, and only the clock owners read
the wall clock.

Layers, lowest first (a package may import itself and what its row allows, nothing else):

- ``planner``: pure computation (rig file, poses, optics, visibility, focus, TSDF, capture
  schedule);
- ``drivers``: real devices, on top of ``planner``'s rig description;
- ``drivers.sim``: device twins, impersonating ``drivers``' devices at their protocols;
- ``daemon``: the scan runtime, on ``drivers`` and ``planner``, never a simulator;
- ``sim``: the simulated world (virtual clock, bodies, the simulated rig, device processes);
- ``analysis``: evaluation, QA report, navigation, on scan folders and the simulated world;
- ``archive``: the scan folder as a DICOM study, its export (C-STORE, STOW-RS) and the export queue,
  on ``analysis`` (marks, navigation) and the daemon's store and clinic modules;
- ``web``: the browser's viewer and console (aiohttp), on ``analysis`` and the daemon's handler;
- ``cli``: the ``tbp`` command, on everything.

Every ``import`` counts, also those inside functions (they are imports all the same).
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent

ALLOWED: dict[str, frozenset[str]] = {
    "planner": frozenset({"planner"}),
    "drivers": frozenset({"drivers", "planner"}),
    "drivers.sim": frozenset({"drivers.sim", "drivers", "planner"}),
    "daemon": frozenset({"daemon", "drivers", "planner"}),
    "sim": frozenset({"sim", "daemon", "drivers.sim", "drivers", "planner"}),
    "analysis": frozenset({"analysis", "sim", "daemon", "drivers.sim", "drivers", "planner"}),
    "archive": frozenset({"archive", "analysis", "daemon", "drivers", "planner"}),
    "web": frozenset({"web", "archive", "analysis", "daemon", "drivers", "planner"}),
    "cli": frozenset({"cli", "web", "archive", "analysis", "sim", "daemon", "drivers.sim", "drivers", "planner"}),
}
"""Importer layer -> the layers it may import."""

WALL_CLOCK = {
    ("time", "time"), ("time", "time_ns"), ("time", "monotonic"), ("time", "monotonic_ns"),
    ("time", "sleep"), ("datetime", "now"), ("datetime", "utcnow"), ("date", "today"),
}
"""Calls that read (or wait on) the machine's clock. ``time.perf_counter`` is allowed: it
times compute for reports and never decides when anything happens."""

CLOCK_OWNERS = {
    "sim/clock.py",  # the virtual-time loop paces itself against the real clock
    "sim/loopback.py",  # the loopback rig waits for real processes in real time
    "daemon/utc.py",  # calendar time for the records a scan folder keeps
    "drivers/motor/guard.py",  # the drive guard keeps real time apart from the event loop's
    "drivers/motor/port.py",  # stamps received frames for a guard thread that runs beside the loop
    "drivers/sim/canopen_node.py",  # stamps the simulator's logs so another process can time its reactions
    "sim/processes/keys.py",  # stamps the faults a harness injects, to time the daemon's reactions
}


def layer_of(module: str) -> str | None:
    """The layer of a dotted module name (``drivers.sim`` before ``drivers``), None if not ours."""
    for layer in sorted(ALLOWED, key=len, reverse=True):
        if module == layer or module.startswith(layer + "."):
            return layer
    return None


def module_name(path: Path) -> str:
    parts = list(path.relative_to(ROOT).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


def source_files() -> list[Path]:
    return sorted(p for layer in ("planner", "drivers", "daemon", "sim", "analysis", "archive", "web", "cli")
                  for p in (ROOT / layer).rglob("*.py"))


def imported_modules(tree: ast.AST, package: str) -> list[tuple[int, str]]:
    """(line, absolute module) of every import in a module of ``package``."""
    found = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            found += [(node.lineno, alias.name) for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")[: len(package.split(".")) - node.level + 1]
                module = ".".join(base + ([node.module] if node.module else []))
            else:
                module = node.module or ""
            found.append((node.lineno, module))
            # ``from drivers import sim`` imports the subpackage drivers.sim
            found += [(node.lineno, f"{module}.{alias.name}") for alias in node.names
                      if layer_of(f"{module}.{alias.name}") != layer_of(module)]
    return found


def violations(path: Path) -> list[str]:
    name = module_name(path)
    importer = layer_of(name)
    assert importer is not None, name
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    tree = ast.parse(path.read_text(), str(path))
    bad = []
    for line, module in imported_modules(tree, package):
        target = layer_of(module)
        if target is not None and target not in ALLOWED[importer]:
            bad.append(f"{path.relative_to(ROOT)}:{line}: {importer} must not import {module} ({target})")
    return bad


def wall_clock_calls(path: Path) -> list[str]:
    if str(path.relative_to(ROOT)) in CLOCK_OWNERS:
        return []
    return clock_reads(path.read_text(), str(path.relative_to(ROOT)))


def clock_reads(source: str, label: str) -> list[str]:
    """``label:line: call`` for every wall-clock read in ``source``."""
    bad = []
    for node in ast.walk(ast.parse(source, label)):
        if isinstance(node, ast.Attribute) and isinstance(node.value, ast.Name):
            if (node.value.id, node.attr) in WALL_CLOCK:
                bad.append(f"{label}:{node.lineno}: {node.value.id}.{node.attr}")
        elif isinstance(node, ast.ImportFrom) and node.module in ("time", "datetime"):
            names = {alias.name for alias in node.names}
            if node.module == "time" and names & {n for m, n in WALL_CLOCK if m == "time"}:
                bad.append(f"{label}:{node.lineno}: from time import {sorted(names)}")
    return bad


def test_every_import_points_down_the_layers() -> None:
    bad = [v for path in source_files() for v in violations(path)]
    assert bad == [], "\n".join(bad)


def test_only_the_clock_owners_read_the_wall_clock() -> None:
    bad = [v for path in source_files() for v in wall_clock_calls(path)]
    assert bad == [], "\n".join(bad)


@pytest.mark.parametrize("importer, module, allowed", [
    ("daemon/jobs/scan.py", "sim.body", False),
    ("daemon/jobs/scan.py", "drivers.sim.phone", False),
    ("daemon/jobs/scan.py", "drivers.motor.drive", True),
    ("planner/plan.py", "daemon.records.store", False),
    ("drivers/adb/usb.py", "drivers.sim.adbd", False),
    ("drivers/sim/phone.py", "sim.body", False),
    ("sim/rig.py", "drivers.sim.drive", True),
    ("analysis/navigate.py", "cli", False),
    ("cli/scan.py", "analysis.qa_report", True),
    ("daemon/server/service.py", "web.app", False),
    ("web/rig.py", "sim.run", False),
    ("web/scans.py", "analysis.navigate", True),
    ("archive/instances.py", "analysis.marks", True),
    ("archive/instances.py", "web.app", False),
    ("daemon/server/service.py", "archive.queue", False),
])
def test_the_rule_itself(importer: str, module: str, allowed: bool) -> None:
    """The checker catches a forbidden arrow (so an empty violation list means something)."""
    package = module_name(ROOT / importer).rpartition(".")[0]
    tree = ast.parse(f"def f():\n    import {module}\n")
    importer_layer = layer_of(package)
    assert importer_layer is not None
    targets = [layer_of(m) for _, m in imported_modules(tree, package)]
    assert all((t in ALLOWED[importer_layer]) == allowed for t in targets if t is not None)


@pytest.mark.parametrize("source, found", [
    ("import time\nasync def f():\n    time.sleep(1)\n", ["x.py:3: time.sleep"]),
    ("from time import monotonic\n", ["x.py:1: from time import ['monotonic']"]),
    ("from datetime import datetime\nstamp = datetime.now()\n", ["x.py:2: datetime.now"]),
    ("import time\nt0 = time.perf_counter()\n", []),
    ("loop.time()\n", []),
])
def test_the_clock_rule_itself(source: str, found: list[str]) -> None:
    """The checker finds a wall-clock read (so an empty list from the tree means something)."""
    assert clock_reads(source, "x.py") == found


def _type_checking(node: ast.AST) -> bool:
    """An ``if TYPE_CHECKING:`` block (its imports never run)."""
    return isinstance(node, ast.If) and ast.unparse(node.test) in ("TYPE_CHECKING", "typing.TYPE_CHECKING")


def runtime_imports(tree: ast.Module) -> ast.Module:
    """The module's import statements that run, at module level or inside functions and classes,
    leaving out ``if TYPE_CHECKING:`` blocks."""
    found: list[ast.stmt] = []

    def visit(node: ast.AST) -> None:
        if isinstance(node, (ast.Import, ast.ImportFrom)):
            found.append(node)
        elif not _type_checking(node):
            for child in ast.iter_child_nodes(node):
                visit(child)

    visit(tree)
    return ast.Module(body=found, type_ignores=[])


def import_graph(sources: dict[str, tuple[str, bool]]) -> dict[str, set[str]]:
    """Module -> the modules of ours it imports when it runs (``sources``: module -> (its text,
    whether it is a package's ``__init__``))."""
    graph: dict[str, set[str]] = {}
    for name, (text, is_package) in sources.items():
        package = name if is_package else name.rpartition(".")[0]
        imports = runtime_imports(ast.parse(text, name))
        graph[name] = {m for _, m in imported_modules(imports, package) if layer_of(m) is not None}
    known = set(graph)
    for name in graph:
        # ``from pkg import sub`` depends on pkg.sub; a module's own parent packages are already
        # importing when it runs (re-exports in an ``__init__`` are not a cycle).
        targets = {m if m in known else m.rpartition(".")[0] for m in graph[name]} & known
        graph[name] = {t for t in targets if t != name and not name.startswith(t + ".")}
    return graph


def find_cycle(graph: dict[str, set[str]]) -> list[str]:
    """One import cycle (``a -> b -> a``), or [] when there is none."""
    state: dict[str, int] = {}
    cycle: list[str] = []

    def visit(node: str, stack: list[str]) -> bool:
        state[node] = 1
        for nxt in sorted(graph[node]):
            if state.get(nxt) == 1:
                cycle.extend(stack[stack.index(nxt):] + [node, nxt] if nxt in stack else [node, nxt])
                return True
            if nxt not in state and visit(nxt, stack + [node]):
                return True
        state[node] = 2
        return False

    for name in sorted(graph):
        if name not in state and visit(name, []):
            break
    return cycle


def test_no_import_cycles_between_modules() -> None:
    """No two modules import each other, directly or around a loop, counting the imports inside
    functions: a cycle hidden in a function is still two modules that cannot be read, tested or
    moved apart."""
    sources = {module_name(p): (p.read_text(), p.name == "__init__.py") for p in source_files()}
    cycle = find_cycle(import_graph(sources))
    assert not cycle, " -> ".join(cycle)


@pytest.mark.parametrize("a, b, cycle", [
    ("from daemon.b import f\n", "def g():\n    from daemon.a import h\n", ["daemon.a", "daemon.b", "daemon.a"]),
    ("import daemon.b\n", "class C:\n    def m(self):\n        import daemon.a\n",
     ["daemon.a", "daemon.b", "daemon.a"]),
    ("from daemon.b import f\n", "from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n    from daemon.a import T\n", []),
    ("from daemon.b import f\n", "import daemon.c\n", []),
])
def test_the_cycle_rule_itself(a: str, b: str, cycle: list[str]) -> None:
    """The checker finds a cycle closed by an import inside a function (so an empty list from the
    tree means something), and leaves out imports for type checking only."""
    graph = import_graph({"daemon.a": (a, False), "daemon.b": (b, False), "daemon.c": ("", False)})
    assert find_cycle(graph) == cycle


def test_no_import_cycles_between_the_daemons_packages() -> None:
    """The daemon's sub-packages import each other one way (server -> jobs -> rig, records, offload,
    clinic -> the modules at the daemon's top), and the top modules import none of them: each
    package is read and tested on what lies below it."""
    paths = list((ROOT / "daemon").rglob("*.py"))
    package = {module_name(p): "daemon." + p.relative_to(ROOT / "daemon").parts[0]
               if p.parent != ROOT / "daemon" else "daemon" for p in paths}
    sources = {module_name(p): (p.read_text(), p.name == "__init__.py") for p in paths}
    graph: dict[str, set[str]] = {name: set() for name in package.values()}
    for name, imports in import_graph(sources).items():
        graph[package[name]] |= {package[m] for m in imports if m in package} - {package[name]}
    cycle = find_cycle(graph)
    assert not cycle, " -> ".join(cycle)
