"""Every device the daemon is given implements its protocol (daemon/rig/devices.py), member by member:
the real drivers, the simulated rig's devices and the test doubles alike."""

from __future__ import annotations

import inspect
import typing
from collections.abc import Callable
from typing import Any

import pytest

from daemon.rig.devices import DepthCamera, Drive, Panel, Phone
from planner.rig import DEFAULT_RIG_PATH, load_rig

RIG = load_rig(DEFAULT_RIG_PATH)


def _protocol_members(protocol: type) -> dict[str, Any]:
    """name -> the protocol's function, property, or None for a plain attribute."""
    members: dict[str, Any] = {name: None for name in typing.get_type_hints(protocol)}
    for name, value in vars(protocol).items():
        if not name.startswith("_") and (callable(value) or isinstance(value, property)):
            members[name] = value
    return members


def violations(protocol: type, instance: Any) -> list[str]:
    """How ``instance`` falls short of ``protocol``: missing members, a coroutine where a plain
    method is expected (or the other way), parameters the protocol passes that it does not take."""
    problems = []
    for name, member in _protocol_members(protocol).items():
        if not hasattr(instance, name):
            problems.append(f"{name}: missing")
            continue
        if member is None or isinstance(member, property):
            continue
        implementation = getattr(instance, name)
        if inspect.iscoroutinefunction(member) != inspect.iscoroutinefunction(implementation):
            problems.append(f"{name}: {'async' if inspect.iscoroutinefunction(member) else 'plain'} "
                            "method expected")
        wanted = [p for p in inspect.signature(member).parameters.values() if p.name != "self"]
        have = inspect.signature(implementation).parameters
        for parameter in wanted:
            if parameter.name not in have:
                problems.append(f"{name}: no parameter {parameter.name}")
            elif parameter.default is not inspect.Parameter.empty and have[parameter.name].default is inspect.Parameter.empty:
                problems.append(f"{name}: {parameter.name} needs a default")
        extra = [p for n, p in have.items() if n not in {w.name for w in wanted}
                 and p.default is inspect.Parameter.empty and p.kind not in (p.VAR_POSITIONAL, p.VAR_KEYWORD)]
        problems += [f"{name}: extra required parameter {p.name}" for p in extra]
    return problems


def _beam_drive() -> Any:
    from drivers.motor import BeamDrive, LoopbackCanBus

    return BeamDrive(LoopbackCanBus().port(), RIG.motor)


def _mock_drive() -> Any:
    from tests.daemon_mocks import MockDrive

    return MockDrive()


def _phone_camera() -> Any:
    from drivers.adb.auth import AdbKey
    from drivers.phone.camera import PhoneCamera
    from drivers.phone.focus import load_focus_calibration

    phone = RIG.phones[0]

    async def never() -> Any:
        raise AssertionError("not connected in this test")

    return PhoneCamera(never, phone, load_focus_calibration(RIG.resolve(phone.focus_calibration)),
                       key=AdbKey.generate())


def _mock_phone() -> Any:
    from tests.daemon_mocks import MockPhone

    return MockPhone("S0")


def _realsense() -> Any:
    from drivers.depth.realsense import RealSenseCamera

    return RealSenseCamera(RIG.depth_cameras[0])


def _bag() -> Any:
    from drivers.depth.bag import BagPlayback

    return BagPlayback("/nonexistent.db3", camera_id="depth0")


def _simulated_depth() -> Any:
    from drivers.sim.depth import DepthScene, SimulatedDepthCamera
    from sim.rig import sim_depth_model
    from tests.daemon_rigs import capsule_subject

    model = sim_depth_model(RIG.depth_camera_model, 8, 10.0)
    return SimulatedDepthCamera(RIG.depth_cameras[0], model, DepthScene(capsule_subject()), lambda _t: 0.0)


def _panel() -> Any:
    from drivers.panel import OperatorPanel

    return OperatorPanel.at("/dev/null")


IMPLEMENTATIONS: list[tuple[type, Callable[[], Any]]] = [
    (Drive, _beam_drive), (Drive, _mock_drive),
    (Phone, _phone_camera), (Phone, _mock_phone),
    (DepthCamera, _realsense), (DepthCamera, _bag), (DepthCamera, _simulated_depth),
    (Panel, _panel),
]


@pytest.mark.parametrize("protocol, make", IMPLEMENTATIONS,
                         ids=[f"{p.__name__}-{m.__name__.lstrip('_')}" for p, m in IMPLEMENTATIONS])
def test_each_device_implements_its_protocol(protocol: type, make: Callable[[], Any]) -> None:
    device = make()
    assert violations(protocol, device) == []
    assert isinstance(device, protocol)


def test_the_check_finds_a_missing_member_a_wrong_kind_and_a_missing_parameter() -> None:
    from tests.daemon_mocks import MockDrive

    class Incomplete(MockDrive):
        def __getattribute__(self, name: str) -> Any:
            if name == "quick_stop":
                raise AttributeError(name)
            return super().__getattribute__(name)

        def stop(self) -> None:  # type: ignore[override]
            pass

    problems = violations(Drive, Incomplete())
    assert "quick_stop: missing" in problems
    assert "stop: async method expected" in problems
    assert "stop: no parameter deceleration_deg_s2" in problems


def test_the_simulated_rig_hands_the_daemon_protocol_devices() -> None:
    from sim.clock import run_virtual
    from sim.rig import SimOptions, build_sim_rig
    from tests.daemon_rigs import capsule_subject

    async def build() -> list[str]:
        hardware, world = await build_sim_rig(RIG, SimOptions(depth_decimation=8), subject=capsule_subject())
        try:
            devices = [(Drive, hardware.drive), (Panel, hardware.panel)]
            devices += [(Phone, p) for p in hardware.phones] + [(DepthCamera, c) for c in hardware.depth_cameras]
            return [f"{type(d).__name__}: {v}" for protocol, d in devices for v in violations(protocol, d)]
        finally:
            await world.close()

    assert run_virtual(build()) == []
