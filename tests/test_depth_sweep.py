"""Depth sweep: beam-angle tagging from the motor trace, refusals, frame selection, and the daemon's
sweep (daemon/jobs/depth_sweep.py) with simulated cameras and recordings on a mock beam, in virtual time."""

from __future__ import annotations

import asyncio
import dataclasses
import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from daemon.errors import SweepFailed
from daemon.jobs.depth_sweep import DepthSweeper, SweepRecord
from daemon.rig.beam import BeamTracker
from drivers.depth.base import DepthFrame
from drivers.depth.errors import DepthCameraError, DepthStreamStalled
from drivers.motor.samples import BeamSample
from drivers.sim.depth import DepthFaults, SimulatedDepthCamera
from planner.poses import depth_camera_pose
from planner.shape_errors import BadTrace, FrameOutsideTrace, UnknownDepthCamera
from planner.sweep import BeamTrace, observed, tag_frame, tag_frames
from planner.tsdf import FRAME_SPACING_DEG, TsdfFusion
from sim.clock import run_virtual
from tests.daemon_mocks import MockDrive
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


def test_fusion_keeps_frames_a_fixed_angle_apart_and_skips_empty_ones():
    trace = BeamTrace(np.array([0.0, 10.0]), np.array([0.0, 100.0]))
    frames = tag_frames([_frame(k * 0.1, "depth0", k) for k in range(40)], trace, RIG).frames
    empty = tag_frames([_frame(0.0, "depth0", 99, np.zeros((4, 4), dtype=np.uint16))], trace, RIG).frames
    fusion = TsdfFusion(RIG)
    assert fusion.add(empty) == 0  # an empty frame does not take the place of the next one
    assert fusion.add(frames) == len(range(0, 40, int(FRAME_SPACING_DEG)))  # 1 deg between frames
    assert fusion.per_camera == {"depth0": 5} and fusion.offered == 41


# ---------------------------------------------------------------------- the daemon's sweep

SHORT = dataclasses.replace(RIG, depth_sweep=dataclasses.replace(RIG.depth_sweep, end_deg=RIG.depth_sweep.start_deg + 60.0))


SWEEP_MODEL = dataclasses.replace(MODEL, fps=10.0)  # 3 deg between frames at 30 deg/s


class Sweeper(DepthSweeper):
    SPACING_DEG = 2.0
    FRAME_TIMEOUT_S = 0.2


class Recording:
    """A finite DepthCamera (a sweep recording played back): frames with recorded angles, then the end."""

    def __init__(self, camera_id: str, angles: list[float], *, fail_stop: bool = False) -> None:
        self.id, self.angles, self.fail_stop = camera_id, angles, fail_stop
        self.started = self.stopped = 0

    async def start(self) -> None:
        self.started += 1

    async def stop(self) -> None:
        self.stopped += 1
        if self.fail_stop:
            raise DepthCameraError(self.id, "did not stop within 5.0 s")

    async def frames(self):
        for k, angle in enumerate(self.angles):
            await asyncio.sleep(0.01)
            yield DepthFrame(self.id, k, -1000.0 + k, 0.0, np.full((4, 4), 900, np.uint16), 1.0, MODEL.intrinsic_matrix,
                             beam_angle_deg=angle)


def _beam() -> MockDrive:
    return MockDrive(max_accel=RIG.motor.max_acceleration_deg_s2)


def _true_angle(drive: MockDrive):
    return lambda t: drive.trajectory.at(t)[0] + drive.offset


def _sim_camera(index: int, drive: MockDrive, faults: DepthFaults | None = None, rig=SHORT) -> SimulatedDepthCamera:
    return SimulatedDepthCamera(rig.depth_cameras[index], SWEEP_MODEL, sphere(), _true_angle(drive), seed=index,
                                faults=faults)


async def _sweep(drive: MockDrive, cameras, *, rig=SHORT, sweeper=Sweeper, sink=None) -> SweepRecord:
    await drive.connect()
    await drive.set_zero(rig.depth_sweep.start_deg)
    tracker = BeamTracker()
    await tracker.start(drive)
    try:
        return await sweeper(rig, drive, tracker, cameras, sink=sink).run()
    finally:
        await tracker.stop()
        await drive.close()


def _moves(drive: MockDrive) -> list[tuple[float, ...]]:
    return [args for name, args in drive.calls if name == "move_to"]


