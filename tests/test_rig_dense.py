"""calibration_data/rig-dense.yaml: the default rig with more captures in the same rotation."""

from __future__ import annotations

import numpy as np
import pytest

from planner.rig import DEFAULT_RIG_PATH, load_rig
from planner.schedule import PlanInfeasible, compile_plan, rig_profile

DENSE = DEFAULT_RIG_PATH.parent / "rig-dense.yaml"


def test_same_rotation_more_captures() -> None:
    default, dense = load_rig(DEFAULT_RIG_PATH), load_rig(DENSE)
    assert dense.n_poses == 840 and dense.n_poses > 2 * default.n_poses
    assert [(s.start_deg, s.end_deg, s.speed_deg_s) for s in dense.capture.sectors] == \
        [(s.start_deg, s.end_deg, s.speed_deg_s) for s in default.capture.sectors]
    assert rig_profile(dense).duration_s == pytest.approx(rig_profile(default).duration_s)
    assert set(default.capture.angles_deg) <= set(dense.capture.angles_deg)  # the rig's own angles stay
    assert dense.phones == default.phones and dense.optics == default.optics


def test_the_phones_keep_up_with_the_worst_focus_changes() -> None:
    """Every phone swings between its nearest and farthest planned focus at every angle: the
    capture cycle, the lens travel and settling still fit between the dense rig's angles."""
    rig = load_rig(DENSE)
    near_far = np.where(np.arange(rig.n_angles) % 2 == 0, 200.0, 2000.0)
    focus = np.repeat(near_far, rig.n_cameras)
    schedule = compile_plan(focus, rig)  # PlanInfeasible if any capture could not be made
    assert schedule.violations == () and schedule.n_angles == rig.n_angles == 120
    assert float(np.max(schedule.blur_px)) <= rig.capture.max_motion_blur_px


def test_halving_the_fast_step_again_is_refused() -> None:
    """Not a free lunch: 2.5 deg at 9 deg/s is faster than a phone's capture cycle."""
    import dataclasses

    rig = load_rig(DENSE)
    sectors = tuple(dataclasses.replace(s, capture_step_deg=s.capture_step_deg / 2, captures=2 * s.captures - 1)
                    if s.speed_deg_s > 5 else s for s in rig.capture.sectors)
    tight = dataclasses.replace(rig, capture=dataclasses.replace(rig.capture, sectors=sectors))
    with pytest.raises(PlanInfeasible):
        compile_plan(np.full(tight.n_poses, 500.0), tight)


def test_importance_samples_cover_the_same_few_view_skin_as_on_the_default_rig() -> None:
    """840 poses see each piece of skin about 2.5x as often as 336: the few-view threshold of the
    importance samples grows with the poses, so they refine the same folds (docs/planner.md)."""
    default, dense = load_rig(DEFAULT_RIG_PATH), load_rig(DENSE)
    assert dense.planner.importance_density == default.planner.importance_density > 1.0
    assert dense.planner.importance_radius_mm == default.planner.importance_radius_mm
    per_pose = dense.planner.importance_views / dense.n_poses
    assert per_pose == pytest.approx(default.planner.importance_views / default.n_poses, rel=0.1)
