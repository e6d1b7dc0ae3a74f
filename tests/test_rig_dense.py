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