def test_every_frame_is_posed_at_the_encoder_angle_of_its_time():
    drive = _beam()
    cameras = [_sim_camera(i, drive) for i in range(3)]
    record = run_virtual(_sweep(drive, cameras))
    s = SHORT.depth_sweep
    assert _moves(drive) == [(s.end_deg, s.speed_deg_s, SHORT.motor.max_acceleration_deg_s2)]
    assert record.angle_source == {"depth0": "encoder", "depth1": "encoder", "depth2": "encoder"}
    truth = _true_angle(drive)
    for camera in SHORT.depth_cameras:
        frames = [f for f in record.sweep.frames if f.camera_id == camera.id]
        angles = np.array([f.beam_angle_deg for f in frames])
        assert np.all(np.diff(angles) >= 2.0 - 1e-6)  # thinned to the spacing
        assert np.all(np.diff(angles) <= 3.0 + 0.05)  # no 10 fps frame of the cruise left out
        assert angles[0] < s.start_deg + 1.0 and angles[-1] > s.end_deg - 3.0
        for f in frames:
            assert f.beam_angle_deg == pytest.approx(truth(f.timestamp_s), abs=0.02)
            np.testing.assert_allclose(f.camera_to_world, depth_camera_pose(camera, math.radians(f.beam_angle_deg)))
    assert record.trace[-1, 1] == pytest.approx(s.end_deg)
    assert all(c._t0 is None for c in cameras)  # stopped
    assert record.frames_seen["depth0"] >= 25  # 10 fps for 2.5 s


def test_a_camera_that_fails_to_start_stops_the_one_already_streaming_and_the_beam_never_moves():
    drive = _beam()

    class Unplugged(SimulatedDepthCamera):
        async def start(self) -> None:
            raise DepthCameraError(self.id, "no RealSense device with serial '000000000002'")

    cameras = [_sim_camera(0, drive), Unplugged(SHORT.depth_cameras[1], SWEEP_MODEL, sphere(), _true_angle(drive)),
               _sim_camera(2, drive)]
    with pytest.raises(DepthCameraError, match="depth1: no RealSense device"):
        run_virtual(_sweep(drive, cameras))
    assert cameras[0]._t0 is None  # was streaming, now stopped
    assert cameras[2]._t0 is None  # never started
    assert _moves(drive) == []


def test_a_camera_stalling_mid_sweep_ends_it_with_a_typed_error_and_every_camera_stopped():
    drive = _beam()
    cameras = [_sim_camera(0, drive), _sim_camera(1, drive, DepthFaults(stop_after_frame=14)), _sim_camera(2, drive)]
    ended: list[float] = []

    async def main() -> None:
        try:
            await _sweep(drive, cameras)
        finally:
            ended.append(asyncio.get_running_loop().time())

    with pytest.raises(DepthStreamStalled) as err:
        run_virtual(main())
    assert err.value.camera_id == "depth1" and err.value.frames == 15
    assert "depth1" in str(err.value) and "0.20 s" in str(err.value)
    assert ended[0] < 15 / 10 + 0.2 + 0.1  # right after the stall, long before the beam arrives
    assert all(c._t0 is None for c in cameras)


def test_a_drive_error_ends_the_sweep_with_every_camera_stopped():
    class FaultyDrive(MockDrive):
        async def move_to(self, angle_deg: float, speed_deg_s: float, acceleration_deg_s2: float) -> None:
            await asyncio.sleep(0.3)
            raise RuntimeError("drive fault 0x7500")

    drive = FaultyDrive()
    cameras = [_sim_camera(0, drive), _sim_camera(2, drive)]
    with pytest.raises(RuntimeError, match="drive fault 0x7500"):
        run_virtual(_sweep(drive, cameras))
    assert all(c._t0 is None for c in cameras)


def test_a_second_stop_while_the_sweep_unwinds_still_stops_every_camera():
    """The drive's error ends the sweep and, while its cameras are being stopped (each stop takes a
    while, as the SDK's does), the job is stopped too: the cameras are stopped all the same, and the
    stop reaches the caller once they are."""

    class SlowStop(SimulatedDepthCamera):
        async def stop(self) -> None:
            await asyncio.sleep(0.2)
            await super().stop()

    class FaultyDrive(MockDrive):
        async def move_to(self, angle_deg: float, speed_deg_s: float, acceleration_deg_s2: float) -> None:
            await asyncio.sleep(0.3)
            raise RuntimeError("drive fault 0x2310")

    drive = FaultyDrive()
    cameras = [SlowStop(SHORT.depth_cameras[i], SWEEP_MODEL, sphere(), _true_angle(drive), seed=i) for i in range(3)]

    async def main() -> float:
        loop = asyncio.get_running_loop()
        sweep = asyncio.create_task(_sweep(drive, cameras))
        await asyncio.sleep(0.35)  # the drive failed; the first camera is stopping
        sweep.cancel()
        await asyncio.sleep(0.05)
        sweep.cancel()  # and once more
        with pytest.raises(asyncio.CancelledError):
            await sweep
        return loop.time()

    ended = run_virtual(main())
    assert all(c._t0 is None for c in cameras)
    assert ended >= 0.3 + 3 * 0.2 - 1e-6  # the cancel came after the last camera's stop


