"""The configuration schema (planner/schema): every field of every file's table refuses any value
outside its range or of the wrong type, naming the key and what is allowed, and returns any value
inside it as it was written; in a whole shipped file, a bad value anywhere is refused by the file's
loader naming its key path."""

from __future__ import annotations

import copy
import math
import tempfile
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest
import yaml
from hypothesis import given
from hypothesis import strategies as st

from daemon.rig.hardware_config import HARDWARE, HardwareConfigError, hardware_from_mapping
from drivers.phone.errors import FocusCalibrationError
from drivers.phone.focus import load_focus_calibration
from planner.calibration.model import CalibrationFileError, load_calibration
from planner.calibration.target import DEFAULT_TARGET_PATH, TargetError, load_target
from planner.rig import CALIBRATION_DIR, DEFAULT_RIG_PATH, RigConfigError, load_rig, rig_from_mapping
from planner.schema import nodes as schema
from planner.schema.tables import CALIBRATION_FILE, FOCUS_FILE, RIG_FILE, TARGET_FILE
from tests.fuzz import FUZZ

RIG = load_rig()
LEAVES = (schema.Number, schema.Text, schema.Flag, schema.Choice, schema.Serial, schema.Note, schema.Kinds)


def table_leaves(node: schema.Node, key: str, nullable: bool = False) -> Iterator[tuple[str, schema.Node, bool]]:
    """(key path, leaf node, null allowed) of every value a table reads ("[]" for any entry)."""
    if isinstance(node, schema.Nullable):
        yield from table_leaves(node.inner, key, True)
    elif isinstance(node, schema.Section):
        for name, field in node.fields.items():
            yield from table_leaves(field, schema.child(key, name))
    elif isinstance(node, schema.ListOf):
        yield from table_leaves(node.item, f"{key}[0]")
    elif isinstance(node, schema.Tuple):
        for i, item in enumerate(node.items):
            yield from table_leaves(item, f"{key}[{i}]")
    elif isinstance(node, schema.MapOf):
        yield from table_leaves(node.values, schema.child(key, "k"))
    elif isinstance(node, schema.Kinds):
        yield key, node, nullable
        for name, kind in node.kinds.items():
            yield from table_leaves(kind.value, f"{key}.{name}")
    else:
        assert isinstance(node, LEAVES), node
        yield key, node, nullable


TABLES = [RIG_FILE.table, HARDWARE.table, CALIBRATION_FILE.table, TARGET_FILE.table, FOCUS_FILE.table]
ALL_LEAVES = [leaf for table in TABLES for leaf in table_leaves(table, "")]

wrong_types = st.one_of(st.none(), st.booleans(), st.integers(-(10**30), 10**30), st.floats(allow_nan=True),
                        st.text(max_size=20), st.lists(st.integers(), max_size=3),
                        st.dictionaries(st.text(max_size=4), st.integers(), max_size=2), st.dates())


def invalid(node: schema.Node) -> st.SearchStrategy[Any]:
    """Values ``node`` must refuse: outside its range, of another type, or not of its form."""
    if isinstance(node, schema.Number):
        outside = [st.sampled_from([math.nan, math.inf, -math.inf])]
        if node.low is not None:
            outside += [st.floats(max_value=node.low, exclude_max=True, allow_infinity=False, allow_nan=False),
                        st.integers(max_value=math.ceil(node.low) - 1, min_value=-(10**400))]
        if node.high is not None:
            outside += [st.floats(min_value=node.high, exclude_min=True, allow_infinity=False, allow_nan=False),
                        st.integers(min_value=math.floor(node.high) + 1, max_value=10**400)]
        if isinstance(node, schema.Integer):
            outside.append(st.floats(node.low, node.high).filter(lambda x: not x.is_integer()))
        return st.one_of(*outside, wrong_types.filter(lambda v: isinstance(v, bool) or not isinstance(v, (int, float))))
    if isinstance(node, schema.Text):
        bad = [wrong_types.filter(lambda v: not isinstance(v, str)), st.text(min_size=node.max_len + 1,
                                                                             max_size=node.max_len + 50)]
        if node.min_len:
            bad.append(st.just(""))
        if node.pattern is not None:
            pattern = node.pattern
            bad.append(st.text(max_size=40).filter(lambda v: not pattern.fullmatch(v)))
        return st.one_of(*bad)
    if isinstance(node, schema.Flag):
        return st.one_of(wrong_types.filter(lambda v: not isinstance(v, bool)), st.sampled_from(["true", "yes", 0, 1]))
    if isinstance(node, schema.Choice):
        return st.one_of(wrong_types, st.text(max_size=12)).filter(lambda v: v not in node.options)
    if isinstance(node, schema.Serial):
        return st.one_of(st.integers(max_value=-1), st.integers(min_value=2**64, max_value=10**400), st.booleans(),
                         st.floats(), st.none(), st.lists(st.text(), max_size=2), st.text(min_size=257, max_size=300))
    if isinstance(node, schema.Note):
        return st.one_of(st.lists(st.integers(), max_size=3), st.dictionaries(st.text(max_size=3), st.integers()))
    assert isinstance(node, schema.Kinds)
    bare = [name for name, kind in node.kinds.items() if kind.bare]
    return st.one_of(wrong_types.filter(lambda v: v not in bare and not (isinstance(v, dict) and len(v) == 1)),
                     st.dictionaries(st.sampled_from(sorted(node.kinds)), st.none(), min_size=2),
                     st.dictionaries(st.text(max_size=8).filter(lambda k: k not in node.kinds), st.none(),
                                     min_size=1, max_size=1))


