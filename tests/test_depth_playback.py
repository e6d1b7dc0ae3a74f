"""Depth recordings with the real pyrealsense2: written by its software device and recorder, played
back through BagPlayback, as the daemon and ``tbp depth`` use them.

Streaming runs on librealsense's own threads, so these tests use the real event loop; they wait for
frames or the end of the file, never for a wall-clock duration.
"""

from __future__ import annotations

import asyncio
import json
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from drivers.depth.bag import BagPlayback
from drivers.depth.base import DepthCamera, DepthFrame
from drivers.depth.beam_angles import beam_angles_path, read_beam_angles, write_beam_angles
from drivers.depth.errors import DepthCameraError, RecordingUnreadable
from drivers.depth.recorder import DepthRecorder

W, H = 64, 48
K = np.array([[50.0, 0.0, 31.5], [0.0, 51.0, 23.5], [0.0, 0.0, 1.0]])
PERIOD_MS = 100.0


def depth_of(k: int) -> np.ndarray:
    """Frame k's image: a ramp offset by k (every frame distinct, every pixel checked)."""
    return (np.arange(H * W, dtype=np.uint16).reshape(H, W) + 1000 + 7 * k).astype(np.uint16)


def record(path: Path, count: int, *, angles: bool = True, first_ms: float = 5_000.0,
           pace_s: float = 0.0) -> list[tuple[int, float, float]]:
    """Record count frames; pace_s: wall-clock pause between frames (the SDK stamps each message with
    the time it was written, and real-time playback keeps that pace)."""
    rows = [(k, first_ms + k * PERIOD_MS, -200.0 + 3.0 * k) for k in range(count)]
    with DepthRecorder(path, camera_id="depth1", width=W, height=H, intrinsics=K, depth_unit_mm=0.25,
                       fps=10.0, serial="000000000002") as recorder:
        for k, ms, _angle in rows:
            recorder.write(k, ms, depth_of(k))
            time.sleep(pace_s)
    if angles:
        write_beam_angles(beam_angles_path(path), "depth1", path, rows, {"test": True})
    return rows


async def play(bag: BagPlayback, *, consumer_delay_s: float = 0.0, limit: int | None = None) -> list[DepthFrame]:
    frames: list[DepthFrame] = []
    await bag.start()
    try:
        async for frame in bag.frames():  # ends by itself at the end of the file
            frames.append(frame)
            if consumer_delay_s:
                await asyncio.sleep(consumer_delay_s)
            if limit is not None and len(frames) == limit:
                break
    finally:
        await bag.stop()
    return frames


@pytest.fixture(scope="module")
def sweep_recording(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, list[tuple[int, float, float]]]:
    path = tmp_path_factory.mktemp("rec") / "depth1.db3"
    return path, record(path, 40)


async def test_every_frame_plays_back_at_the_consumers_pace_with_its_recorded_angle(sweep_recording) -> None:
    path, rows = sweep_recording
    bag = BagPlayback(path, camera_id="depth1")
    assert isinstance(bag, DepthCamera)
    bag.QUEUE_FRAMES = 4  # the consumer is slower than the reader: back-pressure, no drops
    frames = await play(bag, consumer_delay_s=0.003)
    assert bag.realtime is False and bag.dropped_frames == 0
    assert [f.frame_number for f in frames] == list(range(40))
    for frame, (k, ms, angle) in zip(frames, rows, strict=True):
        np.testing.assert_array_equal(frame.depth, depth_of(k))
        assert frame.device_timestamp_ms == pytest.approx(ms)
        assert frame.beam_angle_deg == pytest.approx(angle)
        assert frame.camera_id == "depth1"
    assert frames[0].depth_unit_mm == pytest.approx(0.25)
    np.testing.assert_allclose(frames[0].intrinsics, K)
    np.testing.assert_allclose(np.diff([f.timestamp_s for f in frames]), PERIOD_MS / 1000.0, atol=1e-6)


