"""Depth sweep: beam-angle tagging from the motor trace, refusals, frame selection, the async recorder."""

from __future__ import annotations

import asyncio
import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from drivers.depth.base import DepthFrame
from drivers.depth.errors import DepthStreamStalled
from drivers.motor.samples import BeamSample
from drivers.depth.sweep import SweepCollector, collect_sweep
from drivers.sim.depth import DepthFaults, SimulatedDepthCamera
from planner.poses import depth_camera_pose
from planner.shape_errors import BadTrace, FrameOutsideTrace, UnknownDepthCamera
from planner.sweep import BeamTrace, observed, select_by_spacing, tag_frame, tag_frames
from sim.clock import run_virtual
from tests.depth_helpers import small_rig, sphere

RIG = small_rig(scale=8)
MODEL = RIG.depth_camera_model


def _frame(t: float, camera_id: str = "depth0", n: int = 0, depth: np.ndarray | None = None) -> DepthFrame:
    depth = np.ones((4, 4), dtype=np.uint16) if depth is None else depth
    return DepthFrame(camera_id, n, t, 0.0, depth, 1.0, MODEL.intrinsic_matrix)


def _sample(time_s: float, angle_deg: float) -> BeamSample:
    return BeamSample(time_s, angle_deg, 0.0, 0x27)


@settings(max_examples=50, deadline=None)
@given(
    steps=st.lists(st.floats(0.001, 1.0), min_size=1, max_size=20),
    speeds=st.lists(st.floats(-50.0, 50.0), min_size=20, max_size=20),
    where=st.floats(0.0, 1.0),
)
def test_angle_is_linear_between_trace_samples(steps, speeds, where):
    t = np.concatenate([[10.0], 10.0 + np.cumsum(steps)])
    a = np.concatenate([[5.0], 5.0 + np.cumsum(np.array(steps) * speeds[: len(steps)])])
    trace = BeamTrace(t, a)
    assert np.allclose(trace.angle_at(t), a)
    i = min(int(where * (len(t) - 1)), len(t) - 2)
    tq = t[i] + where * (t[i + 1] - t[i])
    expected = a[i] + (a[i + 1] - a[i]) * (tq - t[i]) / (t[i + 1] - t[i])
    assert float(trace.angle_at(tq)) == pytest.approx(expected, abs=1e-9)


def test_frame_gets_the_interpolated_angle_and_the_pose_at_that_angle():
    trace = BeamTrace(np.array([0.0, 1.0, 2.0]), np.array([0.0, 30.0, 90.0]))
    posed = tag_frame(_frame(1.5, "depth2"), trace, RIG)
    assert posed.beam_angle_deg == pytest.approx(60.0)
    camera = RIG.depth_cameras[2]
    assert np.allclose(posed.camera_to_world, depth_camera_pose(camera, math.radians(60.0)))
    # the pose is the beam rotation applied to the camera's pose at beam angle 0
    c, s = math.cos(math.radians(60.0)), math.sin(math.radians(60.0))
    rz = np.array([[c, -s, 0, 0], [s, c, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]])
    assert np.allclose(posed.camera_to_world, rz @ depth_camera_pose(camera, 0.0))


@pytest.mark.parametrize("t", [-0.001, 2.0001, 100.0])
def test_frames_outside_the_trace_are_refused(t):
    trace = BeamTrace(np.array([0.0, 2.0]), np.array([0.0, 60.0]))
    with pytest.raises(FrameOutsideTrace) as err:
        tag_frames([_frame(1.0), _frame(t, "depth1", 7)], trace, RIG)
    assert err.value.camera_id == "depth1" and err.value.frame_number == 7
    assert "depth1" in str(err.value) and "outside the beam trace" in str(err.value)


def test_unknown_camera_is_refused():
    trace = BeamTrace(np.array([0.0, 2.0]), np.array([0.0, 60.0]))
    with pytest.raises(UnknownDepthCamera, match="depth9"):
        tag_frame(_frame(1.0, "depth9"), trace, RIG)


@pytest.mark.parametrize(
    "times, angles, problem",
    [
        ([0.0], [0.0], "at least 2"),
        ([0.0, 1.0, 1.0], [0.0, 1.0, 2.0], "must increase"),
        ([0.0, 1.0], [0.0, float("nan")], "non-finite"),
        ([0.0, 1.0], [0.0], "equal-length"),
    ],
)
def test_bad_traces_are_refused(times, angles, problem):
    with pytest.raises(BadTrace, match=problem):
        BeamTrace(np.array(times), np.array(angles))


def test_trace_from_motor_samples_sorts_and_drops_duplicate_times():
    trace = BeamTrace.from_samples([_sample(1.0, 10.0), _sample(0.0, 0.0), _sample(1.0, 10.0)])
    assert list(trace.time_s) == [0.0, 1.0]


def test_selection_keeps_frames_a_fixed_angle_apart_and_skips_empty_ones():
    trace = BeamTrace(np.array([0.0, 10.0]), np.array([0.0, 100.0]))
    frames = [_frame(k * 0.1, "depth0", k) for k in range(40)]
    empty = _frame(0.05, "depth0", 99, np.zeros((4, 4), dtype=np.uint16))
    posed = tag_frames(frames + [empty], trace, RIG).frames
    kept = select_by_spacing(posed, 3.0)
    assert [f.frame_number for f in kept] == list(range(0, 40, 3))


