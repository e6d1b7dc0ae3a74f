"""plan_focus / evaluate / the JSON plan / `tbp plan`, and their typed errors."""

from __future__ import annotations

import functools
import json
from pathlib import Path

import numpy as np
import pytest
import trimesh

from cli import main as tbp
from planner import plan as plan_module
from planner.focus_errors import BadFocusPlan, EmptyMesh, MeshLoadError, NothingVisible
from planner.plan import METHODS, evaluate, load_subject_mesh, plan_focus
from planner.poses import rgb_poses
from planner.rig import load_rig
from tests.planner_standin import standin_body

RIG = load_rig()
METHOD_KEYS = {"total_cost", "in_focus_fraction", "focus_mm", "seconds"}


@pytest.fixture(scope="module")
def body() -> trimesh.Trimesh:
    return standin_body()


@pytest.fixture(scope="module")
def result(body):
    return plan_focus(body, RIG, points=2000, seed=4)


def test_json_has_the_agreed_keys(result) -> None:
    out = json.loads(json.dumps(result.to_json()))
    assert {"points", "poses", "angles_deg", "camera_heights_mm", "visible_fraction",
            "resolution_mm_per_px", "methods", "timing_s"} <= set(out)
    assert out["points"] == 2000 and out["poses"] == 336
    assert out["angles_deg"] == RIG.capture.angles_deg.tolist()
    assert out["camera_heights_mm"] == [p.height_mm for p in RIG.phones]
    assert set(out["methods"]) == {"closest", "average", "em", "shape-aware", "robust", "robust-angles", "fixed",
                                   "autofocus"}
    for m in out["methods"].values():
        assert set(m) >= METHOD_KEYS
        assert len(m["focus_mm"]) == 336
    # The plan to capture with chose its own 48 angles; the others use the rig's.
    assert out["capture_method"] == "robust-angles"
    assert out["capture_angles_deg"] == out["methods"]["robust-angles"]["angles_deg"]
    assert len(out["capture_angles_deg"]) == 48 and "angles_deg" not in out["methods"]["robust"]
    assert {"mean", "std", "share_at_most_0.075"} <= set(out["resolution_mm_per_px"])
    assert {"visibility", "total"} <= set(out["timing_s"])


def test_methods_rank_as_expected(result) -> None:
    m = result.methods
    assert m["shape-aware"].total_cost <= m["em"].total_cost < m["average"].total_cost
    assert m["shape-aware"].in_focus_fraction >= m["em"].in_focus_fraction
    assert m["average"].in_focus_fraction > m["closest"].in_focus_fraction
    assert np.all(np.diff(m["fixed"].focus_mm) == 0)
    assert m["shape-aware"].in_focus_fraction <= result.visible_fraction
    np.testing.assert_array_equal(result.focus_mm, m["robust-angles"].focus_mm)
    assert m["robust-angles"].in_focus_fraction >= m["robust"].in_focus_fraction - 0.01


def test_evaluate_reproduces_the_plan_on_its_own_samples(body, result) -> None:
    same = evaluate(result.methods["robust"].focus_mm, body, RIG, points=result.samples)
    assert same.total_cost == pytest.approx(result.methods["robust"].total_cost)
    fresh = evaluate(result.methods["robust"].focus_mm, body, RIG, points=2000, seed=99)
    assert abs(fresh.in_focus_fraction - result.methods["robust"].in_focus_fraction) < 0.05


def test_evaluate_on_other_poses(body, result) -> None:
    shifted = rgb_poses(RIG, RIG.capture.angles_deg + 20.0)
    moved = evaluate(result.methods["robust"].focus_mm, body, RIG, points=result.samples, poses=shifted)
    assert moved.total_cost != pytest.approx(result.methods["robust"].total_cost)


def test_plan_on_given_methods_only(body) -> None:
    only = plan_focus(body, RIG, points=500, methods=("closest",))
    assert set(only.methods) == {"closest"}
    with pytest.raises(ValueError, match="unknown focus method 'magic'"):
        plan_focus(body, RIG, points=500, methods=("magic",))


def test_sorting_the_ends_beside_em_changes_no_plan(body, monkeypatch) -> None:
    """The presort runs on a second thread while EM runs when a core is spare; the plans are the
    same either way, and the thread is used when allowed (the table's ends come from it)."""
    methods = ("em", "shape-aware", "robust")
    monkeypatch.setattr(plan_module, "spare_core", lambda: False)
    alone = plan_focus(body, RIG, points=800, seed=2, methods=methods)
    monkeypatch.setattr(plan_module, "spare_core", lambda: True)
    threads: list[str] = []
    real = plan_module.CostTable.ends.func

    def ends(table):
        import threading

        threads.append(threading.current_thread().name)
        return real(table)

    monkeypatch.setattr(plan_module.CostTable, "ends", functools.cached_property(ends))
    plan_module.CostTable.ends.__set_name__(plan_module.CostTable, "ends")
    beside = plan_focus(body, RIG, points=800, seed=2, methods=methods)
    assert threads and threads[0].startswith("presort")
    for name in methods:
        assert np.array_equal(alone.methods[name].focus_mm, beside.methods[name].focus_mm)


def test_empty_mesh_is_refused() -> None:
    with pytest.raises(EmptyMesh, match="empty.ply is empty: 0 faces"):
        plan_focus(trimesh.Trimesh(), RIG, mesh_name="empty.ply")


