"""PhoneCamera against the simulated phone on virtual time: bring-up, focus, capture, clock, pull, faults.

Every test runs twice: against the phone's Python twin of the capture agent and against the real
agent's core (agent/) run under the JVM by the same simulated phone; both must pass unchanged.
"""

from __future__ import annotations

import asyncio
import hashlib
import io
import os
from collections.abc import Awaitable, Callable
from pathlib import Path
from typing import Any

import pytest
from PIL import Image

from drivers.adb.auth import AdbKey
from drivers.phone import protocol
from drivers.phone.camera import PhoneCamera
from drivers.phone.errors import (
    AgentMissing,
    AgentProtocolError,
    AgentStartFailed,
    CaptureFailed,
    FocusOutOfRange,
    FocusTimeout,
    PhoneDisconnected,
    PhoneUnauthorized,
    PullFailed,
    RequestTimeout,
    WrongPhone,
)
from drivers.phone.focus import load_focus_calibration
from drivers.sim.phone import SimulatedPhone
from planner.rig import load_rig
from sim.clock import run_virtual
from tests.adb_links import SimLink

RIG = load_rig()
PHONE = RIG.phones[2]
TABLE = load_focus_calibration(RIG.resolve(PHONE.focus_calibration))
KEY = AdbKey.generate("test@host")
_AGENT: dict[str, Any] = {}  # the simulated phone's agent for the running test


@pytest.fixture(autouse=True, params=["python", pytest.param("jvm", marks=pytest.mark.realtime)])
def agent_runtime(request: pytest.FixtureRequest) -> Any:
    """The agent the simulated phones run: the Python twin, or the real agent core under the JVM."""
    jar = request.getfixturevalue("agent_jvm_jar") if request.param == "jvm" else None
    _AGENT.update(agent_runtime=request.param, agent_jar=jar)
    yield request.param
    _AGENT.clear()


def _agent_jar_bytes() -> bytes:
    """A jar the simulated phone can run: the twin does not look inside, java does."""
    jar = _AGENT["agent_jar"]
    return b"PK\x03\x04" + bytes(5000) if jar is None else jar.read_bytes()


def run(scenario: Callable[[PhoneCamera, SimulatedPhone], Awaitable[Any]], *, serial: str = PHONE.serial,
        known: bool = True, agent_jar: Path | None = None, **options: Any) -> Any:
    async def main() -> Any:
        sim = SimulatedPhone(serial, known_keys=[KEY.public_blob()] if known else [], optics=RIG.optics,
                             seed=3, **{**_AGENT, **options})
        link = SimLink(sim)
        camera = PhoneCamera(link.streams, PHONE, TABLE, key=KEY, agent_jar=agent_jar)
        try:
            return await scenario(camera, sim)
        finally:
            await camera.close()
            await link.finish()

    return run_virtual(main())


def now() -> float:
    return asyncio.get_running_loop().time()


def test_connect_focus_capture_clock_pull(tmp_path: Path) -> None:
    async def scenario(camera: PhoneCamera, sim: SimulatedPhone) -> None:
        info = await camera.connect()
        assert (info.serial, info.min_focus_diopters, info.focus_calibration_quality, info.timestamp_source) == \
            (PHONE.serial, 10.0, 1, "realtime")
        assert camera.state == "ready" and sim.agent_running

        start = now()
        focus = await camera.set_focus_mm(400.0)
        expected_s = sim.LENS_BASE_S + sim.LENS_S_PER_DIOPTER * focus.diopters + sim.LENS_SETTLE_S
        assert now() - start == pytest.approx(expected_s)
        assert focus.focus_mm == pytest.approx(400.0, rel=1e-4)
        assert focus.diopters == pytest.approx(TABLE.diopters_for(400.0), abs=1e-6) == sim.lens_diopters
        assert focus.lens_stationary_at_ns == sim.sensor_ns(now())

        sample = await camera.clock_sample()
        assert sample.host_send_s < sim.loop_time_of(sample.device_ns) < sample.host_recv_s

        sent = now()
        done = await camera.capture()
        exposure_start = sim.loop_time_of(done.sensor_timestamp_ns)
        assert sent < exposure_start < now()
        assert done.exposure_s == RIG.optics.exposure_s and done.focus_diopters == focus.diopters
        assert sim.fs.read(done.path) is not None and len(sim.fs.read(done.path)) == done.size_bytes

        size, sha = await camera.pull(done.path, tmp_path / "img.jpg")
        assert size == done.size_bytes and sha == hashlib.sha256(sim.fs.read(done.path)).hexdigest()
        assert Image.open(io.BytesIO((tmp_path / "img.jpg").read_bytes())).size == (192, 256)
        await camera.delete(done.path)
        assert sim.fs.read(done.path) is None

    run(scenario)


