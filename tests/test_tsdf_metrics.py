"""Shape metrics (Chamfer both ways, coverage) and the recorded-sweep format and CLI."""

from __future__ import annotations

import asyncio
import json

import numpy as np
import pytest
import trimesh
import yaml
from hypothesis import given, settings
from hypothesis import strategies as st

from cli import main as tbp
from drivers.depth.base import DepthFrame
from drivers.depth.recording import RecordingError, load_sweep, load_trace, read_recordings, save_sweep
from drivers.sim.depth import simulate_sweep
from planner.mesh_metrics import shape_metrics, surface_distance
from planner.rig import DEFAULT_RIG_PATH
from tests.depth_helpers import small_rig, sphere

RIG = small_rig(scale=4)


@pytest.fixture
def small_rig_file(tmp_path):
    """The default rig file with quarter-resolution depth images (fast simulated sweeps)."""
    raw = yaml.safe_load(DEFAULT_RIG_PATH.read_text())
    model = raw["depth_camera_model"]
    for key in ("width_px", "height_px"):
        model[key] //= 4
    for key in ("fx_px", "fy_px", "cx_px", "cy_px"):
        model[key] /= 4
    for phone in raw["phones"]:
        phone["focus_calibration"] = str(DEFAULT_RIG_PATH.parent / phone["focus_calibration"])
    path = tmp_path / "rig.yaml"
    path.write_text(yaml.safe_dump(raw))
    return path


def test_identical_meshes_have_zero_chamfer_and_full_coverage():
    ball = sphere(300.0)
    m = shape_metrics(ball, ball, samples=5000)
    assert m.true_to_estimate_mean_mm < 1e-3 and m.estimate_to_true_mean_mm < 1e-3
    assert m.coverage_5mm == 1.0 and m.coverage_10mm == 1.0
    assert m.estimate_within_5mm == 1.0 and m.estimate_off_10mm_cm2 == 0.0


@settings(max_examples=10, deadline=None)
@given(grow=st.floats(1.0, 30.0))
def test_concentric_spheres_are_their_radius_difference_apart(grow):
    inner, outer = sphere(300.0), sphere(300.0 + grow)
    m = shape_metrics(inner, outer, samples=3000)
    # the icosphere's flat facets sit up to ~0.1 mm inside its vertices' sphere
    assert m.true_to_estimate_mean_mm == pytest.approx(grow, abs=0.3)
    assert m.estimate_to_true_mean_mm == pytest.approx(grow, abs=0.3)
    assert m.coverage_10mm == (1.0 if grow < 9.7 else 0.0) or 9.7 <= grow <= 10.3
    assert m.coverage_5mm == (1.0 if grow < 4.7 else 0.0) or 4.7 <= grow <= 5.3
    assert m.estimate_within_5mm == (1.0 if grow < 4.7 else 0.0) or 4.7 <= grow <= 5.3
    off = outer.area / 100 if grow > 10.3 else 0.0
    assert m.estimate_off_10mm_cm2 == pytest.approx(off) or 9.7 <= grow <= 10.3


def test_missing_half_counts_against_true_to_estimate_only():
    ball = sphere(300.0)
    upper = ball.submesh([np.flatnonzero(ball.triangles_center[:, 2] > 1000.0)], append=True)
    m = shape_metrics(ball, upper, samples=20_000)
    assert m.estimate_to_true_mean_mm < 0.2 and m.estimate_within_5mm == 1.0
    assert m.coverage_10mm == pytest.approx(0.5, abs=0.03)
    assert m.true_to_estimate_p95_mm > 200.0


def test_a_bridge_off_the_body_counts_against_the_estimate_only():
    """Webbing: surface spanning between two body parts, off both, is area more than 10 mm off."""
    ball = sphere(300.0)
    bridge = trimesh.creation.box(extents=[100.0, 100.0, 2.0]).apply_translation([0.0, 0.0, 1400.0])
    m = shape_metrics(ball, trimesh.util.concatenate([ball, bridge]), samples=50_000)
    assert m.coverage_5mm == 1.0
    assert m.estimate_off_10mm_cm2 == pytest.approx(bridge.area / 100, rel=0.1)
    assert m.estimate_within_5mm == pytest.approx(ball.area / (ball.area + bridge.area), abs=0.003)


def test_surface_distance_is_exact_for_a_box():
    box = trimesh.creation.box(extents=[100.0, 100.0, 100.0])
    d = surface_distance(np.array([[0.0, 0.0, 80.0], [0.0, 0.0, 0.0]]), box)
    assert d == pytest.approx([30.0, 50.0], abs=1e-4)


def test_a_recorded_sweep_reads_back_identically(tmp_path):
    sweep = simulate_sweep(sphere(), RIG, seed=2, frame_spacing_deg=45.0)
    save_sweep(sweep, tmp_path / "sweep")
    back = load_sweep(tmp_path / "sweep")
    assert len(back.frames) == len(sweep.frames)
    for a, b in zip(sweep.frames, back.frames):
        assert a.camera_id == b.camera_id and a.frame_number == b.frame_number
        assert a.beam_angle_deg == b.beam_angle_deg and a.timestamp_s == b.timestamp_s
        assert np.array_equal(a.depth, b.depth) and b.depth.dtype == np.uint16
        assert np.allclose(a.camera_to_world, b.camera_to_world) and np.allclose(a.intrinsics, b.intrinsics)
    assert np.array_equal(back.trace.angle_deg, sweep.trace.angle_deg)
    assert not list((tmp_path / "sweep").glob("*.tmp"))


