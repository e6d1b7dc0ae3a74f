"""Rig file validation: every bad file stops with a RigConfigError naming file, key and range."""

from __future__ import annotations

from pathlib import Path

import pytest
import yaml

from planner.rig import DEFAULT_RIG_PATH, RigConfigError, load_rig


@pytest.fixture()
def raw() -> dict:
    return yaml.safe_load(DEFAULT_RIG_PATH.read_text())


def _write(tmp_path: Path, data) -> Path:
    path = tmp_path / "rig.yaml"
    path.write_text(data if isinstance(data, str) else yaml.safe_dump(data))
    return path


def test_default_rig_loads() -> None:
    rig = load_rig()
    assert rig.n_cameras == 7 and rig.n_angles == 48 and rig.n_poses == 336
    assert rig.pose_index(2, 3) == 17


def test_out_of_range_value_names_file_key_and_range(tmp_path: Path, raw: dict) -> None:
    raw["optics"]["hfov_deg"] = 500.0
    path = _write(tmp_path, raw)
    with pytest.raises(RigConfigError) as info:
        load_rig(path)
    err = info.value
    assert err.path == str(path) and err.key == "optics.hfov_deg"
    assert "500" in str(err) and "[5, 120]" in str(err) and str(path) in str(err)


def test_wrong_type_is_refused(tmp_path: Path, raw: dict) -> None:
    raw["phones"][2]["height_mm"] = "tall"
    with pytest.raises(RigConfigError, match=r"phones\[2\]\.height_mm: got 'tall'; expected a number in \[0, 2600\]"):
        load_rig(_write(tmp_path, raw))


def test_unknown_key_is_refused(tmp_path: Path, raw: dict) -> None:
    raw["cost"]["w_aera"] = 0.3
    with pytest.raises(RigConfigError) as info:
        load_rig(_write(tmp_path, raw))
    assert info.value.key == "cost.w_aera"
    assert "unknown key" in str(info.value) and "w_area" in str(info.value)


def test_missing_key_names_the_expected_range(tmp_path: Path, raw: dict) -> None:
    del raw["planner"]["em_max_iterations"]
    with pytest.raises(RigConfigError) as info:
        load_rig(_write(tmp_path, raw))
    assert info.value.key == "planner.em_max_iterations"
    assert "missing" in str(info.value) and "an integer in [1, 10000]" in str(info.value)


def test_missing_section_is_refused(tmp_path: Path, raw: dict) -> None:
    del raw["optics"]
    with pytest.raises(RigConfigError, match="optics: missing section"):
        load_rig(_write(tmp_path, raw))


def test_malformed_yaml_names_the_file(tmp_path: Path) -> None:
    path = _write(tmp_path, "optics: [unclosed\n  focal: {")
    with pytest.raises(RigConfigError) as info:
        load_rig(path)
    assert info.value.path == str(path) and "not valid YAML" in str(info.value)


def test_missing_file_names_the_file(tmp_path: Path) -> None:
    with pytest.raises(RigConfigError, match="nowhere.yaml: <file>: cannot read"):
        load_rig(tmp_path / "nowhere.yaml")


def test_blurring_sector_speed_is_refused(tmp_path: Path, raw: dict) -> None:
    raw["capture"]["sectors"][0]["speed_deg_s"] = 30.0
    with pytest.raises(RigConfigError, match=r"capture.sectors\[0\].speed_deg_s: 30 deg/s blurs"):
        load_rig(_write(tmp_path, raw))


@pytest.mark.parametrize("name", ["rig.yaml", "rig-dense.yaml"])
def test_every_value_of_a_shipped_rig_file_reaches_the_rig_as_written(name: str) -> None:
    path = DEFAULT_RIG_PATH.parent / name
    raw, rig = yaml.safe_load(path.read_text()), load_rig(path)

    def check(value: object, loaded: object, key: str) -> None:
        if isinstance(value, dict):
            for field, inner in value.items():
                check(inner, getattr(loaded, field), f"{key}.{field}")
        elif isinstance(value, list):
            assert len(value) == len(loaded), key  # type: ignore[arg-type]
            for i, inner in enumerate(value):
                check(inner, loaded[i], f"{key}[{i}]")  # type: ignore[index]
        else:
            assert loaded == value and type(loaded) in (type(value), float), key

    raw["ring_radius_mm"] = raw.pop("ring")["radius_mm"]
    check(raw, rig, name)
