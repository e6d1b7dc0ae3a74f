"""Every consumer uses the installed calibration: planning and the TSDF (the daemon's scan), the scan
manifest, navigation; a calibration for other cameras refuses the scan, an old one warns."""

from __future__ import annotations

import asyncio
import dataclasses
import json
import math
from pathlib import Path

import numpy as np
import pytest
import yaml

from daemon.errors import CalibrationRefused
from daemon.jobs.controller import RigController
from daemon.records.store import ScanStore, calibration_digest
from daemon.rig.hardware import RigHardware
from planner.calibration.target import load_target
from planner.poses import rgb_poses, rig_depth_pose, rig_rgb_poses
from planner.rig import CALIBRATION_DIR, DEFAULT_RIG_PATH, load_rig
from planner.sweep import BeamTrace, tag_frame
from sim.calibration import true_rig
from tests.daemon_mocks import MockDrive

TARGET = load_target()


def rig_with_calibration(tmp: Path, *, drop: str | None = None, created: str = "2026-11-20T10:00:00+00:00"):
    """A rig file in tmp naming tmp/calibration.yaml: the simulated truth of seed 3 (optionally without one camera)."""
    raw = yaml.safe_load(DEFAULT_RIG_PATH.read_text())
    for phone in raw["phones"]:
        phone["focus_calibration"] = str(CALIBRATION_DIR / phone["focus_calibration"])
    raw["calibration"] = {"file": "calibration.yaml", "max_age_days": 30}
    (tmp / "rig.yaml").write_text(yaml.safe_dump(raw))
    rig = load_rig(tmp / "rig.yaml")
    truth = true_rig(rig, TARGET, 3)
    cameras = tuple(c for c in truth.cameras if c.id != drop)
    dataclasses.replace(truth, cameras=cameras, created_utc=created).save(tmp / "calibration.yaml")
    return rig


def _controller(rig) -> RigController:
    """A controller whose (stand-in) devices all answered the bring-up."""
    controller = RigController(rig, RigHardware(MockDrive(), [], []), ScanStore(Path("/nonexistent")))
    for device in controller.bringup.devices.values():
        device.ok = True
    return controller


def test_without_a_calibration_the_poses_are_nominal() -> None:
    rig = load_rig()
    a, b = rig_rgb_poses(rig), rgb_poses(rig)
    assert np.array_equal(a.centres, b.centres) and np.array_equal(a.forward, b.forward)


def test_poses_and_depth_frames_come_from_the_calibration(tmp_path: Path) -> None:
    from planner.calibration.installed import installed_calibration

    rig = rig_with_calibration(tmp_path)
    cal = installed_calibration(rig)
    assert cal is not None
    poses = rig_rgb_poses(rig, cal)
    pose = rig.pose_index(7, 3)
    expected = cal.world_from_camera("cam3", float(rig.capture.angles_deg[7]))
    assert np.allclose(poses.centres[pose], expected[:3, 3]) and np.allclose(poses.forward[pose], expected[:3, 2])
    assert np.linalg.norm(poses.centres[pose] - rgb_poses(rig).centres[pose]) > 0.1  # not the nominal pose
    # a depth frame is tagged with the calibrated depth camera pose at its beam angle

    @dataclasses.dataclass
    class Frame:
        camera_id: str = "depth1"
        frame_number: int = 0
        timestamp_s: float = 1.0
        depth: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros((2, 2), np.uint16))
        depth_unit_mm: float = 1.0
        intrinsics: np.ndarray = dataclasses.field(default_factory=lambda: np.eye(3))

    trace = BeamTrace(np.array([0.0, 2.0]), np.array([-100.0, -60.0]))
    posed = tag_frame(Frame(), trace, rig, cal)
    assert np.allclose(posed.camera_to_world, cal.world_from_camera("depth1", -80.0))
    assert np.allclose(posed.camera_to_world, rig_depth_pose(rig.depth_cameras[1], math.radians(-80.0), cal))