def valid(node: schema.Node) -> st.SearchStrategy[Any]:
    """Values ``node`` must accept and return as written."""
    if isinstance(node, schema.Integer):
        return st.integers(node.low, node.high)  # type: ignore[arg-type]
    if isinstance(node, schema.Number):
        return st.floats(node.low, node.high, allow_nan=False, allow_infinity=False)
    if isinstance(node, schema.Text):
        if node.pattern is not None:
            return st.from_regex(node.pattern, fullmatch=True).filter(lambda v: len(v) <= node.max_len)
        return st.text(min_size=node.min_len, max_size=node.max_len)
    if isinstance(node, schema.Flag):
        return st.booleans()
    if isinstance(node, schema.Choice):
        return st.sampled_from(node.options)
    if isinstance(node, schema.Serial):
        return st.one_of(st.text(max_size=256), st.integers(0, 2**64 - 1))
    if isinstance(node, schema.Note):
        return st.one_of(st.text(), st.integers(), st.floats(allow_nan=False), st.booleans(), st.none(), st.dates())
    assert isinstance(node, schema.Kinds)
    return st.sampled_from([name for name, kind in node.kinds.items() if kind.bare] or [None]).filter(bool)


def _read(node: schema.Node, value: Any, key: str) -> Any:
    return node.read(value, key, schema.Reader("t.yaml", schema.ConfigError))


@FUZZ
@given(st.sampled_from(ALL_LEAVES).flatmap(lambda leaf: st.tuples(st.just(leaf), invalid(leaf[1]))))
def test_a_value_outside_a_field_or_of_another_type_is_refused_naming_key_and_form(case: tuple) -> None:
    (key, node, nullable), value = case
    if nullable and value is None:
        return
    with pytest.raises(schema.ConfigError) as info:
        _read(node, value, key)
    assert info.value.key == key, (info.value, value)
    assert info.value.path == "t.yaml" and node.form() in info.value.problem
    assert len(str(info.value)) < 400


@FUZZ
@given(st.sampled_from([leaf for leaf in ALL_LEAVES if not isinstance(leaf[1], schema.Kinds)]).flatmap(
    lambda leaf: st.tuples(st.just(leaf), valid(leaf[1]))))
def test_a_value_inside_a_field_is_read_as_written(case: tuple) -> None:
    (key, node, _), value = case
    got = _read(node, value, key)
    assert got == (str(value) if isinstance(node, schema.Serial) else value)
    assert type(got) is {schema.Integer: int, schema.Number: float}.get(type(node), type(got))


def test_a_kind_reads_as_its_name_and_value() -> None:
    kinds = [(key, node) for key, node, _ in ALL_LEAVES if isinstance(node, schema.Kinds)]
    assert [key for key, _ in kinds] == ["phones.k", "depth_cameras.k"]
    for key, node in kinds:
        for name, kind in node.kinds.items():
            if kind.bare:
                assert _read(node, name, key) == (name, None)
            else:
                with pytest.raises(schema.ConfigError, match=f"{key}: got '{name}'; expected"):
                    _read(node, name, key)
    assert _read(kinds[0][1], {"tcp": "[::1]:5555"}, "p") == ("tcp", "[::1]:5555")
    assert _read(kinds[1][1], {"realsense": 12}, "d") == ("realsense", "12")


