"""The live RealSense driver against a fake pyrealsense2 injected at its API boundary (no camera here).

Streaming runs on the fake's own thread, as librealsense's does, so these tests use the real
event loop; they wait for frames, never for a wall-clock duration.
"""

from __future__ import annotations

import asyncio
import sys
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from drivers.depth.bag import BagPlayback
from drivers.depth.base import DepthCamera
from drivers.depth.errors import DepthCameraError, DepthStreamStalled, InfraredUnavailable
from drivers.depth.realsense import DepthBackendMissing, DepthCameraNotFound, HostClockMap, RealSenseCamera
from planner.rig import load_rig
from tests.depth_fake_realsense import FakeDevice, FakeRealSense, depth_value, infrared_image, intrinsics
from tests.depth_fake_realsense import format as rs_format
from tests.depth_fake_realsense import option as rs_option
from tests.depth_fake_realsense import stream as rs_stream

RIG = load_rig()
CAMERA = RIG.depth_cameras[0]


@pytest.fixture
def world(monkeypatch: pytest.MonkeyPatch) -> FakeRealSense:
    world = FakeRealSense()
    monkeypatch.setitem(sys.modules, "pyrealsense2", world.module())
    return world


async def collect(camera: DepthCamera, n: int) -> list:
    frames = []
    async for frame in camera.frames():
        frames.append(frame)
        if len(frames) == n:
            break
    return frames