def test_a_calibration_for_other_cameras_refuses_the_scan(tmp_path: Path) -> None:
    rig = rig_with_calibration(tmp_path, drop="depth2")
    with pytest.raises(CalibrationRefused) as info:
        asyncio.run(_controller(rig).start_scan("x"))
    assert "no pose for the rig's depth2" in str(info.value) and "calibration.yaml" in str(info.value)


def test_an_old_calibration_warns(tmp_path: Path) -> None:
    rig = rig_with_calibration(tmp_path, created="2020-01-01T00:00:00+00:00")
    controller = _controller(rig)
    calibration = asyncio.run(controller.calibration())
    assert calibration is not None
    warnings = [e for e in controller.machine.history if e.cause == "calibration_old"]
    assert warnings and warnings[0].data["max_age_days"] == 30


def test_the_manifest_digest_covers_the_calibration(tmp_path: Path) -> None:
    rig = rig_with_calibration(tmp_path)
    before = calibration_digest(rig)
    (tmp_path / "calibration.yaml").write_text((tmp_path / "calibration.yaml").read_text() + "\n# edited\n")
    assert calibration_digest(rig) != before


@pytest.mark.slow
def test_a_scan_plans_with_the_calibration_and_keeps_it(tmp_path: Path) -> None:
    from analysis.scan_views import open_scan
    from tests.daemon_rigs import run_scan

    rig = rig_with_calibration(tmp_path)
    report, controller, _ = run_scan(tmp_path / "store", rig=rig)
    assert report.outcome.value == "COMPLETED", report.reason
    manifest = json.loads((report.folder / "manifest.json").read_text())
    assert manifest["files"]["calibration"] == "calibration.yaml"
    assert (report.folder / "calibration.yaml").read_bytes() == (tmp_path / "calibration.yaml").read_bytes()
    assert manifest["calibration_digest"] == calibration_digest(rig)
    events = [json.loads(line) for line in (report.folder / "events.jsonl").read_text().splitlines()]
    started = next(e for e in events if e.get("event") == "scan_started")
    assert started["calibration"] == controller.current.calibration.digest
    # navigation reads the scan's own calibration: poses at the images' actual angles
    scan = open_scan(report.folder, rig_path=rig.path)
    assert scan.calibration is not None and scan.calibration.digest == controller.current.calibration.digest
    image = scan.images[100]
    pose = scan.poses()
    expected = scan.calibration.world_from_camera(image.camera_id, image.actual_angle_deg)
    assert np.allclose(pose.centres[rig.pose_index(image.angle_index, image.camera_index)], expected[:3, 3])


def test_calibrated_plans_keep_the_beam_angles_and_choose_angles_on_calibrated_poses(tmp_path: Path) -> None:
    """The capture fires at beam angles: a plan on calibrated poses captures at the rig's angles
    (not the camera centres' azimuths, which the calibration moves), and per-subject angles are
    chosen and posed with the calibration."""
    from planner.calibration.installed import installed_calibration
    from planner.plan import plan_focus
    from tests.daemon_rigs import capsule_subject

    rig = rig_with_calibration(tmp_path)
    cal = installed_calibration(rig)
    mesh = capsule_subject()
    fixed = plan_focus(mesh, rig, points=600, calibration=cal, methods=("robust",))
    assert np.array_equal(fixed.capture_angles_deg, rig.capture.angles_deg)
    assert np.array_equal(fixed.to_json()["angles_deg"], rig.capture.angles_deg)
    chosen = plan_focus(mesh, rig, points=600, calibration=cal, methods=("robust", "robust-angles"))
    angles = chosen.capture_angles_deg
    posed = chosen.methods["robust-angles"]
    assert posed.angles_deg is not None and np.array_equal(angles, posed.angles_deg)
    # its score is the score of its focus on the calibrated poses at its angles
    from planner.cost import cost_table
    from planner.visibility import RayScene, visible_pairs

    table = cost_table(visible_pairs(RayScene(mesh), rig_rgb_poses(rig, cal, angles), chosen.samples, rig.optics),
                       rig.cost, rig.optics)
    assert table.in_focus_fraction(posed.focus_mm) == pytest.approx(posed.in_focus_fraction, abs=1e-9)
