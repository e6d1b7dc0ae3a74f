"""A careless or hostile rig file (issue 14, probe 4): refused with a short, typed error naming the
key, never a traceback, never an unbounded allocation; and meshes outside the ring refused."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import trimesh
import yaml

from planner.focus_errors import PlanTooLarge, SubjectOutsideRing
from planner.plan import plan_focus
from planner.rig import DEFAULT_RIG_PATH, PLAN_MEMORY_BUDGET_BYTES, RigConfigError, load_rig
from tests.memory import rss_bytes, run_bounded

MAX_MESSAGE = 400  # characters: an error names file, key and range, it does not quote a file


@pytest.fixture()
def text() -> str:
    return DEFAULT_RIG_PATH.read_text()


def _load(tmp_path: Path, text: str) -> RigConfigError:
    path = tmp_path / "rig.yaml"
    path.write_text(text)
    before = rss_bytes()
    with pytest.raises(RigConfigError) as info:
        load_rig(path)
    assert rss_bytes() - before < 100 * 1024 * 1024
    assert len(str(info.value)) < MAX_MESSAGE + len(str(path)), str(info.value)[:1000]
    return info.value


def _raw_with(**changes: object) -> dict:
    raw = yaml.safe_load(DEFAULT_RIG_PATH.read_text())
    for dotted, value in changes.items():
        *parents, leaf = dotted.split("__")
        node = raw
        for part in parents:
            node = node[int(part)] if isinstance(node, list) else node[part]
        node[leaf] = value
    return raw


@pytest.mark.parametrize("bad_id", ["../../../escaped", "..", ".hidden", "cam/0", "cam 0", "", "a" * 33,
                                    "cam0\n", "-rf", "caméra"])
def test_phone_ids_outside_the_safe_pattern_are_refused(tmp_path: Path, bad_id: str) -> None:
    raw = _raw_with(phones__0__id=bad_id)
    error = _load(tmp_path, yaml.safe_dump(raw))
    assert error.key == "phones[0].id" and "letters, digits" in error.problem


def test_depth_camera_ids_and_sector_names_follow_the_same_pattern(tmp_path: Path) -> None:
    assert _load(tmp_path, yaml.safe_dump(_raw_with(depth_cameras__1__id="../x"))).key == "depth_cameras[1].id"
    assert _load(tmp_path, yaml.safe_dump(_raw_with(capture__sectors__0__name="a/b"))).key == \
        "capture.sectors[0].name"


@pytest.mark.parametrize("levels, expected", [
    (12, "optics.focal_length_mm[6]: aliases make it 5380840 values, more than the 1048576 a rig file holds"),
    (5, "optics.focal_length_mm: got [["),
])
def test_an_alias_bomb_under_a_known_key_is_refused_or_described_never_expanded(
        tmp_path: Path, text: str, levels: int, expected: str) -> None:
    """9**12 strings if expanded: refused while the file is parsed, past what a file of the allowed
    size holds; 9**5 is within that bound and the type check quotes a few values. In a child whose
    memory may grow 200 MiB."""
    lines = ["    - &l0 [lol, lol, lol, lol, lol, lol, lol, lol, lol]"]
    lines += [f"    - &l{i} [{', '.join([f'*l{i - 1}'] * 9)}]" for i in range(1, levels)]
    path = tmp_path / "rig.yaml"
    path.write_text(text.replace("focal_length_mm: 6.0", "focal_length_mm:\n" + "\n".join(lines)))
    child = run_bounded("from planner.rig import RigConfigError, load_rig",
                        f"try:\n    load_rig({str(path)!r})\nexcept RigConfigError as exc:\n    print(exc)")
    assert child.returncode == 0, child.stderr[-2000:]
    assert expected in child.stdout
    assert len(child.stdout) < MAX_MESSAGE + len(str(path))


@pytest.mark.parametrize("number, shown", [("1" + "0" * 400, "integer of about 401 digits"),
                                           ("0x" + "f" * 20_000, "integer of about 24083 digits"),
                                           ("-" + "9" * 300, "integer of about 301 digits")])
def test_huge_integers_are_refused_by_size(tmp_path: Path, text: str, number: str, shown: str) -> None:
    error = _load(tmp_path, text.replace("iso: 50", f"iso: {number}"))
    assert error.key == "optics.iso" and shown in error.problem


def test_numbers_python_cannot_read_and_deep_nesting_name_the_file(tmp_path: Path, text: str) -> None:
    assert _load(tmp_path, text.replace("iso: 50", "iso: " + "7" * 5000)).key == "<file>"
    assert _load(tmp_path, "optics: " + "[" * 800 + "]" * 800 + "\n").problem.startswith("lists or mappings nested")
    assert _load(tmp_path, "optics: " + "[" * 500_000 + "\n").key == "<file>"  # quadratic to scan: refused first
    nested = "".join(" " * i + f"k{i}:\n" for i in range(1200)) + "v\n"  # block nesting: the parser's recursion
    assert _load(tmp_path, nested).problem.startswith("not a rig file: RecursionError")


def test_huge_strings_and_files_are_refused(tmp_path: Path, text: str) -> None:
    error = _load(tmp_path, text.replace("focus/default.yaml", "x" * 100_000, 1))
    assert error.key == "phones[0].focus_calibration" and "at most 256 characters" in error.problem
    assert _load(tmp_path, text + "#" * (1024 * 1024)).problem.startswith("larger than")


def test_planning_points_are_bounded_by_the_memory_budget(tmp_path: Path) -> None:
    error = _load(tmp_path, yaml.safe_dump(_raw_with(planner__points=10_000_000)))
    assert error.key == "planner.points"
    assert "needs about 50.1 GiB" in error.problem and "allowed at most 798915 points" in error.problem
    path = tmp_path / "ok.yaml"
    path.write_text(yaml.safe_dump(_raw_with(planner__points=500_000)))
    assert load_rig(path).planner.points == 500_000


def test_all_cost_weights_zero_is_refused(tmp_path: Path) -> None:
    error = _load(tmp_path, yaml.safe_dump(_raw_with(cost__w_area=0.0, cost__w_axis=0.0, cost__w_focus=0)))
    assert error.key == "cost" and "at least one weight must be positive" in error.problem


def _box(centre: tuple[float, float, float]) -> trimesh.Trimesh:
    box = trimesh.creation.box(extents=(300.0, 300.0, 1600.0))
    box.apply_translation(centre)
    return box


@pytest.mark.parametrize("vertex", [(1e30, 0.0, 0.0), (np.nan, 0.0, 100.0), (0.0, 460.0, 500.0)])
def test_a_mesh_vertex_outside_the_ring_is_refused(vertex: tuple[float, float, float]) -> None:
    body = _box((0.0, 0.0, 900.0))
    stray = trimesh.Trimesh(np.vstack([body.vertices, vertex]), body.faces, process=False)
    with pytest.raises(SubjectOutsideRing, match=r"stray.ply: vertex 8 at .* outside the camera ring \(radius 450"):
        plan_focus(stray, load_rig(), points=500, mesh_name="stray.ply")


def test_planning_more_samples_than_the_budget_is_refused_before_sampling() -> None:
    rig = load_rig()
    with pytest.raises(PlanTooLarge, match="10000000 samples x 336 poses need about 50.1 GiB") as info:
        plan_focus(_box((0.0, 0.0, 900.0)), rig, points=10_000_000)
    assert info.value.budget_bytes == PLAN_MEMORY_BUDGET_BYTES
