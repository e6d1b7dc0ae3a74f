"""Rig designer: constraints are kept, the search never ends below its start, the rig file loads."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from cli import main as tbp
from planner.design import (
    Constraints,
    ConstraintValueError,
    DesignError,
    Subject,
    depth_coverage,
    design_score,
    nearest_configs,
    pattern_sector_dicts,
    phone_library,
    search_phones,
    split_capture,
)
from planner.rig import load_rig, rig_from_mapping
from planner.sampling import sample_surface
from planner.schedule import compile_plan, rig_profile
from tests.planner_standin import standin_body

RIG = load_rig()


@pytest.fixture(scope="module")
def subjects():
    out = []
    for i, scale in enumerate((0.9, 1.15)):
        mesh = standin_body(scale=scale)
        out.append(Subject(f"standin{i}", mesh, sample_surface(mesh, 400, seed=i)))
    return out


def test_constraints_that_cannot_hold_the_phones_are_refused():
    with pytest.raises(DesignError, match="7 phones 400 mm apart"):
        Constraints(phones=7, ring_radius_mm=450.0, column_height_mm=2000.0, phone_spacing_mm=400.0).heights()
    with pytest.raises(DesignError, match="no room"):
        Constraints(phones=2, ring_radius_mm=450.0, column_height_mm=50.0).heights()


def test_phone_search_keeps_spacing_and_never_scores_below_its_start(subjects):
    constraints = Constraints(phones=4, ring_radius_mm=450.0, column_height_mm=2100.0, phone_spacing_mm=250.0,
                              tilts_deg=(-25.0, 0.0, 25.0), height_step_mm=120.0)
    library = phone_library(subjects, RIG, constraints)
    assert library.seen.shape == (2, len(library.configs), 400)
    start = nearest_configs(library, [200.0, 700.0, 1200.0, 1700.0], [0.0] * 4)
    chosen = search_phones(library, constraints, start)
    heights = library.configs[chosen, 0]
    assert np.all(np.diff(heights) >= 250.0 - 1e-9)
    assert heights.max() <= 2100.0

    def score(choice):
        return design_score(library.seen[:, choice].any(axis=1), library.quality[:, choice].min(axis=1))[0]

    assert score(chosen) >= score(start)
    # A single phone at the bottom looking down sees less than the designed column.
    lone = nearest_configs(library, [80.0], [-25.0])
    assert library.seen[:, lone].any(axis=1).mean() < library.seen[:, chosen].any(axis=1).mean()


def test_depth_coverage_grows_with_more_cameras(subjects):
    one = depth_coverage(subjects[0], RIG, RIG.depth_cameras[:1])
    every = depth_coverage(subjects[0], RIG, RIG.depth_cameras)
    assert every.shape == (3, 400)
    assert every.any(axis=0).mean() >= one.any(axis=0).mean() > 0.3


@pytest.mark.parametrize("fast", [7, 9, 11])
def test_capture_splits_are_valid_rig_patterns(fast):
    capture = split_capture(RIG.capture, fast, RIG.n_angles)
    assert sum(s.captures for s in capture.sectors) == RIG.n_angles
    raw = {"capture": {"sectors": pattern_sector_dicts(capture)}}
    import yaml

    mapping = yaml.safe_load(Path(RIG.path).read_text())
    mapping["capture"]["sectors"] = raw["capture"]["sectors"]
    rig = rig_from_mapping(mapping, "<split>")
    rig_profile(rig)  # no capture in a ramp
    assert compile_plan(np.full(rig.n_poses, 500.0), rig, check=False).violations == ()
    with pytest.raises(DesignError, match="cannot be split"):
        split_capture(RIG.capture, 13, 47)


@pytest.mark.slow
def test_tbp_design_writes_a_loadable_rig_and_a_report(tmp_path, capsys):
    out = tmp_path / "design"
    assert tbp(["design", "--bodies", "0", "--points", "300", "--verify-bodies", "0", "--verify-points", "600",
                "--out", str(out)]) == 0
    rig = load_rig(out / "rig.yaml")
    assert rig.n_cameras == 7 and rig.n_angles == 48 and rig.ring_radius_mm == 450.0
    heights = sorted(p.height_mm for p in rig.phones)
    assert np.all(np.diff(heights) >= 170.0 - 1e-9) and heights[-1] <= 2300.0
    assert rig.tsdf.volume_height_mm >= 2200.0  # holds the 2.1 m adult
    summary = json.loads((out / "design.json").read_text())
    assert [r["label"] for r in summary["verification"]["designed"]] == ["tall", "short"]
    page = (out / "report.html").read_text()
    assert "designed rig" in page and "layout.png" in page
    for name in ("layout.png", "visible.png", "in_focus.png"):
        assert (out / name).stat().st_size > 1000
    assert "designed rig: visible" in capsys.readouterr().out
    assert tbp(["design", "--phones", "30", "--out", str(tmp_path / "x")]) == 1


@pytest.mark.parametrize("args, problem", [
    (["--phones", "0"], "--phones 0: expected 1 to 64"),
    (["--radius", "-5"], "--radius -5: expected a positive length in mm"),
    (["--radius", "nan"], "--radius nan: expected a positive length in mm"),
    (["--spacing", "0"], "--spacing 0: expected a positive length in mm"),
    (["--column-height", "inf"], "--column-height inf: expected a positive length in mm"),
    (["--out", "{tmp}/a-file/design"], "--out {tmp}/a-file/design: {tmp}/a-file is not a folder"),
])
def test_unusable_design_constraints_are_refused_in_one_line_before_any_work(tmp_path, capsys, monkeypatch, args,
                                                                            problem):
    import analysis.design

    def never(*args: object, **kwargs: object) -> None:
        raise AssertionError("the search ran before the refusal")

    monkeypatch.setattr(analysis.design, "design", never)
    (tmp_path / "a-file").write_text("x")
    args = [a.replace("{tmp}", str(tmp_path)) for a in args]
    out = [] if "--out" in args else ["--out", str(tmp_path / "design")]
    assert tbp(["design", *args, *out]) == 2
    err = capsys.readouterr().err
    assert err.strip() == f"tbp design: {problem.replace('{tmp}', str(tmp_path))}", err


@pytest.mark.parametrize("field, value", [("phones", 0), ("phones", 65), ("ring_radius_mm", 0.0),
                                          ("column_height_mm", float("nan")), ("phone_spacing_mm", -170.0),
                                          ("lowest_mm", -1.0), ("height_step_mm", float("inf"))])
def test_constraints_refuse_a_value_that_is_not_a_count_or_length(field, value):
    given = {"phones": 7, "ring_radius_mm": 450.0, "column_height_mm": 2300.0, field: value}
    with pytest.raises(ConstraintValueError) as refused:
        Constraints(**given)
    assert refused.value.name == field and str(refused.value).startswith(f"{field} {value!r}: expected ")