async def test_missing_pyrealsense2_says_how_to_install(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setitem(sys.modules, "pyrealsense2", None)  # import raises ImportError
    camera = RealSenseCamera(CAMERA)
    with pytest.raises(DepthBackendMissing) as info:
        await camera.start()
    message = str(info.value)
    assert CAMERA.id in message and "pip install tbp-rig[realsense]" in message
    assert "pip install pyrealsense2" in message


async def test_unknown_serial_names_it_and_the_connected_ones(world: FakeRealSense) -> None:
    world.devices.append(FakeDevice("111122223333"))
    with pytest.raises(DepthCameraNotFound) as info:
        await RealSenseCamera(CAMERA).start()
    assert info.value.serial == CAMERA.serial and info.value.available == ["111122223333"]
    assert repr(CAMERA.serial) in str(info.value) and "111122223333" in str(info.value)


async def test_frames_carry_depth_scale_intrinsics_and_host_times(world: FakeRealSense) -> None:
    device = FakeDevice(CAMERA.serial, depth_scale=0.00025, frames=6, device_ms0=9_000_000.0,
                        intrinsics=intrinsics(1280, 720, 641.5, 359.25, 912.0, 911.0))
    world.devices.append(device)
    camera = RealSenseCamera(CAMERA, fps=30.0)
    assert isinstance(camera, DepthCamera)
    await camera.start()
    try:
        frames = await collect(camera, 6)
        now = asyncio.get_running_loop().time()
    finally:
        await camera.stop()
    assert device.configured == [(world.module().stream.depth, 1280, 720,
                                  world.module().format.z16, 30)]
    k = np.array([[912.0, 0.0, 641.5], [0.0, 911.0, 359.25], [0.0, 0.0, 1.0]])
    for n, frame in enumerate(frames):
        assert frame.camera_id == CAMERA.id and frame.frame_number == n
        assert frame.depth.dtype == np.uint16 and frame.depth.shape == (720, 1280)
        assert (frame.depth == depth_value(n)).all()  # copied before the SDK reused its buffer
        assert frame.depth_unit_mm == pytest.approx(0.25)
        np.testing.assert_array_equal(frame.intrinsics, k)
        assert frame.device_timestamp_ms >= 9_000_000.0
        assert now - 5.0 < frame.timestamp_s <= now  # on the loop clock, not the device's
    times = [f.timestamp_s for f in frames]
    assert times == sorted(times)
    assert camera.timestamp_domain == "hardware_clock"
    assert frames[0].depth_mm()[0, 0] == pytest.approx(depth_value(0) * 0.25)


async def test_camera_that_stops_streaming_is_a_stall(world: FakeRealSense) -> None:
    world.devices.append(FakeDevice(CAMERA.serial, frames=50, stop_after=3))
    camera = RealSenseCamera(CAMERA)
    camera.FRAME_TIMEOUT_S = 0.3
    await camera.start()
    try:
        with pytest.raises(DepthStreamStalled) as info:
            await collect(camera, 50)
    finally:
        await camera.stop()
    assert info.value.frames == 3 and info.value.waited_s == pytest.approx(0.3)
    assert CAMERA.id in str(info.value)


async def test_start_failure_and_wrong_pixel_format_are_typed(world: FakeRealSense) -> None:
    world.devices.append(FakeDevice(CAMERA.serial, fail_start="Couldn't resolve requests"))
    with pytest.raises(DepthCameraError, match="start failed: Couldn't resolve requests"):
        await RealSenseCamera(CAMERA).start()
    world.devices[0] = FakeDevice(CAMERA.serial, dtype=np.float32)
    camera = RealSenseCamera(CAMERA)
    await camera.start()
    try:
        with pytest.raises(DepthCameraError, match="expected 1280x720 Z16 depth, got float32"):
            await collect(camera, 1)
    finally:
        await camera.stop()


async def test_slow_start_times_out_and_the_late_pipeline_is_released(world: FakeRealSense) -> None:
    device = FakeDevice(CAMERA.serial, start_delay_s=0.3)
    world.devices.append(device)
    camera = RealSenseCamera(CAMERA)
    camera.START_TIMEOUT_S = 0.05
    with pytest.raises(DepthCameraError, match="did not start streaming within 0.05 s"):
        await camera.start()
    loop = asyncio.get_running_loop()
    assert await loop.run_in_executor(None, device.stopped.wait, 10.0)


async def test_stop_ends_a_waiting_reader_and_is_idempotent(world: FakeRealSense) -> None:
    world.devices.append(FakeDevice(CAMERA.serial, frames=100, stop_after=2))
    camera = RealSenseCamera(CAMERA)
    await camera.start()
    reader = asyncio.create_task(collect(camera, 100))
    await asyncio.sleep(0.05)
    await camera.stop()
    await camera.stop()
    assert len(await asyncio.wait_for(reader, 5.0)) <= 2
    with pytest.raises(DepthCameraError, match="frames\\(\\) before start"):
        await collect(RealSenseCamera(CAMERA), 1)


# ---------------------------------------------------------------------- infrared (calibration)


async def run_camera(camera: RealSenseCamera, n: int) -> list:
    await camera.start()
    try:
        return await collect(camera, n)
    finally:
        await camera.stop()


async def test_infrared_streams_the_left_imager_with_the_projector_off(world: FakeRealSense) -> None:
    device = FakeDevice(CAMERA.serial, frames=4)
    world.devices.append(device)
    camera = RealSenseCamera(CAMERA, fps=30.0)
    camera.infrared = True
    frames = await run_camera(camera, 4)
    assert device.configured == [(rs_stream.depth, 1280, 720, rs_format.z16, 30),
                                 (rs_stream.infrared, 1, 1280, 720, rs_format.y8, 30)]
    assert device.options_set == [(rs_option.emitter_enabled, 0.0)]
    assert [f.frame_number for f in frames] == [0, 1, 2, 3]
    for n, frame in enumerate(frames):
        assert frame.infrared.dtype == np.uint8 and frame.infrared.shape == (720, 1280)
        # copied before the SDK reused its buffer
        np.testing.assert_array_equal(frame.infrared, infrared_image(n, 720, 1280))
        assert (frame.depth == depth_value(n)).all()


async def test_without_infrared_the_projector_is_switched_back_on(world: FakeRealSense) -> None:
    device = FakeDevice(CAMERA.serial, frames=4)
    world.devices.append(device)
    camera = RealSenseCamera(CAMERA, fps=30.0)
    camera.infrared = True
    await run_camera(camera, 2)  # a calibration left the projector off
    camera.infrared = False
    frames = await run_camera(camera, 4)
    assert device.configured == [(rs_stream.depth, 1280, 720, rs_format.z16, 30)]
    assert device.options_set == [(rs_option.emitter_enabled, 0.0), (rs_option.emitter_enabled, 1.0)]
    assert len(frames) == 4 and all(f.infrared is None for f in frames)


async def test_a_camera_without_an_emitter_option_is_left_alone(world: FakeRealSense) -> None:
    device = FakeDevice(CAMERA.serial, frames=2, options=set())
    world.devices.append(device)
    camera = RealSenseCamera(CAMERA)
    camera.infrared = True
    frames = await run_camera(camera, 2)
    assert device.options_set == [] and all(f.infrared is not None for f in frames)


async def test_a_frameset_without_its_infrared_image_is_a_typed_error(world: FakeRealSense) -> None:
    world.devices.append(FakeDevice(CAMERA.serial, frames=6, infrared_missing={2}))
    camera = RealSenseCamera(CAMERA)
    camera.infrared = True
    with pytest.raises(DepthCameraError, match="depth frame 2 came without its left infrared image") as info:
        await run_camera(camera, 6)
    assert info.value.camera_id == CAMERA.id


async def test_a_recording_has_no_infrared(world: FakeRealSense, tmp_path: Path) -> None:
    path = tmp_path / "depth1.db3"
    bag = BagPlayback(path, camera_id="depth1")
    bag.infrared = True
    with pytest.raises(InfraredUnavailable) as info:
        await bag.start()
    assert info.value.camera_id == "depth1" and str(path) in str(info.value)


# ---------------------------------------------------------------------- host clock mapping


@given(
    offset=st.floats(-1e6, 1e6),
    latencies=st.lists(st.floats(0.0, 0.05), min_size=1, max_size=60),
)
def test_host_clock_map_removes_transport_latency(offset: float, latencies: list[float]) -> None:
    clock = HostClockMap(window_s=10.0)
    for k, latency in enumerate(latencies):
        device_s = 1000.0 + k / 30.0
        mapped = clock.host_time(device_s * 1000.0, device_s + offset + latency)
        exact = device_s + offset
        assert mapped <= exact + latency + 1e-6  # never later than the arrival
        assert mapped >= exact - 1e-6  # never earlier than the latency-free time
        assert mapped - exact <= min(latencies[: k + 1]) + 1e-6


def test_host_clock_map_forgets_old_offsets_and_device_resets() -> None:
    clock = HostClockMap(window_s=1.0)
    assert clock.host_time(0.0, 100.0) == 100.0
    assert clock.host_time(500.0, 100.6) == pytest.approx(100.5)  # 0.1 s late: first offset kept
    assert clock.host_time(2000.0, 102.05) == pytest.approx(102.05)  # first one left the window
    assert clock.host_time(10.0, 103.0) == pytest.approx(103.0)  # device clock went back: reset


# ---------------------------------------------------------------------- tbp depth


def test_tbp_depth_list_and_check(world: FakeRealSense,
                                       capsys: pytest.CaptureFixture[str]) -> None:
    from cli import main

    for config in RIG.depth_cameras[:2]:
        world.devices.append(FakeDevice(config.serial, frames=10_000, period_s=0.01))
    assert main(["depth", "list"]) == 0
    listed = capsys.readouterr().out
    assert all(f"serial {c.serial}  D400  firmware 5.16.0.1" in listed for c in RIG.depth_cameras[:2])

    assert main(["depth", "check", "--seconds", "0.3"]) == 1  # the third camera is not plugged in
    out = capsys.readouterr().out.splitlines()
    assert out[0].startswith(f"{RIG.depth_cameras[0].id} (serial {RIG.depth_cameras[0].serial}): ")
    assert "1280x720, depth unit 1.0000 mm, fx 912.0" in out[0] and "timestamps hardware_clock" in out[0]
    assert out[2].startswith(f"{RIG.depth_cameras[2].id}: FAILED: ")
    assert repr(RIG.depth_cameras[2].serial) in out[2]
    assert main(["depth", "check", "--camera", RIG.depth_cameras[1].id, "--seconds", "0.2"]) == 0
    assert main(["depth", "check", "--camera", "depth9"]) == 2



def test_tbp_depth_without_pyrealsense2_says_how_to_install(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    from cli import main

    monkeypatch.setitem(sys.modules, "pyrealsense2", None)
    assert main(["depth", "list"]) == 1
    assert "pip install tbp-rig[realsense]" in capsys.readouterr().err