def test_subject_out_of_view_is_refused(body) -> None:
    lifted = body.copy()
    lifted.apply_translation([0.0, 0.0, 5000.0])
    with pytest.raises(NothingVisible, match="lifted.ply: none of 300 surface samples") as info:
        plan_focus(lifted, RIG, points=300, mesh_name="lifted.ply")
    assert info.value.poses == 336


@pytest.mark.parametrize(
    "focus, problem",
    [(np.ones(3), "has shape"), (np.full(336, np.nan), "pose 0 has focus nan"), (-np.ones(336), "pose 0")],
)
def test_bad_focus_plan_is_refused(body, focus, problem) -> None:
    with pytest.raises(BadFocusPlan, match=problem):
        evaluate(focus, body, RIG, points=100)


def test_mesh_file_errors(tmp_path: Path) -> None:
    with pytest.raises(MeshLoadError, match="no such file"):
        load_subject_mesh(tmp_path / "missing.ply")
    bad = tmp_path / "bad.ply"
    bad.write_text("not a mesh")
    with pytest.raises(MeshLoadError, match="bad.ply: cannot be read"):
        load_subject_mesh(bad)
    big = tmp_path / "big.ply"
    big.write_bytes(b"ply\nformat ascii 1.0\n" + b" " * 4096)
    with pytest.raises(MeshLoadError, match="larger than the 1024 a body mesh may have"):
        load_subject_mesh(big, max_bytes=1024)


def test_cli_plan_writes_json(tmp_path: Path, body, capsys) -> None:
    mesh = tmp_path / "body.ply"
    body.export(mesh)
    out = tmp_path / "plan.json"
    assert tbp(["plan", "--mesh", str(mesh), "--points", "800", "--json", str(out), "--fresh", "500"]) == 0
    text = capsys.readouterr().out
    for name in METHODS:
        assert name in text
    assert "visible" in text and "fresh sample" in text and "robust-angles in focus" in text
    assert "certified" in text
    plan = json.loads(out.read_text())
    assert plan["points"] == 800 and plan["fresh_sample"]["points"] == 500
    assert plan["methods"]["robust"]["in_focus_fraction"] <= plan["in_focus_bound"] <= plan["visible_fraction"]


def test_cli_plan_errors_name_the_file(tmp_path: Path, capsys) -> None:
    missing = tmp_path / "nope.ply"
    assert tbp(["plan", "--mesh", str(missing)]) == 1
    assert "nope.ply: no such file" in capsys.readouterr().err
    empty = tmp_path / "empty.ply"
    trimesh.Trimesh(vertices=np.zeros((3, 3)), faces=[[0, 1, 2]]).export(empty)
    assert tbp(["plan", "--mesh", str(empty)]) == 1
    assert "empty" in capsys.readouterr().err
    assert tbp(["plan", "--mesh", str(missing), "--points", "0"]) == 2


def test_zero_area_mesh_is_refused() -> None:
    flat = trimesh.Trimesh(vertices=[[0, 0, 0], [1, 0, 0], [2, 0, 0]], faces=[[0, 1, 2]], process=False)
    with pytest.raises(EmptyMesh, match="line.ply is empty: 1 faces, surface area 0"):
        plan_focus(flat, RIG, points=10, mesh_name="line.ply")


def test_inside_out_mesh_is_named(body) -> None:
    from planner.focus_errors import InvertedMesh

    flipped = body.copy()
    flipped.invert()
    with pytest.raises(InvertedMesh, match="flipped.ply is wound inside out"):
        plan_focus(flipped, RIG, points=300, mesh_name="flipped.ply")


def test_cli_plan_views_of_a_point(tmp_path: Path, body, capsys) -> None:
    mesh = tmp_path / "body.ply"
    body.export(mesh)
    chest = f"{body.bounds[1, 0] + 50:.0f},0,1200"
    assert tbp(["plan", "--mesh", str(mesh), "--points", "800", "--view", chest, "--backend", "embree"]) == 0
    out = capsys.readouterr().out
    assert "near" in out and "pixel (" in out and "cam" in out
    assert tbp(["plan", "--mesh", str(mesh), "--view", "1,2"]) == 2
    assert "--view expects X,Y,Z in mm, got '1,2'" in capsys.readouterr().err


def test_json_angles_follow_the_poses_planned_for(body) -> None:
    from planner.plan import pose_angles_deg

    assert pose_angles_deg(rgb_poses(RIG), RIG).tolist() == RIG.capture.angles_deg.tolist()
    few = rgb_poses(RIG, np.array([0.0, 90.0, 180.0, -90.0]))
    result = plan_focus(body, RIG, points=300, poses=few, methods=("average",))
    out = result.to_json()
    assert out["angles_deg"] == [0.0, 90.0, 180.0, -90.0]
    assert out["poses"] == 28 and len(out["methods"]["average"]["focus_mm"]) == 28


def test_json_angles_of_noisy_poses_stay_near_the_rig_angles() -> None:
    from planner.plan import pose_angles_deg
    from planner.pose_noise import perturb_poses

    noisy = pose_angles_deg(perturb_poses(rgb_poses(RIG), seed=2), RIG)
    np.testing.assert_allclose(noisy, RIG.capture.angles_deg, atol=0.5)