def test_a_camera_with_too_few_usable_frames_fails_the_sweep():
    drive = _beam()
    cameras = [_sim_camera(0, drive), _sim_camera(1, drive, DepthFaults(empty_frames=set(range(4, 10_000))))]
    with pytest.raises(SweepFailed) as err:
        run_virtual(_sweep(drive, cameras))
    assert err.value.camera == "depth1" and 1 <= err.value.frames <= 4 and err.value.needed == 8
    assert "depth1" in str(err.value) and "needed 8" in str(err.value)


def test_a_recording_is_posed_at_its_recorded_angles_and_may_end_before_the_beam():
    drive = _beam()
    recorded = [-227.0 + 0.5 * k for k in range(100)]  # 50 deg, faster than the beam
    recording = Recording("depth2", recorded)
    record = run_virtual(_sweep(drive, [recording, _sim_camera(0, drive)]))
    assert record.angle_source == {"depth2": "recording", "depth0": "encoder"}
    posed = [f for f in record.sweep.frames if f.camera_id == "depth2"]
    assert [f.beam_angle_deg for f in posed] == recorded[::4]  # one per 2 deg, not the encoder's angle
    for f in posed:
        np.testing.assert_allclose(f.camera_to_world,
                                   depth_camera_pose(SHORT.depth_cameras[2], math.radians(f.beam_angle_deg)))
    assert recording.started == 1 and recording.stopped == 1
    assert record.frames_seen["depth2"] == 100


def test_a_camera_that_fails_to_stop_is_named_once_the_others_are_stopped():
    drive = _beam()
    stuck = Recording("depth1", [-227.0 + 2.0 * k for k in range(20)], fail_stop=True)
    camera = _sim_camera(0, drive)
    with pytest.raises(DepthCameraError, match="depth1: did not stop within 5.0 s"):
        run_virtual(_sweep(drive, [stuck, camera]))
    assert camera._t0 is None

    drive = _beam()
    stuck = Recording("depth1", [-227.0 + 2.0 * k for k in range(20)], fail_stop=True)
    stalled = _sim_camera(0, drive, DepthFaults(stop_after_frame=3))
    with pytest.raises(DepthStreamStalled) as err:  # the sweep's own error stays the one raised
        run_virtual(_sweep(drive, [stuck, stalled]))
    assert any("depth1: did not stop" in note for note in err.value.__notes__)


def test_observed_counts_only_points_a_frame_measured():
    drive = _beam()
    record = run_virtual(_sweep(drive, [_sim_camera(2, drive)]))
    ball = sphere()
    on_surface = ball.vertices[::50]
    seen = observed(on_surface, record.sweep.frames)
    assert 0.1 < seen.mean() < 0.9
    inside = (on_surface - [0, 0, 1000.0]) * 0.5 + [0, 0, 1000.0]
    assert not observed(inside, record.sweep.frames).any()


def test_frames_go_to_the_sink_while_the_beam_turns_each_once_in_time_order() -> None:
    drive = _beam()
    batches: list[tuple[float, float, list]] = []

    async def sink(frames: list) -> None:
        loop = asyncio.get_running_loop()
        batches.append((loop.time(), drive.trajectory.at(loop.time())[1], frames))

    cameras = [_sim_camera(i, drive) for i in range(len(SHORT.depth_cameras))]
    record = run_virtual(_sweep(drive, cameras, sink=sink))
    fed = [f for _, _, frames in batches for f in frames]
    assert len(batches) >= 3 and all(speed > 0 for _, speed, _ in batches)  # during the motion
    assert len(fed) > len(record.unfed)  # most frames were fused before the beam stopped
    ids = lambda frames: [(f.camera_id, f.frame_number) for f in frames]  # noqa: E731
    assert sorted(ids(fed) + ids(record.unfed)) == sorted(ids(record.sweep.frames))
    for camera in {f.camera_id for f in record.sweep.frames}:
        times = [f.timestamp_s for f in fed + list(record.unfed) if f.camera_id == camera]
        assert times == sorted(times)


def test_a_sink_that_fails_ends_the_sweep_with_its_error_and_every_camera_stopped() -> None:
    drive = _beam()

    async def sink(frames: list) -> None:
        raise MemoryError("no room for the voxel blocks")

    cameras = [_sim_camera(i, drive) for i in range(len(SHORT.depth_cameras))]
    with pytest.raises(MemoryError, match="voxel blocks"):
        run_virtual(_sweep(drive, cameras, sink=sink))
    assert all(c._t0 is None for c in cameras)  # stopped
