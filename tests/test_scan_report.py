"""The scan QA report and image navigation on a small simulated scan."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from analysis.navigate import NavigationError, navigate
from analysis.qa_report import generate_report
from analysis.scan_views import open_scan
from analysis.skin_map import BLURRED, SHARP, payload_shares, read_skin_mesh, read_skin_shares, skin_shares
from cli import main
from daemon.records.manifest import ManifestError, ScanEnd
from daemon.records.store import read_folder
from planner.visibility import RayScene


@pytest.fixture
def scan_dir(web_store: Path) -> Path:
    """The session's simulated scan (tests/conftest.py), read only: tests that write use a copy."""
    return next(p for p in web_store.iterdir() if p.is_dir())


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


def test_sharp_skin_is_one_measure_in_the_report_the_viewer_and_the_list(scan_dir, capsys):
    """The report's headline, the shares it stores for the lists, and the shares of the mesh the
    viewer colours are one number: the area-weighted per-vertex map."""
    shares = read_skin_shares(scan_dir)
    assert shares is not None and 0.5 < shares["sharp"] < 1.0
    assert sum(shares.values()) == pytest.approx(1.0)
    assert payload_shares(read_skin_mesh(open_scan(scan_dir))) == shares
    text = (scan_dir / "report" / "index.html").read_text()
    assert f"Sharp skin: <b>{100 * shares['sharp']:.1f} %</b>" in text
    assert main(["scans", "--store", str(scan_dir.parent)]) == 0
    assert f"{100 * shares['sharp']:.1f} %" in capsys.readouterr().out


def _grid(x0: float, width: float, height: float, n: int) -> tuple[np.ndarray, np.ndarray]:
    """A width x height rectangle at x0 in the z = 0 plane, n x n cells of two triangles."""
    xs, ys = np.meshgrid(np.linspace(x0, x0 + width, n + 1), np.linspace(0.0, height, n + 1), indexing="ij")
    vertices = np.column_stack([xs.ravel(), ys.ravel(), np.zeros(xs.size)])
    index = np.arange((n + 1) ** 2).reshape(n + 1, n + 1)
    a, b, c, d = index[:-1, :-1].ravel(), index[1:, :-1].ravel(), index[1:, 1:].ravel(), index[:-1, 1:].ravel()
    return vertices, np.concatenate([np.column_stack([a, b, c]), np.column_stack([a, c, d])])


@settings(max_examples=60, deadline=None)
@given(st.floats(1.0, 500.0), st.floats(1.0, 500.0), st.floats(1.0, 500.0), st.floats(1.0, 500.0),
       st.integers(1, 30), st.integers(1, 30))
def test_skin_shares_are_shares_of_area_whatever_the_triangle_density(w1, h1, w2, h2, n1, n2):
    """Two patches, one sharp and one blurred, meshed as finely or coarsely as may be: the
    shares are their areas' (a count of vertices would follow the meshing instead)."""
    v1, f1 = _grid(0.0, w1, h1, n1)
    v2, f2 = _grid(w1 + 10.0, w2, h2, n2)
    vertices, faces = np.vstack([v1, v2]), np.vstack([f1, f2 + len(v1)])
    status = np.r_[np.full(len(v1), SHARP), np.full(len(v2), BLURRED)].astype(np.uint8)
    shares = skin_shares(vertices, faces, status)
    total = w1 * h1 + w2 * h2
    assert shares["sharp"] == pytest.approx(w1 * h1 / total, rel=1e-9)
    assert shares["blurred"] == pytest.approx(w2 * h2 / total, rel=1e-9) and shares["unseen"] == 0.0


def test_a_partial_scan_says_so_first_with_its_missing_images_per_phone(scan_dir, tmp_path):
    copy = tmp_path / scan_dir.name
    shutil.copytree(scan_dir, copy)
    folder = read_folder(copy)
    for angle in range(10, 20):
        folder.update_image(2, angle, save=False, status="missing", missing_reason="phone_dropped",
                            error="PhoneDropped: cam2 dropped")
    folder.finish(ScanEnd.COMPLETE)  # asked complete, closed partial
    assert main(["report", str(copy)]) == 0
    text = (copy / "report" / "index.html").read_text()
    assert ": partial</h1>" in text
    banner = text[text.index("id='ended'"):text.index("<p>Images:")]
    assert "Partial scan" in banner and "10 of 336 images missing" in banner
    assert "<tr><td>cam2</td><td>10</td><td>10 phone dropped</td></tr>" in banner
    assert "<td>missing</td><td>phone dropped</td><td>PhoneDropped: cam2 dropped</td>" in text
    assert "id='ended'" not in (scan_dir / "report" / "index.html").read_text()  # a complete scan: no banner


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