def test_sensor_clock_has_offset_and_drift() -> None:
    async def scenario(camera: PhoneCamera, sim: SimulatedPhone) -> None:
        await camera.connect()
        first = await camera.clock_sample()
        await asyncio.sleep(5000.0)  # link delay jitter (< 0.3 ms) is then < 0.1 ppm
        second = await camera.clock_sample()
        device_s = (second.device_ns - first.device_ns) * 1e-9
        host_s = second.host_send_s - first.host_send_s
        assert abs(first.device_ns * 1e-9 - first.host_send_s) > 100.0
        assert device_s / host_s - 1 == pytest.approx(sim.clock_drift_ppm * 1e-6, abs=2e-7)

    run(scenario)


def test_agent_is_pushed_once_then_reused(tmp_path: Path) -> None:
    jar = tmp_path / "agent.jar"
    jar.write_bytes(_agent_jar_bytes())

    async def scenario(camera: PhoneCamera, sim: SimulatedPhone) -> None:
        assert sim.fs.read(protocol.AGENT_PATH) is None
        await camera.connect()
        pushed = sim.fs.files[protocol.AGENT_PATH]
        assert pushed.data == jar.read_bytes()
        await camera.connect()  # reconnect: same size and mtime on the phone, no second push
        assert sim.fs.files[protocol.AGENT_PATH] is pushed and sim.connections == 2
        os.utime(jar, (1_700_000_000, 1_700_000_000))  # a new build of the same size
        await camera.connect()
        assert sim.fs.files[protocol.AGENT_PATH] is not pushed
        assert sim.fs.files[protocol.AGENT_PATH].mtime == 1_700_000_000

    run(scenario, agent_jar=jar, agent_installed=False)


def test_agent_missing_everywhere() -> None:
    async def scenario(camera: PhoneCamera, sim: SimulatedPhone) -> None:
        with pytest.raises(AgentMissing, match="no local jar"):
            await camera.connect()
        assert camera.state == "disconnected"

    run(scenario, agent_installed=False)


def test_agent_that_does_not_start_quotes_its_output() -> None:
    async def scenario(camera: PhoneCamera, sim: SimulatedPhone) -> None:
        del sim.commands["app_process"]
        with pytest.raises(AgentStartFailed, match="app_process: inaccessible or not found"):
            await camera.connect()

    run(scenario)


def test_agent_of_another_protocol_version_is_refused(agent_runtime: str) -> None:
    if agent_runtime == "jvm":
        pytest.skip("the real agent speaks protocol 1 only: a twin-only fault")

    async def scenario(camera: PhoneCamera, sim: SimulatedPhone) -> None:
        sim.agent_version = 2
        with pytest.raises(AgentProtocolError, match="agent speaks protocol 2, this host 1"):
            await camera.connect()
        assert camera.state == "disconnected"

    run(scenario)


def test_wrong_serial_and_refused_key() -> None:
    async def wrong(camera: PhoneCamera, sim: SimulatedPhone) -> None:
        with pytest.raises(WrongPhone, match="reports serial 'OTHER123'"):
            await camera.connect()

    run(wrong, serial="OTHER123")

    async def refused(camera: PhoneCamera, sim: SimulatedPhone) -> None:
        with pytest.raises(PhoneUnauthorized, match=PHONE.serial):
            await camera.connect()
        assert camera.state == "disconnected"

    run(refused, known=False, accept_new_keys=False)


def test_focus_outside_the_table_or_the_lens_is_refused_before_sending() -> None:
    async def scenario(camera: PhoneCamera, sim: SimulatedPhone) -> None:
        await camera.connect()
        with pytest.raises(FocusOutOfRange, match="focus 50.0 mm"):
            await camera.set_focus_mm(50.0)
        sim.min_focus_diopters = 4.0
        camera.info = await camera.connect()
        with pytest.raises(FocusOutOfRange) as info:
            await camera.set_focus_mm(150.0)
        assert info.value.near_mm == pytest.approx(TABLE.focus_mm(4.0))
        assert sim.lens_diopters == 0.0

    run(scenario)


