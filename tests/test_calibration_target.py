"""The ChArUco cuboid: geometry of the boards on the faces, validation, printable boards."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import yaml

from planner.calibration.target import DEFAULT_TARGET_PATH, TargetError, load_target

TARGET = load_target()


def test_default_target_is_the_seed_cuboid_with_unique_marker_ids() -> None:
    assert TARGET.size_mm == (280.0, 280.0, 1800.0)
    assert len(TARGET.faces) == 4
    assert TARGET.legacy_pattern is False
    ids = np.concatenate([TARGET.board(f.index).getIds() for f in TARGET.faces])
    assert len(ids) == len(set(ids.tolist())) == 4 * TARGET.markers_per_face


def test_every_corner_lies_on_its_face_of_the_cuboid() -> None:
    per = TARGET.corners_per_face
    for f in TARGET.faces:
        pts = TARGET.corners[f.index * per:(f.index + 1) * per]
        # on the face plane (140 mm out along the normal), inside the face, z within the height
        assert np.allclose(pts @ f.normal, 140.0)
        across = np.cross([0.0, 0.0, 1.0], f.normal)
        assert np.all(np.abs(pts @ across) < 140.0)
        assert pts[:, 2].min() > 0 and pts[:, 2].max() < 1800.0
    # the board's first row is at the top: corner 0 is one square below the cuboid's top
    assert TARGET.corners[0, 2] == pytest.approx(1800.0 - TARGET.square_mm)


def test_boards_face_outwards_right_handed() -> None:
    for f in TARGET.faces:
        r = f.cuboid_from_board[:3, :3]
        assert np.allclose(r.T @ r, np.eye(3)) and np.linalg.det(r) == pytest.approx(1.0)
        assert np.allclose(r[:, 2], -f.normal)  # board z points into the cuboid


def test_face_of_marker() -> None:
    first = [f.first_marker_id for f in TARGET.faces]
    assert TARGET.face_of_marker(np.array(first + [999])).tolist() == [0, 1, 2, 3, -1]


@pytest.mark.parametrize("key, value, words", [
    ("marker_mm", 45.0, "smaller than square_mm"),
    ("dictionary", "DICT_NOPE", "predefined ArUco dictionary"),
    ("legacy_pattern", "no", "true or false"),
    ("squares", [8, 45], "does not fit face"),
    ("faces", [{"name": "+x", "first_marker_id": 0}, {"name": "+y", "first_marker_id": 100}], "overlap"),
    ("colour", "red", "unknown key"),
])
def test_bad_target_file_names_the_key(tmp_path: Path, key: str, value: object, words: str) -> None:
    raw = yaml.safe_load(DEFAULT_TARGET_PATH.read_text())
    raw[key] = value
    path = tmp_path / "t.yaml"
    path.write_text(yaml.safe_dump(raw))
    with pytest.raises(TargetError) as info:
        load_target(path)
    assert key in str(info.value) and words in str(info.value)


def test_printable_boards_are_true_size(tmp_path: Path) -> None:
    from PIL import Image

    from analysis.target_prints import write_target_prints

    files = write_target_prints(TARGET, tmp_path)
    assert sorted(p.name for p in files if p.suffix == ".pdf") == [
        "face_minus_x.pdf", "face_minus_y.pdf", "face_plus_x.pdf", "face_plus_y.pdf"]
    with Image.open(tmp_path / "face_plus_x.png") as im:
        width_mm = im.size[0] / TARGET.print_dpi * 25.4
        assert width_mm == pytest.approx(280.0, abs=0.2)
    assert (tmp_path / "face_plus_x.pdf").read_bytes().startswith(b"%PDF")