# ---------------------------------------------------------------------------- whole files


def doc_leaves(node: schema.Node, raw: Any, path: tuple, key: str) -> Iterator[tuple[tuple, str, schema.Node, bool]]:
    """(path in the document, key path, leaf node, null allowed) of every value of a parsed file,
    and of every optional field it leaves out."""
    nullable = isinstance(node, schema.Nullable)
    inner = node.inner if isinstance(node, schema.Nullable) else node
    if isinstance(inner, schema.Section) and (isinstance(raw, dict) or raw is None and inner.optional):
        for name, field in inner.fields.items():
            yield from doc_leaves(field, (raw or {}).get(name), (*path, name), schema.child(key, name))
    elif isinstance(inner, schema.ListOf | schema.Tuple) and isinstance(raw, list):
        for i, item in enumerate(raw):
            yield from doc_leaves(inner.item if isinstance(inner, schema.ListOf) else inner.items[i], item, (*path, i),
                                  f"{key}[{i}]")
    elif isinstance(inner, schema.MapOf) and isinstance(raw, dict):
        for name, item in raw.items():
            yield from doc_leaves(inner.values, item, (*path, name), schema.child(key, name))
    elif isinstance(inner, LEAVES):
        yield path, key, inner, nullable


def _with(raw: Any, path: tuple, value: Any) -> Any:
    raw = copy.deepcopy(raw)
    node = raw
    for step in path[:-1]:
        if isinstance(node, dict) and not isinstance(node.get(step), dict | list):
            node[step] = {}
        node = node[step]
    node[path[-1]] = value
    return raw


def _from_file(load: Callable[[Path], Any]) -> Callable[[Any], Any]:
    def read(raw: Any) -> Any:
        with tempfile.TemporaryDirectory() as folder:
            path = Path(folder) / "file.yaml"
            path.write_text(yaml.safe_dump(raw))
            return load(path)
    return read


def _calibration() -> dict:
    from sim.calibration import true_rig

    with tempfile.TemporaryDirectory() as folder:
        true_rig(RIG, load_target(), seed=3).save(Path(folder) / "c.yaml")
        return yaml.safe_load((Path(folder) / "c.yaml").read_text())


SHIPPED = {
    "rig": (yaml.safe_load(DEFAULT_RIG_PATH.read_text()), RIG_FILE.table, RigConfigError,
            lambda raw: rig_from_mapping(raw, "rig.yaml")),
    "hardware": (yaml.safe_load((CALIBRATION_DIR / "hardware.example.yaml").read_text()), HARDWARE.table,
                 HardwareConfigError, lambda raw: hardware_from_mapping(raw, RIG, "hardware.yaml")),
    "calibration": (_calibration(), CALIBRATION_FILE.table, CalibrationFileError, _from_file(load_calibration)),
    "target": (yaml.safe_load(DEFAULT_TARGET_PATH.read_text()), TARGET_FILE.table, TargetError,
               _from_file(load_target)),
    "focus": (yaml.safe_load((CALIBRATION_DIR / "focus" / "default.yaml").read_text()), FOCUS_FILE.table,
              FocusCalibrationError, _from_file(load_focus_calibration)),
}
PLACES = {name: [(name, *leaf) for leaf in doc_leaves(table, raw, (), "")]
          for name, (raw, table, _, _) in SHIPPED.items()}


@pytest.mark.slow  # a bad value at every key of every shipped file
@FUZZ
@given(st.sampled_from(sorted(PLACES)).flatmap(lambda name: st.sampled_from(PLACES[name])).flatmap(
    lambda place: st.tuples(st.just(place), invalid(place[3]))))
def test_a_bad_value_anywhere_in_a_shipped_file_is_refused_naming_its_key(case: tuple) -> None:
    (name, path, key, node, nullable), value = case
    if nullable and value is None:
        return
    raw, _, error, load = SHIPPED[name]
    with pytest.raises(error) as info:
        load(_with(raw, path, value))
    assert info.value.key == key and node.form() in info.value.problem, (info.value, value)


@pytest.mark.parametrize("name", sorted(SHIPPED))
def test_every_shipped_file_reads_as_parsed(name: str) -> None:
    raw, _, _, load = SHIPPED[name]
    assert load(raw) is not None
    assert len(PLACES[name]) >= 5
