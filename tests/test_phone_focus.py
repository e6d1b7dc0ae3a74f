"""Focus calibration tables: validation, interpolation, inversion and the shipped default table."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from drivers.phone.errors import FocusCalibrationError, FocusOutOfRange
from drivers.phone.focus import FocusCalibration, load_focus_calibration
from planner.rig import load_rig


@st.composite
def tables(draw: st.DrawFn) -> FocusCalibration:
    n = draw(st.integers(2, 12))
    steps = draw(st.lists(st.floats(0.05, 3.0), min_size=n, max_size=n))
    diopters = np.cumsum(steps)
    scale = draw(st.lists(st.floats(0.8, 1.2), min_size=n, max_size=n))
    measured = np.cumsum(np.array(scale) * steps) + 0.05  # strictly increasing measured diopters
    return FocusCalibration(diopters, 1000.0 / measured)


@settings(deadline=None)
@given(tables(), st.floats(0.0, 1.0))
def test_inverse_round_trips(table: FocusCalibration, fraction: float) -> None:
    mm = table.near_mm + fraction * (table.far_mm - table.near_mm)
    d = table.diopters_for(mm)
    assert table.diopters[0] - 1e-9 <= d <= table.diopters[-1] + 1e-9
    assert table.focus_mm(d) == pytest.approx(mm, rel=1e-9)


@settings(deadline=None)
@given(tables(), st.floats(0.0, 1.0), st.floats(0.0, 1.0))
def test_nearer_focus_needs_more_diopters(table: FocusCalibration, a: float, b: float) -> None:
    lo, hi = sorted((a, b))
    span = table.far_mm - table.near_mm
    near, far = table.near_mm + lo * span, table.near_mm + hi * span
    assert table.diopters_for(near) >= table.diopters_for(far) - 1e-12


@settings(deadline=None)
@given(tables())
def test_table_points_are_exact(table: FocusCalibration) -> None:
    for d, mm in zip(table.diopters, table.distance_mm):
        assert table.focus_mm(d) == pytest.approx(mm, rel=1e-12)
        assert table.diopters_for(mm) == pytest.approx(d, rel=1e-9, abs=1e-12)


def test_out_of_range_names_the_values() -> None:
    table = FocusCalibration(np.array([1.0, 2.0, 4.0]), np.array([1000.0, 500.0, 250.0]), source="t.yaml")
    with pytest.raises(FocusOutOfRange, match=r"focus 100.0 mm outside the calibrated range \[250.0, 1000.0\]") as info:
        table.diopters_for(100.0, device="PHONE1")
    assert info.value.device == "PHONE1"
    for bad in (1001.0, float("nan"), float("inf")):
        with pytest.raises(FocusOutOfRange):
            table.diopters_for(bad)


@pytest.mark.parametrize("diopters, mm, problem", [
    ([1.0], [1000.0], ">= 2"),
    ([1.0, 1.0], [1000.0, 500.0], "strictly increase"),
    ([1.0, 2.0], [500.0, 1000.0], "strictly decrease"),
    ([-1.0, 2.0], [1000.0, 500.0], "outside"),
    ([1.0, 2.0], [1000.0, 5.0], "outside"),
    ([1.0, float("nan")], [1000.0, 500.0], "finite"),
])
def test_invalid_tables_refused(diopters: list[float], mm: list[float], problem: str) -> None:
    with pytest.raises(FocusCalibrationError, match=problem):
        FocusCalibration(np.array(diopters), np.array(mm))


def test_default_table_covers_the_rig() -> None:
    rig = load_rig()
    for phone in rig.phones:
        table = load_focus_calibration(rig.resolve(phone.focus_calibration))
        assert table.near_mm <= 150.0 and table.far_mm >= 1500.0
        assert table.diopters_for(450.0) == pytest.approx(1000.0 / 450.0, rel=0.05)


@pytest.mark.parametrize("text, key, allowed", [
    ("points: [[1, 1000], [2, 500]]\nextra: 1\n", "extra", "allowed keys: measured, phone_model, points"),
    ("points: [[1, 1000], [2]]\n", "points[1]", "a list of 2 values"),
    ("points: [[1, 1000], [true, 500]]\n", "points[1][0]", "a number in [0, 50]"),
    ("points: [[1, 1000], [2, 5]]\n", "points[1][1]", "a number in [20, 100000]"),
    ("points: [[1, 1000]]\n", "points", "allowed 2 to 1000"),
    ("phone_model: [a, b]\npoints: [[1, 1000], [2, 500]]\n", "phone_model", "any text, number or date"),
    ("- 1\n- 2\n", "<top>", "expected a mapping"),
    ("points: [[1, 1000]\n", "<file>", "not valid YAML"),
])
def test_bad_files_name_file_key_and_range(tmp_path: Path, text: str, key: str, allowed: str) -> None:
    path = tmp_path / "phone.yaml"
    path.write_text(text)
    with pytest.raises(FocusCalibrationError) as info:
        load_focus_calibration(path)
    assert info.value.key == key and str(path) in str(info.value) and allowed in str(info.value)
    with pytest.raises(FocusCalibrationError, match="cannot read"):
        load_focus_calibration(tmp_path / "missing.yaml")


def test_a_huge_or_deeply_nested_focus_table_is_refused_before_parsing(tmp_path):
    from drivers.phone.errors import FocusCalibrationError
    from drivers.phone.focus import MAX_FILE_BYTES, load_focus_calibration

    huge = tmp_path / "huge.yaml"
    huge.write_bytes(b"points:\n" + b"  - [1.0, 1000.0]\n" * (MAX_FILE_BYTES // 17 + 1))
    with pytest.raises(FocusCalibrationError, match=f"larger than {MAX_FILE_BYTES} bytes"):
        load_focus_calibration(huge)
    deep = tmp_path / "deep.yaml"
    deep.write_text("points: " + "[" * 5000 + "]" * 5000 + "\n")
    with pytest.raises(FocusCalibrationError, match="nested more than 32 deep"):
        load_focus_calibration(deep)