def _sim_camera(index: int, angle, faults: DepthFaults | None = None) -> SimulatedDepthCamera:
    return SimulatedDepthCamera(RIG.depth_cameras[index], MODEL, sphere(), angle, seed=index, faults=faults)


def _sweep_parts(duration: float, speed: float = 30.0):
    """A simulated beam: samples at 100 Hz from t=0.1 s and a motion that ends at the duration."""
    loop_start: list[float] = []

    def angle(t: float) -> float:
        return speed * t

    async def samples():
        loop = asyncio.get_running_loop()
        loop_start.append(loop.time())
        k = 10
        while True:
            await asyncio.sleep(max(0.0, k * 0.01 - loop.time()))
            yield _sample(loop.time(), angle(loop.time()))
            k += 1

    async def motion() -> None:
        await asyncio.sleep(duration)

    return angle, samples, motion


def test_collect_sweep_tags_every_frame_inside_the_trace():
    angle, samples, motion = _sweep_parts(1.0)
    cameras = [_sim_camera(i, angle) for i in range(3)]
    sweep = run_virtual(collect_sweep(cameras, motion(), samples(), RIG, spacing_deg=0.0))
    per_camera = sweep.per_camera()
    # 30 fps for 1 s; frames before the first beam sample (t < 0.1 s) are left out
    assert all(27 <= n <= 28 for n in per_camera.values()), per_camera
    for f in sweep.frames:
        assert f.beam_angle_deg == pytest.approx(angle(f.timestamp_s), abs=1e-6)
        assert sweep.trace.covers(f.timestamp_s)


def test_frames_are_thinned_to_the_spacing_as_they_arrive():
    angle, samples, motion = _sweep_parts(2.0)
    collector = SweepCollector([_sim_camera(0, angle), _sim_camera(2, angle)], RIG, spacing_deg=6.0)
    sweep = run_virtual(collector.run(motion(), samples()))
    assert collector.received["depth0"] >= 59
    for camera_id in ("depth0", "depth2"):
        angles = [f.beam_angle_deg for f in sweep.frames if f.camera_id == camera_id]
        assert len(angles) == 10, angles  # 3 .. 57 deg in 6 deg steps
        assert np.all(np.diff(angles) >= 6.0 - 1e-6)


def test_a_stalled_camera_stops_the_sweep_with_a_typed_error():
    angle, samples, motion = _sweep_parts(5.0)
    stalled = _sim_camera(1, angle, DepthFaults(stop_after_frame=4))
    cameras = [_sim_camera(0, angle), stalled]

    class Collector(SweepCollector):
        FRAME_TIMEOUT_S = 0.2

    with pytest.raises(DepthStreamStalled) as err:
        run_virtual(Collector(cameras, RIG).run(motion(), samples()))
    assert err.value.camera_id == "depth1" and err.value.frames == 5
    assert "depth1" in str(err.value) and "0.20 s" in str(err.value)


def test_dropped_frames_leave_gaps_but_the_sweep_completes():
    angle, samples, motion = _sweep_parts(1.0)
    cameras = [_sim_camera(0, angle, DepthFaults(drop_frames=set(range(10, 20)))), _sim_camera(1, angle)]
    sweep = run_virtual(collect_sweep(cameras, motion(), samples(), RIG, spacing_deg=0.0))
    counts = sweep.per_camera()
    assert counts["depth1"] - counts["depth0"] == 10
    numbers = [f.frame_number for f in sweep.frames if f.camera_id == "depth0"]
    assert not set(range(10, 20)) & set(numbers)


def test_a_failing_motion_stops_the_cameras_and_raises():
    angle, samples, _ = _sweep_parts(1.0)
    cameras = [_sim_camera(0, angle)]

    async def motion() -> None:
        await asyncio.sleep(0.3)
        raise RuntimeError("drive fault")

    with pytest.raises(RuntimeError, match="drive fault"):
        run_virtual(collect_sweep(cameras, motion(), samples(), RIG))
    assert cameras[0]._t0 is None


def test_observed_counts_only_points_a_frame_measured():
    angle, samples, motion = _sweep_parts(1.0)
    sweep = run_virtual(collect_sweep([_sim_camera(2, angle)], motion(), samples(), RIG))
    ball = sphere()
    on_surface = ball.vertices[::50]
    seen = observed(on_surface, sweep.frames)
    assert 0.1 < seen.mean() < 0.9
    inside = (on_surface - [0, 0, 1000.0]) * 0.5 + [0, 0, 1000.0]
    assert not observed(inside, sweep.frames).any()


def test_a_camera_that_fails_to_start_never_moves_the_beam():
    angle, samples, _ = _sweep_parts(1.0)
    moved: list[bool] = []

    async def motion() -> None:
        moved.append(True)

    class Broken(SimulatedDepthCamera):
        async def start(self) -> None:
            raise DepthStreamStalled(self.id, 0, None)

    cameras = [_sim_camera(0, angle), Broken(RIG.depth_cameras[1], MODEL, sphere(), angle)]
    with pytest.raises(DepthStreamStalled, match="depth1"):
        run_virtual(collect_sweep(cameras, motion(), samples(), RIG))
    assert moved == []
    assert cameras[0]._t0 is None