class SlowToOpen(BagPlayback):
    """The file already streams while the SDK call that opened it has not returned (a loaded
    machine): every frame arrives before start() knows the depth scale and intrinsics."""

    def _open(self, rs, on_frame):
        opened = super()._open(rs, on_frame)
        time.sleep(0.5)  # the SDK's reader runs meanwhile, as a descheduled start() lets it
        return opened


async def test_frames_read_before_start_finishes_wait_for_it_and_none_is_dropped(sweep_recording) -> None:
    path, _ = sweep_recording
    bag = SlowToOpen(path, camera_id="depth1")
    bag.QUEUE_FRAMES = 4
    frames = await play(bag)
    assert bag.dropped_frames == 0
    assert [f.frame_number for f in frames] == list(range(40))


async def test_each_start_replays_the_recording_from_its_beginning(sweep_recording) -> None:
    path, _ = sweep_recording
    bag = BagPlayback(path, camera_id="depth1")
    first = await play(bag, limit=5)  # stopped mid-file: the reader thread must let go
    context = bag._context
    again = await play(bag)
    assert [f.frame_number for f in first] == [0, 1, 2, 3, 4]
    assert [f.frame_number for f in again] == list(range(40))
    # one SDK context for the stream's life: destroying one at every stop held the loop 70-100 ms
    assert context is not None and bag._context is context


class LateEndReport(BagPlayback):
    """The SDK's "stopped" report of the previous start reaches the loop while the next start is
    opening the file (a loaded machine: CI saw a restarted playback end with no frame)."""

    previous: int | None = None

    def _open(self, rs, on_frame):
        if self.previous is not None:
            delivered = threading.Event()
            stale = self.previous
            self._loop.call_soon_threadsafe(lambda: (self._end_of_file(stale), delivered.set()))
            assert delivered.wait(5.0)
        opened = super()._open(rs, on_frame)
        self.previous = self._playing
        return opened


async def test_a_late_end_report_of_the_previous_start_does_not_end_the_next(sweep_recording) -> None:
    path, _ = sweep_recording
    bag = LateEndReport(path, camera_id="depth1")
    assert len(await play(bag, limit=3)) == 3
    assert [f.frame_number for f in await play(bag, limit=5)] == [0, 1, 2, 3, 4]


async def test_stopping_mid_file_again_and_again_never_crashes_the_sdk(sweep_recording) -> None:
    """Without a pause before the stop, about one cycle in a hundred aborted the whole process."""
    path, _ = sweep_recording
    bag = BagPlayback(path, camera_id="depth1")
    for _ in range(40):
        assert len(await play(bag, limit=3)) == 3


@pytest.mark.realtime
async def test_realtime_playback_ends_at_the_end_of_the_file(tmp_path: Path) -> None:
    path = tmp_path / "plain.db3"
    record(path, 10, angles=False, pace_s=0.05)
    bag = BagPlayback(path, camera_id="depth0")
    frames = await asyncio.wait_for(play(bag), 30.0)  # a lost end-of-file would stall, not end
    assert bag.realtime is True  # no beam angles: in step with the beam, at the recorded pace
    numbers = [f.frame_number for f in frames]
    assert numbers and numbers == sorted(numbers) and numbers[-1] == 9
    assert all(f.beam_angle_deg is None for f in frames)


async def test_a_beam_file_of_another_recording_is_refused(tmp_path: Path) -> None:
    path = tmp_path / "depth1.db3"
    record(path, 6, first_ms=9_000.0)
    write_beam_angles(beam_angles_path(path), "depth1", path, [(k, 100.0 * k, 0.0) for k in range(6)], {})
    with pytest.raises(DepthCameraError, match=r"depth1.beam.json: frame 0 is stamped 9000.000 ms in the recording but 0.000 ms"):
        await play(BagPlayback(path, camera_id="depth1"))


