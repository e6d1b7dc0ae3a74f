"""Fuzzing the rig file with hypothesis: any value at any key, any text, any missing key gives a Rig
or a RigConfigError naming the key in a short message, never another exception."""

from __future__ import annotations

import copy
from pathlib import Path
from typing import Any

import yaml
from hypothesis import given
from hypothesis import strategies as st

from planner.rig import DEFAULT_RIG_PATH, Rig, RigConfigError, load_rig, rig_from_mapping
from tests.fuzz import FUZZ

DEFAULT = yaml.safe_load(DEFAULT_RIG_PATH.read_text())
MAX_MESSAGE = 600


def _paths(node: Any, prefix: tuple = ()) -> list[tuple]:
    """Every key path of the parsed rig file, leaves and containers."""
    out = [prefix] if prefix else []
    children = node.items() if isinstance(node, dict) else enumerate(node) if isinstance(node, list) else ()
    for key, child in children:
        out += _paths(child, (*prefix, key))
    return out


PATHS = _paths(DEFAULT)

hostile_values = st.one_of(
    st.none(), st.booleans(), st.integers(min_value=-(10**500), max_value=10**500),
    st.floats(allow_nan=True, allow_infinity=True), st.text(max_size=400), st.binary(max_size=20),
    st.lists(st.integers(), max_size=4), st.dictionaries(st.text(max_size=6), st.integers(), max_size=3),
    st.sampled_from(["../../etc", "..", "cam0", "", "x" * 300, 0, -1, 1e300, 10**19, 2**63]),
)


def _check(make: Any) -> Rig | None:
    try:
        return make()
    except RigConfigError as exc:
        assert len(str(exc)) < MAX_MESSAGE, str(exc)[:2000]
        return None


def _replace(raw: dict, path: tuple, value: Any) -> dict:
    raw = copy.deepcopy(raw)
    node = raw
    for key in path[:-1]:
        node = node[key]
    node[path[-1]] = value
    return raw


@FUZZ
@given(st.sampled_from(PATHS), hostile_values)
def test_any_value_at_any_key(path: tuple, value: Any) -> None:
    rig = _check(lambda: rig_from_mapping(_replace(DEFAULT, path, value), "fuzz.yaml"))
    if rig is not None:
        assert all(phone.id.isascii() and "/" not in phone.id and not phone.id.startswith(".") for phone in rig.phones)


@FUZZ
@given(st.sampled_from(PATHS))
def test_any_missing_key(path: tuple) -> None:
    raw = copy.deepcopy(DEFAULT)
    node = raw
    for key in path[:-1]:
        node = node[key]
    del node[path[-1]]
    _check(lambda: rig_from_mapping(raw, "fuzz.yaml"))


@FUZZ
@given(st.text(max_size=400) | st.binary(max_size=400).map(lambda b: b.decode("latin-1")))
def test_any_text(text: str) -> None:
    import tempfile

    with tempfile.TemporaryDirectory() as folder:
        path = Path(folder) / "rig.yaml"
        path.write_text(text, errors="surrogateescape")
        _check(lambda: load_rig(path))


@FUZZ
@given(st.integers(0, len(DEFAULT_RIG_PATH.read_bytes()) - 1), st.binary(min_size=1, max_size=8))
def test_the_default_file_with_bytes_overwritten(at: int, junk: bytes) -> None:
    import tempfile

    data = bytearray(DEFAULT_RIG_PATH.read_bytes())
    data[at:at + len(junk)] = junk
    with tempfile.TemporaryDirectory() as folder:
        path = Path(folder) / "rig.yaml"
        path.write_bytes(bytes(data))
        _check(lambda: load_rig(path))
