"""A subject reaching towards the camera ring is refused before the capture rotation."""

from __future__ import annotations

import json

import pytest
import trimesh

from daemon.jobs.scan import ScanOutcome
from sim.run import run_sim_scan
from tests.daemon_rigs import PLAN_POINTS, capsule_subject


@pytest.mark.slow  # a simulated scan to the end of its depth sweep
def test_an_outstretched_arm_ends_the_scan_before_any_capture(tmp_path):
    arm = trimesh.creation.capsule(height=280.0, radius=45.0, count=[16, 16])
    arm.apply_transform(trimesh.transformations.rotation_matrix(1.5708, [1, 0, 0]))
    arm.apply_translation([0.0, 260.0, 1150.0])  # reaches about 445 mm from the axis
    subject = trimesh.util.concatenate([capsule_subject(), arm])
    report = run_sim_scan(store=tmp_path, seed=1, plan_points=PLAN_POINTS, depth_decimation=4,
                          subject=subject, panel=False)
    assert report.outcome is ScanOutcome.ABORTED
    assert "SubjectTooCloseToCameras" in report.reason and "azimuth" in report.reason
    assert report.captured == 0
    manifest = json.loads((report.folder / "manifest.json").read_text())
    assert manifest["state"] == "aborted" and not manifest["in_progress"]
    assert "SubjectTooCloseToCameras" in manifest["reason"]
