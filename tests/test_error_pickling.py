"""Planner errors raised in a worker process (TSDF fusion, planning) reach the daemon intact:
same class, same message, same fields."""

from __future__ import annotations

import pickle

import pytest

from planner import focus_errors, schedule, shape_errors
from planner.calibration.calibrate import CalibrationFailed
from planner.calibration.installed import CalibrationMismatch
from planner.rig import RigConfigError

CASES = [
    shape_errors.FrameOutsideTrace("depth0", 7, 1.5, 0.0, 1.0),
    shape_errors.UnknownDepthCamera("depth9", ["depth0", "depth1"]),
    shape_errors.TooFewFrames(3, 20, {"depth0": 3}),
    shape_errors.NoSubject("only floor"),
    shape_errors.SubjectTouchesBoundary("side", 90.0, 1200.0, 425.0, 430.0),
    shape_errors.SubjectTooCloseToCameras(10.0, 900.0, 410.0, 450.0, 50.0),
    shape_errors.ImplausibleSubject("height", 400.0, 1000.0, 2300.0),
    shape_errors.BadTrace("times not increasing"),
    focus_errors.EmptyMesh("body.ply", 0, 0.0),
    focus_errors.PlanTooLarge(10_000_000, 336, 10**12, 2 * 2**30),
    focus_errors.BadFocusPlan("wrong length", 336),
    schedule.OutsideProfile(400.0, -45.0, 315.0),
    RigConfigError("rig.yaml", "motor.node_id", "must be 1..127, not 0"),
    CalibrationMismatch("calibration.yaml", ["cam7"], ["cam0"]),
    CalibrationFailed("no pictures", []),
]


@pytest.mark.parametrize("error", CASES, ids=lambda e: type(e).__name__)
def test_error_survives_the_process_boundary(error):
    back = pickle.loads(pickle.dumps(error))
    assert type(back) is type(error)
    assert str(back) == str(error) and back.args == error.args
    assert vars(back) == vars(error)