async def test_a_frame_missing_from_the_beam_file_is_refused(tmp_path: Path) -> None:
    path = tmp_path / "depth1.db3"
    rows = record(path, 6)
    write_beam_angles(beam_angles_path(path), "depth1", path, rows[:3], {})
    with pytest.raises(DepthCameraError, match="frame 3 has no recorded beam angle"):
        await play(BagPlayback(path, camera_id="depth1"))


async def test_missing_and_foreign_files_are_named(tmp_path: Path) -> None:
    with pytest.raises(RecordingUnreadable, match="absent.db3: no recording"):
        await BagPlayback(tmp_path / "absent.db3", camera_id="depth0").start()
    junk = tmp_path / "junk.db3"
    junk.write_bytes(b"not a bag at all" * 64)
    with pytest.raises(RecordingUnreadable, match="junk.db3: not a RealSense recording"):
        await BagPlayback(junk, camera_id="depth0").start()
    bad = tmp_path / "x.beam.json"
    bad.write_text(json.dumps({"format": "tbp-depth-beam/0", "frames": []}))
    with pytest.raises(RecordingUnreadable, match="format 'tbp-depth-beam/0', expected 'tbp-depth-beam/1'"):
        read_beam_angles(bad, "depth0")
    bad.write_text(json.dumps({"format": "tbp-depth-beam/1", "frames": [[0, 1.0, float("nan")]]}))
    with pytest.raises(RecordingUnreadable, match="non-finite"):
        read_beam_angles(bad, "depth0")


def test_the_recorder_writes_db3_only_and_never_leaves_half_a_file(tmp_path: Path) -> None:
    with pytest.raises(RecordingUnreadable, match="must end in .db3"):
        DepthRecorder(tmp_path / "a.bag", camera_id="depth0", width=W, height=H, intrinsics=K,
                      depth_unit_mm=1.0, fps=10.0)
    path = tmp_path / "a.db3"
    with pytest.raises(RecordingUnreadable, match=r"frame 1 is uint16 \(4, 4\)"):
        with DepthRecorder(path, camera_id="depth0", width=W, height=H, intrinsics=K, depth_unit_mm=1.0,
                           fps=10.0) as recorder:
            recorder.write(0, 0.0, depth_of(0))
            recorder.write(1, 100.0, np.zeros((4, 4), dtype=np.uint16))
    assert list(tmp_path.iterdir()) == []


def test_tbp_depth_record_sim_writes_the_sweep_each_camera_saw(tmp_path: Path,
                                                                capsys: pytest.CaptureFixture[str]) -> None:
    import trimesh

    from cli import main
    from drivers.sim.depth import DepthScene, record_sweep_frames, sweep_trajectory
    from planner.rig import load_rig
    from sim.rig import sim_depth_model

    body = tmp_path / "capsule.ply"
    trimesh.creation.capsule(height=1400.0, radius=170.0, count=[16, 16]).apply_translation([0, 0, 870.0]).export(body)
    out = tmp_path / "sweep"
    assert main(["depth", "record", "--sim", "--body", str(body), "--out", str(out), "--fps", "4",
                 "--decimation", "8", "--seed", "3"]) == 0
    printed = capsys.readouterr().out.splitlines()
    assert printed[-1] == str(out)
    rig = load_rig()
    assert sorted(p.name for p in out.iterdir()) == sorted(
        [f"{c.id}.db3" for c in rig.depth_cameras] + [f"{c.id}.beam.json" for c in rig.depth_cameras])

    model = sim_depth_model(rig.depth_camera_model, 8, 4.0)
    scene = DepthScene(trimesh.load(body, force="mesh"))
    camera = rig.depth_cameras[1]
    expected = list(record_sweep_frames(scene, rig, camera, model, seed=301))
    frames = asyncio.run(play(BagPlayback(out / "depth1.db3", camera_id="depth1")))
    assert len(frames) == len(expected) == int(sweep_trajectory(rig).end_time * 4) + 1
    for got, want in zip(frames, expected, strict=True):
        np.testing.assert_array_equal(got.depth, want.depth)
        assert got.beam_angle_deg == pytest.approx(want.beam_angle_deg)
    assert frames[0].beam_angle_deg == rig.depth_sweep.start_deg
    assert frames[-1].beam_angle_deg == pytest.approx(rig.depth_sweep.end_deg)
    np.testing.assert_allclose(frames[0].intrinsics, model.intrinsic_matrix)
    assert read_beam_angles(out / "depth1.beam.json", "depth1").source["noise_seed"] == 301

    assert main(["depth", "play", str(out / "depth2.db3"), "--camera-id", "depth2"]) == 0
    played = capsys.readouterr().out.splitlines()
    assert played[0].startswith(f"depth2 ({out / 'depth2.db3'}): {len(expected)} frames, 4.0 fps, 160x90")
    assert played[1] == "depth2: recorded beam angles -227.0 .. -47.0 deg"


