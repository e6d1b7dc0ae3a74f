"""The simulated depth camera: geometry, RealSense-like error model, timing and injected faults."""

from __future__ import annotations

import asyncio
import contextlib
import math

import numpy as np
import pytest
import trimesh

from drivers.depth.base import DepthCamera, DepthFrame
from drivers.depth.errors import InfraredUnavailable
from drivers.sim.depth import DepthFaults, DepthRenderer, DepthScene, SimulatedDepthCamera, simulate_sweep
from planner.poses import depth_camera_pose
from sim.clock import run_virtual
from tests.depth_helpers import look_minus_x, small_rig, sphere, wall

RIG = small_rig(scale=4)
MODEL = RIG.depth_camera_model


def _render(mesh: trimesh.Trimesh, pose: np.ndarray, seed: int | None = 0) -> np.ndarray:
    renderer = DepthRenderer(DepthScene(mesh, floor=False), MODEL)
    return renderer.render(pose, None if seed is None else np.random.default_rng(seed))


def test_noise_free_wall_reads_its_z_depth_everywhere():
    depth = _render(wall(800.0), look_minus_x(), seed=None)
    assert depth.shape == (MODEL.height_px, MODEL.width_px)
    assert depth.dtype == np.uint16
    # z-depth, not ray length: the same value in the corners as in the centre
    assert np.all(depth == 800)


def test_noise_rms_grows_with_depth_squared():
    for distance in (600.0, 1500.0):
        depth = _render(wall(distance), look_minus_x(), seed=1).astype(float)
        expected = distance**2 * MODEL.subpixel_px / (MODEL.fx_px * MODEL.baseline_mm)
        # quantisation to 1 mm adds 1/12 mm^2 of variance
        measured = math.sqrt(max(depth.var() - 1 / 12, 0.0))
        assert measured == pytest.approx(expected, rel=0.1)
        assert depth.mean() == pytest.approx(distance, abs=0.2)


def test_a_camera_sampled_at_every_other_pixel_is_the_same_camera():
    """The simulator's cheaper depth frames (sim.rig.sim_depth_model): every other pixel of the
    rig's camera, with that camera's depth noise and its silhouette edges, not a camera with
    pixels twice as coarse."""
    from sim.rig import sim_depth_model

    half = sim_depth_model(MODEL, 2, MODEL.fps)
    wall_depth = DepthRenderer(DepthScene(wall(1500.0), floor=False), half).render(
        look_minus_x(), np.random.default_rng(1)).astype(float)
    expected = 1500.0**2 * MODEL.subpixel_px / (MODEL.fx_px * MODEL.baseline_mm)
    assert math.sqrt(max(wall_depth.var() - 1 / 12, 0.0)) == pytest.approx(expected, rel=0.1)
    pose = look_minus_x()
    ball = sphere(250.0, centre=(-1000.0, 37.0, -21.0))  # off the optical axis
    full = DepthRenderer(DepthScene(ball, floor=False), MODEL).render(pose, None)[::2, ::2]
    coarse = DepthRenderer(DepthScene(ball, floor=False), half).render(pose, None)
    both = (full > 0) & (coarse > 0)
    assert both.sum() > 0.1 * both.size
    assert np.abs(full[both].astype(int) - coarse[both]).max() <= 1
    # the silhouette's band without depth is as wide on the skin as the full camera's
    assert np.mean((full > 0) == (coarse > 0)) > 0.99  # twice as wide: 98.2 %


def test_same_seed_same_frame_other_seed_differs():
    a = _render(wall(1000.0), look_minus_x(), seed=3)
    b = _render(wall(1000.0), look_minus_x(), seed=3)
    c = _render(wall(1000.0), look_minus_x(), seed=4)
    assert np.array_equal(a, b)
    assert not np.array_equal(a, c)


def test_grazing_surfaces_are_holes():
    # a camera turned 75 deg from the wall sees it at 43..107 deg incidence across the image
    pose = look_minus_x(yaw_deg=75.0)
    depth = _render(wall(800.0, size=20000.0), pose, seed=None)
    u, v = np.meshgrid(np.arange(MODEL.width_px), np.arange(MODEL.height_px))
    rays = np.stack([(u - MODEL.cx_px) / MODEL.fx_px, (v - MODEL.cy_px) / MODEL.fy_px, np.ones(u.shape)], -1)
    world = rays @ pose[:3, :3].T
    incidence = np.degrees(np.arccos(-world[..., 0] / np.linalg.norm(world, axis=-1)))
    limit = MODEL.grazing_limit_deg
    assert np.all(depth[incidence > limit + 0.5] == 0)
    in_range = (incidence < limit - 0.5) & (depth > 0)
    assert in_range.sum() > 0.9 * (incidence < limit - 0.5).sum() - 0.05 * depth.size


