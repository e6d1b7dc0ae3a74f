"""Per-subject capture angles: executable by the capture timeline, never worse than the rig's."""

from __future__ import annotations

import numpy as np
import pytest

from planner.angles import candidate_angles, min_capture_gap_s, plan_angles, subset_table
from planner.cost import cost_table
from planner.plan import plan_focus, rig_redundancy
from planner.poses import rgb_poses
from planner.rig import load_rig
from planner.schedule import PlanInfeasible, compile_plan, rig_profile, scan_rig_time
from planner.visibility import RayScene, visible_pairs
from tests.planner_standin import standin_body

RIG = load_rig()


@pytest.fixture(scope="module")
def chosen():
    body = standin_body()
    plan = plan_focus(body, RIG, points=2000, seed=4, methods=("robust",))
    profile = rig_profile(RIG)
    candidates = candidate_angles(RIG, profile, step_deg=2.0)
    table = cost_table(visible_pairs(RayScene(body), rgb_poses(RIG, candidates), plan.samples, RIG.optics),
                       RIG.cost, RIG.optics)
    result = plan_angles(table, candidates, RIG, plan.methods["robust"].focus_mm,
                         redundancy=rig_redundancy(RIG), profile=profile)
    return plan, table, candidates, result


def test_candidates_are_crossed_at_constant_speed():
    profile = rig_profile(RIG)
    candidates = candidate_angles(RIG, profile, step_deg=1.0)
    assert set(RIG.capture.angles_deg.tolist()) <= set(candidates.tolist())
    speed = profile.speed_at_angle(candidates)
    assert np.allclose(speed, profile.nominal_speed(candidates))
    # The ramps between sectors are left out: 45 deg is where the beam slows from 9 to 3 deg/s.
    assert not np.any((candidates > 45.0) & (candidates < 46.5))
    with pytest.raises(ValueError, match="step"):
        candidate_angles(RIG, profile, step_deg=0.0)


def test_chosen_angles_are_executable_with_the_same_images_and_scan_time(chosen):
    plan, _, _, result = chosen
    assert len(result.angles_deg) == RIG.n_angles
    assert result.focus_mm.shape == (RIG.n_poses,)
    schedule = compile_plan(result.focus_mm, RIG, angles_deg=result.angles_deg)
    assert schedule.violations == ()
    np.testing.assert_array_equal(schedule.angles_deg, result.angles_deg)
    gaps = np.diff(schedule.crossing_s)
    assert gaps.min() >= min_capture_gap_s(RIG) - 1e-9
    # Same motion profile: the rotation, so the scan, takes exactly as long.
    assert schedule.profile.duration_s == scan_rig_time(RIG).capture_s
    assert not np.array_equal(result.angles_deg, RIG.capture.angles_deg)


def test_angle_search_never_ends_worse_than_the_rig_angles(chosen):
    plan, table, candidates, result = chosen
    assert result.objective <= result.start_objective + 1e-9
    assert result.objective < result.start_objective  # the stand-in leaves room to gain
    ids = np.searchsorted(candidates, result.angles_deg)[:, None] * RIG.n_cameras + np.arange(RIG.n_cameras)
    again = subset_table(table, ids.ravel(), RIG)
    assert again.total_cost(result.focus_mm) == pytest.approx(result.total_cost)


def test_timeline_refuses_angles_in_a_ramp_or_out_of_order():
    angles = RIG.capture.angles_deg.copy()
    focus = np.full(RIG.n_poses, 400.0)
    angles[8] = 45.5  # inside the 9 -> 3 deg/s ramp
    with pytest.raises(PlanInfeasible, match="speed ramp"):
        compile_plan(focus, RIG, angles_deg=angles)
    swapped = RIG.capture.angles_deg.copy()
    swapped[[3, 4]] = swapped[[4, 3]]
    with pytest.raises(PlanInfeasible, match="not after the previous"):
        compile_plan(focus, RIG, angles_deg=swapped)
    crowded = RIG.capture.angles_deg.copy()
    crowded[1] = crowded[0] + 1.0  # 0.11 s after the previous capture at 9 deg/s
    with pytest.raises(PlanInfeasible, match="capture cycle"):
        compile_plan(focus, RIG, angles_deg=crowded)
