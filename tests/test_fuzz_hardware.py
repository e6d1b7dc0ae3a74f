"""Fuzzing the hardware file with hypothesis: aliases of any shape (lists, mappings, merges, cycles)
at any key, and any value at any key, give a HardwareConfig or a short HardwareConfigError; a file
is refused for its aliases exactly when, expanded, it stands for more nodes than the bound the
loader enforces (counted here independently on PyYAML's composed graph). The properties run in a
child whose address space may grow by at most 200 MiB, so a regression that expands a bomb fails
with MemoryError instead of taking the machine's memory."""

from __future__ import annotations

import tempfile
from pathlib import Path
from typing import Any

import pytest
import yaml
from hypothesis import given
from hypothesis import strategies as st

from daemon.rig.hardware_config import MAX_FILE_BYTES, HardwareConfigError, load_hardware
from planner.rig import load_rig
from tests.fuzz import FUZZ
from tests.memory import run_bounded

RIG = load_rig()
MAX_MESSAGE = 600
VALID = {"can": {"interface": "socketcand", "channel": "can0", "host": "127.0.0.1", "port": 29536},
         "phones": {p.id: "usb" for p in RIG.phones},
         "depth_cameras": {c.id: "realsense" for c in RIG.depth_cameras},
         "panel": {"device": "/dev/ttyACM1", "baud": 115200},
         "capture_agent": "agent.jar",
         "timeouts": {"open_s": 5.0}}
LEAVES = ["lol", "1", "-7", "0x" + "f" * 40, "1e400", "true", "null", "''", "usb", "realsense", "can0",
          "{}", "[]", "'192.168.1.1:5555'", "000000000001"]


def _paths(node: Any, prefix: tuple[str, ...] = ()) -> list[tuple[str, ...]]:
    out = [prefix] if prefix else []
    if isinstance(node, dict):
        for key, child in node.items():
            out += _paths(child, (*prefix, key))
    return out


PATHS = _paths(VALID) + [("x-extra",), ("phones", "cam0", "usb"), ("depth_cameras", "depth1", "realsense"),
                         ("phones", "cam1", "tcp")]


def _document(path: tuple[str, ...], value: str, before: str = "") -> str:
    """The valid file with ``value`` (YAML text) at ``path``; ``before``: lines put first."""
    raw: dict[str, Any] = yaml.safe_load(yaml.safe_dump(VALID))
    node = raw
    for key in path[:-1]:
        if not isinstance(node.get(key), dict):
            node[key] = {}
        node = node[key]
    node[path[-1]] = "VALUE_HERE"
    return before + yaml.safe_dump(raw, width=10_000).replace("VALUE_HERE", value)


@st.composite
def aliased_documents(draw: st.DrawFn) -> str:
    levels = draw(st.integers(1, 14))
    width = draw(st.integers(1, 10))
    forms = draw(st.lists(st.sampled_from(["list", "map", "merge"]), min_size=levels, max_size=levels))
    child = draw(st.sampled_from(LEAVES))
    anchors = []
    for i, form in enumerate(forms):
        if form == "list":
            body = f"[{', '.join([child] * width)}]"
        elif form == "map":
            body = "{" + ", ".join(f"k{j}: {child}" for j in range(width)) + "}"
        else:
            body = "{<<: [" + ", ".join([child] * width) + f"], k: {i}}}"
        anchors.append(f"&l{i} {body}")
        child = f"*l{i}"
    if draw(st.booleans()):  # a cycle: loaded, a list that holds itself
        anchors.append(f"&l{levels} [*l{levels}, {child}]")
        child = f"*l{levels}"
    path = draw(st.sampled_from(PATHS))
    placement = draw(st.sampled_from(["inline", "apart", "key"]))
    if placement == "inline":
        return _document(path, f"[{', '.join(anchors)}]")
    before = f"x-anchors: [{', '.join(anchors)}]\n"
    if placement == "apart":
        return _document(path, child, before)
    return before + yaml.safe_dump(VALID) + f"? {child}\n: 1\n"


hostile_values = st.one_of(
    st.none(), st.booleans(), st.integers(min_value=-(10**500), max_value=10**500),
    st.floats(allow_nan=True, allow_infinity=True), st.text(max_size=400),
    st.lists(st.integers(), max_size=4), st.dictionaries(st.text(max_size=6), st.integers(), max_size=3),
    st.sampled_from(["usb", "realsense", "socketcan", "slcan", "host:1", "[::1]:5555", "x" * 300, 0, -1, 2**64]),
).map(lambda value: yaml.safe_dump(value, default_flow_style=True, width=10_000).strip().removesuffix("\n..."))


def expanded_nodes(text: str) -> int | None:
    """Nodes the document stands for, each alias counted as its anchor's nodes (a cycle once);
    None when PyYAML cannot compose it."""
    try:
        root = yaml.compose(text, Loader=yaml.SafeLoader)
    except (yaml.YAMLError, ValueError, RecursionError):
        return None
    counted: dict[int, int] = {}
    composing: set[int] = set()

    def count(node: yaml.Node) -> int:
        if id(node) in counted:
            return counted[id(node)]
        if id(node) in composing:
            return 1
        composing.add(id(node))
        if isinstance(node, yaml.SequenceNode):
            total = 1 + sum(count(child) for child in node.value)
        elif isinstance(node, yaml.MappingNode):
            total = 1 + sum(count(key) + count(value) for key, value in node.value)
        else:
            total = 1
        composing.discard(id(node))
        counted[id(node)] = total
        return total

    return 0 if root is None else count(root)


def _load(text: str) -> HardwareConfigError | None:
    with tempfile.TemporaryDirectory() as folder:
        path = Path(folder) / "hardware.yaml"
        path.write_text(text)
        try:
            load_hardware(path, RIG)
        except HardwareConfigError as exc:
            assert len(str(exc)) < MAX_MESSAGE + len(str(path)), str(exc)[:2000]
            return exc
    return None


@FUZZ
@given(aliased_documents())
def check_aliases_anywhere(text: str) -> None:
    nodes = expanded_nodes(text)
    refused = _load(text)
    for_aliases = refused is not None and refused.problem.startswith("aliases make it")
    if nodes is None:
        assert refused is not None
    else:
        assert for_aliases == (nodes > MAX_FILE_BYTES), (nodes, refused)


@FUZZ
@given(st.sampled_from(PATHS), hostile_values)
def check_any_value_at_any_key(path: tuple[str, ...], value: str) -> None:
    _load(_document(path, value))


@pytest.mark.slow  # a worker process
def test_the_hardware_file_properties_run_in_bounded_memory() -> None:
    # Hypothesis builds its table of the characters a text may hold the first time a text strategy
    # is validated (and keeps it in .hypothesis/): built in the set-up, outside the bound, or a
    # clean checkout's first run spends the bound on it.
    child = run_bounded("from tests.test_fuzz_hardware import check_aliases_anywhere, check_any_value_at_any_key, "
                        "hostile_values\nhostile_values.validate()",
                        "check_aliases_anywhere()\ncheck_any_value_at_any_key()", timeout_s=600.0)
    assert child.returncode == 0, child.stderr[-4000:]