@pytest.mark.realtime
async def test_the_daemons_sweep_poses_a_played_back_recording_at_its_recorded_angles(tmp_path: Path) -> None:
    """BagPlayback as the daemon's DepthCamera: real pyrealsense2 threads, a mock beam on the real loop."""
    import dataclasses
    import math

    import trimesh

    from daemon.jobs.depth_sweep import DepthSweeper
    from daemon.rig.beam import BeamTracker
    from drivers.sim.depth import DepthScene, record_sweep, record_sweep_frames
    from planner.poses import depth_camera_pose
    from planner.rig import load_rig
    from sim.rig import sim_depth_model
    from tests.daemon_mocks import MockDrive

    rig = load_rig()
    rig = dataclasses.replace(rig, depth_sweep=dataclasses.replace(rig.depth_sweep, end_deg=rig.depth_sweep.start_deg + 45))
    model = sim_depth_model(rig.depth_camera_model, 8, 10.0)
    scene = DepthScene(trimesh.creation.capsule(height=1400.0, radius=170.0, count=[16, 16]).apply_translation([0, 0, 870]))
    paths = record_sweep(scene, rig, model, tmp_path, seed=2)
    recorded = {c.id: {f.frame_number: f for f in record_sweep_frames(scene, rig, c, model, seed=200 + i)}
                for i, c in enumerate(rig.depth_cameras)}

    class Sweeper(DepthSweeper):
        SPACING_DEG = 2.0  # keeps every 10 fps frame of the cruise (3 deg apart)

    drive = MockDrive(max_accel=rig.motor.max_acceleration_deg_s2)
    await drive.connect()
    await drive.set_zero(rig.depth_sweep.start_deg)
    tracker = BeamTracker()
    await tracker.start(drive)
    cameras = [BagPlayback(p, camera_id=p.stem) for p in paths]
    try:
        record = await Sweeper(rig, drive, tracker, cameras).run()
    finally:
        await tracker.stop()
        await drive.close()
    assert record.angle_source == {c.id: "recording" for c in rig.depth_cameras}
    assert record.trace[-1, 1] == pytest.approx(rig.depth_sweep.end_deg)  # the beam swept meanwhile
    for camera in rig.depth_cameras:
        posed = [f for f in record.sweep.frames if f.camera_id == camera.id]
        assert len(posed) >= 14 and record.frames_seen[camera.id] == len(recorded[camera.id])
        for f in posed:
            truth = recorded[camera.id][f.frame_number]
            assert f.beam_angle_deg == truth.beam_angle_deg
            np.testing.assert_array_equal(f.depth, truth.depth)
            np.testing.assert_allclose(f.camera_to_world, depth_camera_pose(camera, math.radians(truth.beam_angle_deg)))
    assert all(c._close_source is None for c in cameras)  # stopped, files released
