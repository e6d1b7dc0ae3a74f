"""The RealSense probe process (drivers/depth/realsense_probe.py): the daemon's re-probes of
missing depth cameras make no librealsense call in the daemon's process."""

from __future__ import annotations

import asyncio
import gc
import io
import sys
from pathlib import Path

import pytest

from drivers.depth.realsense import DepthBackendMissing, DepthCameraNotFound
from drivers.depth.realsense_probe import ProbeFailed, RealSenseProbe, serve
from planner.rig import load_rig
from tests.depth_fake_realsense import FakeDevice, FakeRealSense

RIG = load_rig()


def _fake_probe(*serials: str) -> list[str]:
    """The probe process's command, with the fake pyrealsense2 and these cameras plugged in."""
    script = ("import sys\nfrom tests.depth_fake_realsense import FakeDevice, FakeRealSense\n"
              "world = FakeRealSense()\n"
              f"world.devices += [FakeDevice(s) for s in {list(serials)!r}]\n"
              "sys.modules['pyrealsense2'] = world.module()\n"
              "from drivers.depth.realsense_probe import serve\n"
              "serve(sys.stdin, sys.stdout)\n")
    return [sys.executable, "-c", script]


@pytest.mark.realtime
def test_the_probe_process_keeps_one_context_and_answers_each_request(monkeypatch: pytest.MonkeyPatch) -> None:
    """Destroying an rs.context holds the interpreter lock ~100 ms: one is made, kept, asked."""
    world = FakeRealSense()
    monkeypatch.setitem(sys.modules, "pyrealsense2", world.module())
    answers = io.StringIO()
    contexts: list[tuple[int, int]] = []

    def requests():  # noqa: ANN202
        for n in range(4):
            if n == 2:
                world.devices.append(FakeDevice("123456789012"))  # plugged in meanwhile
            gc.collect()
            contexts.append((world.contexts_made, world.contexts_destroyed))
            yield "serials\n"

    serve(requests(), answers)
    assert answers.getvalue().splitlines() == ['{"serials": []}'] * 2 + ['{"serials": ["123456789012"]}'] * 2
    assert contexts[1:] == [(1, 0)] * 3  # one context, made at start, kept while the process serves


async def test_cameras_probed_together_share_one_answer_from_one_process() -> None:
    probe = RealSenseProbe(_fake_probe("000000000002"))
    try:
        for _ in range(3):
            answers = await asyncio.gather(*(probe.serials(f"depth{i}") for i in range(3)))
            assert answers == [["000000000002"]] * 3
        assert probe.started == 1
    finally:
        await probe.close()
    assert probe._process is None


async def test_a_missing_backend_is_named_for_each_camera() -> None:
    probe = RealSenseProbe([sys.executable, "-c", "import sys; sys.modules['pyrealsense2'] = None\n"
                            "from drivers.depth.realsense_probe import serve; serve(sys.stdin, sys.stdout)"])
    try:
        errors = await asyncio.gather(probe.serials("depth0"), probe.serials("depth1"), return_exceptions=True)
    finally:
        await probe.close()
    assert [type(e) for e in errors] == [DepthBackendMissing, DepthBackendMissing]
    assert "depth0" in str(errors[0]) and "depth1" in str(errors[1]) and "pip install" in str(errors[0])


@pytest.mark.realtime
async def test_a_probe_process_that_hangs_or_dies_is_replaced_at_the_next_probe() -> None:
    hung = RealSenseProbe([sys.executable, "-c", "import time; time.sleep(60)"])
    hung.ANSWER_TIMEOUT_S = 0.5
    with pytest.raises(ProbeFailed, match="depth0.*no answer within 0.5 s"):
        await hung.serials("depth0")
    assert hung._process is None  # killed
    hung.command, hung.ANSWER_TIMEOUT_S = _fake_probe("000000000001"), 60.0  # its start-up included
    assert await hung.serials("depth0") == ["000000000001"] and hung.started == 2
    await hung.close()
    dead = RealSenseProbe([sys.executable, "-c", "pass"])
    with pytest.raises(ProbeFailed, match="exited"):
        await dead.serials("depth1")
    liar = RealSenseProbe([sys.executable, "-c", "import sys; sys.stdin.readline(); print('[1, 2]', flush=True)"])
    with pytest.raises(ProbeFailed, match="not an answer"):
        await liar.serials("depth2")
    await liar.close()


async def test_the_daemons_reprobes_make_no_librealsense_call_in_its_process(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """A rig PC with the depth cameras not plugged in (the real pyrealsense2 in the probe
    process finds none): every re-probe used to make and destroy a context in the daemon."""
    from daemon.rig.hardware_config import hardware_from_mapping
    from daemon.server.real_rig import build_real_rig

    world = FakeRealSense()  # the daemon's own pyrealsense2: must not be asked
    monkeypatch.setitem(sys.modules, "pyrealsense2", world.module())
    config = hardware_from_mapping({
        "can": {"interface": "socketcand", "channel": "can0", "host": "127.0.0.1", "port": 29536},
        "phones": {p.id: {"tcp": "127.0.0.1:5555"} for p in RIG.phones},
        "depth_cameras": {c.id: "realsense" for c in RIG.depth_cameras}, "panel": None,
    }, RIG)
    hardware = build_real_rig(RIG, config, state_dir=tmp_path)
    try:
        for _ in range(3):
            for index in range(len(RIG.depth_cameras)):
                with pytest.raises((DepthCameraNotFound, DepthBackendMissing)):
                    await hardware.depth_probe(index)
    finally:
        for close in hardware.closers:
            await close()
    assert world.contexts_made == 0 and world.query_threads == []