def test_slow_lens_times_out_and_the_camera_stays_usable(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(PhoneCamera, "FOCUS_TIMEOUT_S", 0.2)

    async def scenario(camera: PhoneCamera, sim: SimulatedPhone) -> None:
        await camera.connect()
        sim.lens_slowdown = 50.0
        with pytest.raises(FocusTimeout, match="no answer to 'focus' within 0.2 s"):
            await camera.set_focus_mm(300.0)
        sim.lens_slowdown = 1.0
        await asyncio.sleep(2.0)  # the late answer arrives and is dropped
        assert camera.state == "ready"
        assert (await camera.set_focus_mm(300.0)).focus_mm == pytest.approx(300.0, rel=1e-4)

    run(scenario)


def test_capture_failure_is_typed_and_the_next_capture_works() -> None:
    async def scenario(camera: PhoneCamera, sim: SimulatedPhone) -> None:
        await camera.connect()
        sim.fail_captures = 1
        with pytest.raises(CaptureFailed, match="CAPTURE_FAILED") as info:
            await camera.capture()
        assert info.value.code == "CAPTURE_FAILED" and info.value.device == PHONE.serial
        assert (await camera.capture()).size_bytes > 0

    run(scenario)


def test_mute_agent_times_out(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(PhoneCamera, "REQUEST_TIMEOUT_S", 0.5)

    async def scenario(camera: PhoneCamera, sim: SimulatedPhone) -> None:
        await camera.connect()
        sim.mute_agent = True
        with pytest.raises(RequestTimeout, match="'clock'"):
            await camera.clock_sample()

    run(scenario)


def test_delayed_answers_widen_the_clock_round_trip_then_time_out(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(PhoneCamera, "REQUEST_TIMEOUT_S", 0.5)

    async def scenario(camera: PhoneCamera, sim: SimulatedPhone) -> None:
        await camera.connect()
        sim.answer_delay_s = 0.2
        sample = await camera.clock_sample()
        assert sample.host_recv_s - sample.host_send_s >= 0.2
        assert sim.loop_time_of(sample.device_ns) < sample.host_recv_s - 0.2 + 1e-9
        sim.answer_delay_s = 1.0
        with pytest.raises(RequestTimeout, match="within 0.5 s"):
            await camera.clock_sample()
        sim.answer_delay_s = 0.0
        await asyncio.sleep(1.0)
        assert camera.state == "ready"
        await camera.clock_sample()

    run(scenario)


def test_vanish_then_reconnect() -> None:
    async def scenario(camera: PhoneCamera, sim: SimulatedPhone) -> None:
        await camera.connect()
        focus = asyncio.create_task(camera.set_focus_mm(500.0))
        await asyncio.sleep(0.005)
        sim.vanish()
        with pytest.raises(PhoneDisconnected):
            await focus
        assert camera.state == "disconnected"
        with pytest.raises(PhoneDisconnected):
            await camera.capture()
        with pytest.raises(PhoneDisconnected):
            await camera.connect()
        sim.reappear()
        await camera.connect()
        assert (await camera.capture()).size_bytes > 0

    run(scenario)


def test_pull_faults(tmp_path: Path) -> None:
    async def scenario(camera: PhoneCamera, sim: SimulatedPhone) -> None:
        await camera.connect()
        with pytest.raises(PullFailed, match="/sdcard/DCIM/tbp/none.jpg"):
            await camera.pull("/sdcard/DCIM/tbp/none.jpg", tmp_path / "none.jpg")
        sim.fs.write("/sdcard/DCIM/tbp/big.jpg", bytes(3_000_000))
        sim.disconnect_after_bytes = 1_000_000
        with pytest.raises(PhoneDisconnected, match="big.jpg"):
            await camera.pull("/sdcard/DCIM/tbp/big.jpg", tmp_path / "big.jpg")
        assert list(tmp_path.iterdir()) == []
        with pytest.raises(PhoneDisconnected):
            await camera.capture()

    run(scenario)


def test_an_image_larger_than_the_limit_is_a_pull_failure_not_a_lost_phone(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(PhoneCamera, "MAX_IMAGE_BYTES", 1_000_000)

    async def scenario(camera: PhoneCamera, sim: SimulatedPhone) -> None:
        await camera.connect()
        sim.fs.write("/sdcard/DCIM/tbp/huge.jpg", bytes(3_000_000))
        with pytest.raises(PullFailed, match="huge.jpg: larger than the 1000000-byte image limit"):
            await camera.pull("/sdcard/DCIM/tbp/huge.jpg", tmp_path / "huge.jpg")
        assert list(tmp_path.iterdir()) == []
        assert camera.state == "ready" and (await camera.capture()).size_bytes > 0

    run(scenario)


def test_close_ends_a_request_in_flight_at_once() -> None:
    async def scenario(camera: PhoneCamera, sim: SimulatedPhone) -> None:
        await camera.connect()
        capture = asyncio.create_task(camera.capture())
        await asyncio.sleep(0.01)
        start = now()
        await camera.close()
        with pytest.raises(PhoneDisconnected, match="capture: link closed by the host"):
            await capture
        assert now() - start < 0.01

    run(scenario)


def test_close_is_idempotent_and_final() -> None:
    async def scenario(camera: PhoneCamera, sim: SimulatedPhone) -> None:
        await camera.connect()
        await camera.close()
        await camera.close()
        assert camera.state == "closed"
        await asyncio.sleep(0.01)
        assert not sim.agent_running
        with pytest.raises(PhoneDisconnected):
            await camera.capture()

    run(scenario)


async def test_tcp_link_to_a_simulated_phone_server(tmp_path: Path) -> None:
    from drivers.phone.links import tcp_link

    sim = SimulatedPhone(PHONE.serial, known_keys=[KEY.public_blob()], optics=RIG.optics, render_size=None, **_AGENT)
    server = await asyncio.start_server(sim.accept, "127.0.0.1", 0)
    async with server:
        camera = PhoneCamera(tcp_link("127.0.0.1", server.sockets[0].getsockname()[1]), PHONE, TABLE, key=KEY)
        await camera.connect()
        done = await camera.capture()
        size, _ = await camera.pull(done.path, tmp_path / "img.jpg")
        assert size == done.size_bytes == (tmp_path / "img.jpg").stat().st_size
        await camera.close()
        async with asyncio.timeout(30):  # the phone's side ends with the agent: nothing outlives the test
            while sim.agent_running:
                await asyncio.sleep(0.01)


def test_captures_show_the_subject_from_the_pose_at_exposure(tmp_path: Path) -> None:
    import numpy as np
    import trimesh

    from planner.poses import rgb_poses

    body = trimesh.creation.capsule(height=1400.0, radius=170.0, count=[16, 16])
    body.apply_translation([0.0, 0.0, 870.0])
    asked: list[float] = []

    def pose(time_s: float) -> np.ndarray:
        asked.append(time_s)
        return rgb_poses(RIG, np.array([0.0])).camera_to_world(2)

    async def scenario(camera: PhoneCamera, sim: SimulatedPhone) -> None:
        await camera.connect()
        await camera.set_focus_mm(280.0)  # the capsule's surface, 450 - 170 mm from the phone
        done = await camera.capture()
        exposure_start = sim.loop_time_of(done.sensor_timestamp_ns)
        assert asked == [pytest.approx(exposure_start + done.exposure_s / 2)]
        await camera.pull(done.path, tmp_path / "img.jpg")
        image = np.asarray(Image.open(tmp_path / "img.jpg"))
        assert image.shape == (64, 48, 3)
        assert image[32, 24, 0] > 150 and image[32, 24, 0] > image[32, 24, 2] + 30  # skin in the middle

    run(scenario, subject=body, pose=pose, render_size=(48, 64))


def test_an_agent_exception_is_answered_as_camera_error() -> None:
    def broken_pose(_time_s: float):
        raise ValueError("pose source failed")

    async def scenario(camera: PhoneCamera, sim: SimulatedPhone) -> None:
        await camera.connect()
        with pytest.raises(CaptureFailed, match="CAMERA_ERROR.*pose source failed"):
            await camera.capture()
        assert camera.state == "ready"

    run(scenario, pose=broken_pose)


def test_same_seed_same_timeline() -> None:
    async def scenario(camera: PhoneCamera, sim: SimulatedPhone) -> list:
        await camera.connect()
        events = []
        for focus_mm in (300.0, 420.0, 350.0):
            events.append(await camera.set_focus_mm(focus_mm))
            events.append(await camera.capture())
            events.append(await camera.clock_sample())
        return events

    first, second = run(scenario), run(scenario)
    assert first == second
    assert len({e.sensor_timestamp_ns for e in first[1::3]}) == 3


def test_agent_crash_is_a_disconnect_and_reconnect_restarts_it() -> None:
    async def scenario(camera: PhoneCamera, sim: SimulatedPhone) -> None:
        await camera.connect()
        sim.crash_agent()
        await asyncio.sleep(0.01)
        assert not sim.agent_running and camera.state == "disconnected"
        with pytest.raises(PhoneDisconnected, match="capture agent closed its stream"):
            await camera.capture()
        await camera.connect()
        assert sim.agent_running
        assert (await camera.capture()).size_bytes > 0

    run(scenario)