def test_silhouette_edges_and_out_of_range_are_holes():
    ball = sphere(100.0, centre=(-600.0, 0.0, 0.0))
    scene = trimesh.util.concatenate([ball, wall(2000.0)])
    depth = _render(scene, look_minus_x(), seed=None)
    row = depth[MODEL.height_px // 2]
    centre = MODEL.width_px // 2
    assert 490 <= row[centre] <= 510
    on_ball = np.flatnonzero((row > 0) & (row < 700))
    # the ball's outline and the wall just beside it carry no depth
    left, right = on_ball.min(), on_ball.max()
    assert row[left - 1] == 0 and row[right + 1] == 0
    assert row[0] == 2000
    # nearer than the minimum range or beyond the maximum: no depth
    assert np.count_nonzero(_render(wall(200.0), look_minus_x(), seed=None)) == 0
    assert np.count_nonzero(_render(wall(3500.0), look_minus_x(), seed=None)) == 0


def test_simulated_sweep_frames_are_posed_at_constant_speed():
    sweep = simulate_sweep(sphere(), RIG, seed=0, noise=False, frame_spacing_deg=30.0)
    per_camera = sweep.per_camera()
    assert set(per_camera) == {c.id for c in RIG.depth_cameras}
    s = RIG.depth_sweep
    for f in sweep.frames:
        assert f.beam_angle_deg == pytest.approx(s.start_deg + s.speed_deg_s * f.timestamp_s)
        camera = next(c for c in RIG.depth_cameras if c.id == f.camera_id)
        assert np.allclose(f.camera_to_world, depth_camera_pose(camera, math.radians(f.beam_angle_deg)))
    last = max(f.beam_angle_deg for f in sweep.frames)
    assert last == pytest.approx(s.end_deg)


def _camera(faults: DepthFaults | None = None, angle=lambda t: 10.0 * t, infrared_source=None) -> SimulatedDepthCamera:
    return SimulatedDepthCamera(RIG.depth_cameras[2], MODEL, sphere(), angle, seed=1, faults=faults,
                                infrared_source=infrared_source)


class InfraredSource:
    """Records what it is asked for; frame k's picture is uniform grey 40 + k."""

    def __init__(self, shape: tuple[int, ...] = (MODEL.height_px, MODEL.width_px), dtype=np.uint8) -> None:
        self.shape, self.dtype = shape, dtype
        self.calls: list[tuple[int, float]] = []

    def __call__(self, frame_number: int, angle_deg: float) -> np.ndarray:
        self.calls.append((frame_number, angle_deg))
        return np.full(self.shape, 40 + frame_number, dtype=self.dtype)


async def _take(camera: SimulatedDepthCamera, count: int) -> list[DepthFrame]:
    await camera.start()
    frames = []
    async with contextlib.aclosing(camera.frames()) as stream:
        async for frame in stream:
            frames.append(frame)
            if len(frames) == count:
                break
    await camera.stop()
    return frames


def test_camera_streams_at_fps_on_the_loop_clock_with_the_beam_angle_of_each_frame():
    times: list[float] = []

    def angle(t: float) -> float:
        times.append(t)
        return 10.0 * t

    camera = _camera(angle=angle)
    assert isinstance(camera, DepthCamera)
    frames = run_virtual(_take(camera, 5))
    assert [f.frame_number for f in frames] == [0, 1, 2, 3, 4]
    assert [f.timestamp_s for f in frames] == pytest.approx([k / MODEL.fps for k in range(5)])
    assert times == pytest.approx([f.timestamp_s for f in frames])
    assert all(np.count_nonzero(f.depth) > 0 for f in frames)
    assert np.array_equal(frames[0].intrinsics, MODEL.intrinsic_matrix)


def test_a_frame_rendered_on_the_loop_gives_the_loop_turns_and_the_same_image(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    monkeypatch.setattr("drivers.sim.depth.RAYS_PER_STEP", 1000)
    steps = -(-MODEL.width_px * MODEL.height_px // 1000)

    async def render_with_a_ticker() -> tuple[DepthFrame, int]:
        turns = 0
        done = asyncio.Event()

        async def ticker() -> None:
            nonlocal turns
            while not done.is_set():
                turns += 1
                await asyncio.sleep(0)

        task = asyncio.create_task(ticker())
        await asyncio.sleep(0)
        turns = 0
        frame = await _camera().render_frame_async(0, 0.5)
        done.set()
        await task
        return frame, turns

    frame, turns = run_virtual(render_with_a_ticker())
    assert turns >= steps  # the ticker ran between the ray-casting steps, not only after the frame
    whole = _camera().render_frame(0, 0.5)
    assert np.array_equal(frame.depth, whole.depth) and np.count_nonzero(frame.depth) > 0


def test_dropped_and_empty_frames_are_injected():
    camera = _camera(DepthFaults(drop_frames={1, 2}, empty_frames={4}))
    frames = run_virtual(_take(camera, 4))
    assert [f.frame_number for f in frames] == [0, 3, 4, 5]
    assert np.count_nonzero(frames[2].depth) == 0
    assert np.count_nonzero(frames[3].depth) > 0


def test_drop_next_skips_the_following_frames():
    camera = _camera()

    async def main() -> list[int]:
        await camera.start()
        numbers = []
        async with contextlib.aclosing(camera.frames()) as stream:
            async for frame in stream:
                numbers.append(frame.frame_number)
                if len(numbers) == 1:
                    camera.drop_next(3)
                if len(numbers) == 3:
                    break
        return numbers

    assert run_virtual(main()) == [0, 4, 5]


def test_a_stopped_camera_delivers_nothing_more():
    camera = _camera()

    async def main() -> tuple[int, bool]:
        await camera.start()
        stream = camera.frames().__aiter__()
        first = await stream.__anext__()
        camera.stop_streaming()
        try:
            async with asyncio.timeout(5.0):
                await stream.__anext__()
        except TimeoutError:
            return first.frame_number, True
        return first.frame_number, False

    assert run_virtual(main()) == (0, True)


def test_frames_carry_the_infrared_source_picture_at_the_angle_of_the_depth_render():
    returned: list[float] = []

    def angle(t: float) -> float:  # a different angle at every call: a second call would show
        returned.append(10.0 * t + 0.001 * len(returned))
        return returned[-1]

    source = InfraredSource()
    camera = _camera(angle=angle, infrared_source=source)
    camera.infrared = True
    frames = run_virtual(_take(camera, 3))
    assert len(returned) == 3  # one angle per frame, for the depth render and the infrared picture
    assert source.calls == [(0, returned[0]), (1, returned[1]), (2, returned[2])]
    for k, frame in enumerate(frames):
        assert frame.infrared.dtype == np.uint8 and frame.infrared.shape == (MODEL.height_px, MODEL.width_px)
        assert (frame.infrared == 40 + k).all()
        assert np.count_nonzero(frame.depth) > 0


def test_infrared_without_a_source_is_unavailable():
    camera = _camera()
    camera.infrared = True
    with pytest.raises(InfraredUnavailable, match="no infrared source") as info:
        run_virtual(camera.start())
    assert info.value.camera_id == RIG.depth_cameras[2].id


def test_infrared_off_leaves_frames_without_it_and_the_source_unasked():
    source = InfraredSource()
    frames = run_virtual(_take(_camera(infrared_source=source), 2))
    assert [f.infrared for f in frames] == [None, None] and source.calls == []


@pytest.mark.parametrize("shape, dtype", [((MODEL.height_px, MODEL.width_px), np.uint16),
                                          ((MODEL.height_px, MODEL.width_px + 1), np.uint8),
                                          ((MODEL.height_px, MODEL.width_px, 3), np.uint8)])
def test_an_infrared_picture_of_the_wrong_size_or_type_is_refused(shape, dtype):
    camera = _camera(infrared_source=InfraredSource(shape, dtype))
    camera.infrared = True
    with pytest.raises(ValueError) as info:
        run_virtual(_take(camera, 1))
    message = str(info.value)
    assert RIG.depth_cameras[2].id in message and str(shape) in message and np.dtype(dtype).name in message
