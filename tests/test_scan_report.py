"""The scan QA report and image navigation on a small simulated scan."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from analysis.navigate import NavigationError, navigate
from analysis.qa_report import generate_report
from analysis.scan_views import open_scan
from cli import main
from daemon.manifest import ManifestError
from planner.visibility import RayScene
from sim.run import run_sim_scan
from tests.daemon_rigs import PLAN_POINTS, capsule_subject


@pytest.fixture(scope="module")
def scan_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    store = tmp_path_factory.mktemp("store")
    report = run_sim_scan(store=store, seed=1, plan_points=PLAN_POINTS, depth_decimation=4,
                          subject=capsule_subject(), panel=False, qa_report=generate_report)
    return Path(report.folder)


def test_the_daemon_writes_the_report_at_the_end_of_a_scan(scan_dir):
    page = scan_dir / "report" / "index.html"
    text = page.read_text()
    for figure in ("body.png", "focus.png", "speed.png", "angles.png", "resolution.png"):
        assert figure in text and (scan_dir / "report" / figure).stat().st_size > 1000
    assert "every planned image is on disk and verified" in text


def test_tbp_report_regenerates_and_lists_missing_images(scan_dir, tmp_path):
    copy = tmp_path / scan_dir.name
    shutil.copytree(scan_dir, copy)
    shutil.rmtree(copy / "report")
    manifest = json.loads((copy / "manifest.json").read_text())
    lost = manifest["images"][17]
    lost["status"], lost["error"] = "missing", "PhoneDisconnected: cam3 vanished"
    (copy / "manifest.json").write_text(json.dumps(manifest))
    assert main(["report", str(copy)]) == 0
    text = (copy / "report" / "index.html").read_text()
    assert "PhoneDisconnected: cam3 vanished" in text
    assert f"<td>{lost['camera_id']}</td>" in text


def test_navigation_answers_an_image_whose_pose_sees_the_point(scan_dir):
    scan = open_scan(scan_dir)
    mesh = scan.mesh()
    vertex = int(np.argmax(mesh.vertices[:, 0]))  # the front of the body
    answer = navigate(scan_dir, vertex=vertex, count=3)
    assert 1 <= len(answer["views"]) <= 3
    best = answer["views"][0]
    assert (scan_dir / best["file"]).exists()
    poses = scan.poses()
    point = np.array(answer["point_mm"])
    u, v, depth = poses.project(point[None, :], best["pose"], scan.rig.optics.focal_length_px,
                                scan.rig.optics.image_width_px / 2, scan.rig.optics.image_height_px / 2)[0]
    assert depth > 0
    assert 0 <= u < scan.rig.optics.image_width_px and 0 <= v < scan.rig.optics.image_height_px
    assert (u, v) == pytest.approx((best["u_px"], best["v_px"]), abs=1e-3)
    occluded = RayScene(mesh).occluded(poses.centres[[best["pose"]]], point[None, :], 1.0)
    assert not occluded[0]
    costs = [view["cost"] for view in answer["views"]]
    assert costs == sorted(costs)


def test_navigation_refuses_what_is_not_a_point_on_the_body(scan_dir, tmp_path, capsys):
    with pytest.raises(NavigationError, match="three numbers"):
        navigate(scan_dir, point="1,2")
    with pytest.raises(NavigationError, match="vertices 0.."):
        navigate(scan_dir, vertex=10**9)
    with pytest.raises(ManifestError, match="manifest.json"):
        generate_report(tmp_path)
    assert main(["navigate", str(tmp_path), "--vertex", "0"]) == 2
    assert "manifest.json" in capsys.readouterr().err