def _front_vertex(scan_dir: Path) -> int:
    return int(np.argmax(open_scan(scan_dir).mesh().vertices[:, 0]))


def test_navigation_never_names_a_deleted_image(scan_dir, tmp_path, capsys):
    copy = tmp_path / scan_dir.name
    shutil.copytree(scan_dir, copy)
    vertex = _front_vertex(copy)
    best = navigate(copy, vertex=vertex, count=3)["views"][0]
    (copy / best["file"]).unlink()
    answer = navigate(copy, vertex=vertex, count=3)
    assert best["file"] not in [v["file"] for v in answer["views"]] and answer["views"]
    assert answer["missing_files"] == [best["file"]]
    assert main(["navigate", str(copy), "--vertex", str(vertex)]) == 0
    out, err = capsys.readouterr()
    assert best["file"] not in out and "1 verified image(s) are no longer on disk" in err


@pytest.mark.parametrize("tamper, problem", [
    (lambda m: m["images"][3].update(camera_index="three"), 'images[3].camera_index: "three" is not a valid'),
    (lambda m: m["images"][3].update(camera_index=99), "images[3]: camera 99, angle 0 outside this rig"),
    (lambda m: m["images"][5].update(actual_angle_deg="north"), "images[5].actual_angle_deg"),
    (lambda m: m["images"][5].update(file="../../../etc/passwd"), "is not a file inside the scan folder"),
    (lambda m: m["images"][5].update(status="lost"), "not a valid manifest"),
    (lambda m: m["images"][5].update(missing_reason="lost in space"), "not a valid manifest"),
    (lambda m: m["images"].__setitem__(2, "nothing"), "images[2]: not an object"),
    (lambda m: m.update(images={"a": 1}), "images: "),
    (lambda m: m.update(files={"mesh": "/etc/hostname"}), "files.mesh"),
    (lambda m: m.update(cameras="cam0"), "cameras: "),
    (lambda m: m.clear(), "format_version null"),
])
def test_a_tampered_manifest_is_one_line_from_navigate_and_report(scan_dir, tmp_path, capsys, tamper, problem):
    copy = tmp_path / scan_dir.name
    shutil.copytree(scan_dir, copy)
    manifest = json.loads((copy / "manifest.json").read_text())
    tamper(manifest)
    (copy / "manifest.json").write_text(json.dumps(manifest))
    for command in (["navigate", str(copy), "--vertex", "0"], ["report", str(copy)], ["scans", "--store", str(tmp_path)]):
        code = main(command)
        err = capsys.readouterr()
        assert "Traceback" not in err.err
        if command[0] == "scans":  # no rig at hand: it checks the manifest's own consistency
            in_range = problem.startswith("images[3]: camera 99")
            assert (code, "UNREADABLE" in err.out) == ((0, False) if in_range else (1, True)), err
        else:
            assert code == 2, err
            assert len(err.err.strip().splitlines()) == 1 and problem in err.err


@pytest.mark.parametrize("raw", [b"[1, 2]", b"[" * 50_000 + b"]" * 50_000, b"\xff\xfe", b""])
def test_a_manifest_that_is_not_one_is_a_typed_error(tmp_path, raw, capsys):
    folder = tmp_path / "20260101-000000-x"
    folder.mkdir()
    (folder / "manifest.json").write_bytes(raw)
    with pytest.raises(ManifestError):
        open_scan(folder)
    assert main(["report", str(folder)]) == 2
    assert "Traceback" not in capsys.readouterr().err


@pytest.mark.parametrize("rig_text, problem", [
    ("phones: [1, 2\n", "not valid YAML"),
    ("a: b\n", "a: unknown key"),
    (None, "cannot read"),
])
def test_a_broken_rig_file_is_one_named_error_from_every_command_that_reads_a_scan(scan_dir, tmp_path, capsys,
                                                                                   rig_text, problem):
    rig = tmp_path / "rig.yaml"
    if rig_text is not None:
        rig.write_text(rig_text)
    for command in (["navigate", str(scan_dir), "--vertex", "0"], ["report", str(scan_dir)], ["texture", str(scan_dir)],
                    ["export", str(scan_dir), "--out", str(tmp_path / "dicom")]):
        assert main([*command, "--rig", str(rig)]) == 2, command
        err = capsys.readouterr().err
        assert "Traceback" not in err and f"tbp {command[0]}: {rig}: " in err and problem in err, (command, err)