def test_a_folder_that_is_not_a_sweep_is_refused(tmp_path):
    with pytest.raises(RecordingError, match="no sweep.json"):
        load_sweep(tmp_path)
    (tmp_path / "sweep.json").write_text(json.dumps({"format": "other/9"}))
    with pytest.raises(RecordingError, match="other/9"):
        load_sweep(tmp_path)
    (tmp_path / "sweep.json").write_text(
        json.dumps({"format": "tbp-depth-sweep/1", "trace": {"time_s": [0, 1], "angle_deg": [0, 1]}, "frames": [{"file": "x.npz"}]})
    )
    with pytest.raises(RecordingError, match="inconsistent"):
        load_sweep(tmp_path)


@pytest.mark.slow
def test_cli_reconstructs_a_simulated_body_and_a_recorded_sweep(tmp_path, capsys, small_rig_file):
    from tests.planner_standin import standin_body

    body = tmp_path / "body.ply"
    standin_body().export(body)
    out, report = tmp_path / "mesh.ply", tmp_path / "report.json"
    frames = tmp_path / "frames"
    code = tbp(
        ["reconstruct", "--sim-body", str(body), "--rig", str(small_rig_file), "--out", str(out),
         "--json", str(report), "--save-frames", str(frames)]
    )
    assert code == 0
    result = json.loads(report.read_text())
    assert result["metrics"]["true_to_estimate_mean_mm"] < 5.0
    assert result["metrics"]["coverage_10mm"] > 0.9
    assert result["vertices"] == len(trimesh.load(out, process=False).vertices)
    assert result["timings_s"]["tsdf_total"] > 0
    capsys.readouterr()
    assert tbp(["reconstruct", "--frames", str(frames), "--true-body", str(body), "--rig", str(small_rig_file)]) == 0
    printed = capsys.readouterr().out
    again = json.loads(printed[0 if printed.startswith("{") else printed.index("\n{") + 1 :])
    assert again["vertices"] == result["vertices"]
    # the scan's mesh.ply is the stored surface, finer than the mesh the plan is made on
    assert result["surface"] == "stored surface" and result["voxel_mm"] == 4.0
    assert tbp(["reconstruct", "--frames", str(frames), "--planner-mesh", "--rig", str(small_rig_file)]) == 0
    printed = capsys.readouterr().out
    planners = json.loads(printed[0 if printed.startswith("{") else printed.index("\n{") + 1 :])
    assert planners["surface"] == "planner's mesh" and planners["voxel_mm"] == 5.0
    assert planners["vertices"] < result["vertices"]


def test_cli_reports_a_refusal_with_exit_code_1(tmp_path, capsys, small_rig_file):
    tiny = tmp_path / "tiny.ply"
    sphere(40.0, centre=(0.0, 0.0, 300.0)).export(tiny)
    assert tbp(["reconstruct", "--sim-body", str(tiny), "--rig", str(small_rig_file)]) == 1
    assert "no subject" in capsys.readouterr().err


class _Recording:
    """A finite DepthCamera (like a bag playback): frames at 30 fps from t0, then the stream ends."""

    def __init__(self, camera_id: str, count: int, t0: float) -> None:
        self.id, self.count, self.t0 = camera_id, count, t0
        self.started = self.stopped = False

    async def start(self) -> None:
        self.started = True

    async def stop(self) -> None:
        self.stopped = True

    async def frames(self):
        for k in range(self.count):
            yield DepthFrame(self.id, k, self.t0 + k / 30.0, 0.0, np.ones((4, 4), dtype=np.uint16), 1.0, np.eye(3))


def test_recordings_are_tagged_on_their_own_time_axis_and_thinned(tmp_path):
    trace_file = tmp_path / "trace.json"
    trace_file.write_text(json.dumps({"time_s": [0.0, 2.0], "angle_deg": [0.0, 60.0]}))
    trace = load_trace(trace_file)
    cameras = [_Recording("depth0", 90, t0=1000.0), _Recording("depth2", 30, t0=5.0)]
    sweep = asyncio.run(read_recordings(cameras, trace, RIG, spacing_deg=6.0))
    depth0 = [f for f in sweep.frames if f.camera_id == "depth0"]
    # 2 s of trace at 1 deg per frame, one frame per 6 deg; frames after the trace are skipped
    assert [f.beam_angle_deg for f in depth0] == pytest.approx([0, 6, 12, 18, 24, 30, 36, 42, 48, 54, 60])
    assert len([f for f in sweep.frames if f.camera_id == "depth2"]) == 5
    assert all(c.started and c.stopped for c in cameras)


def test_a_malformed_trace_file_is_refused(tmp_path):
    path = tmp_path / "trace.json"
    path.write_text(json.dumps({"time_s": [0.0]}))
    with pytest.raises(RecordingError, match="not a beam trace"):
        load_trace(path)
