"""The depth camera kinds (drivers/depth/kinds.py): a kind is one registry line that the hardware
file, the real rig, the bring-up's finder and ``tbp check`` all follow."""

from __future__ import annotations

import asyncio
from collections.abc import AsyncIterator
from pathlib import Path

import pytest

from daemon.rig.devices import DepthCamera
from daemon.rig.hardware_config import HardwareConfig, HardwareConfigError, hardware_from_mapping
from daemon.server.real_rig import build_real_rig
from drivers.depth.base import DepthFinder, DepthFrame, DepthSource
from drivers.depth.errors import DepthCameraError
from drivers.depth.kinds import DEPTH_KINDS, DepthKind
from drivers.sim.depth import DEPTH_TWINS
from planner.rig import DEFAULT_RIG_PATH, DepthCameraModel, load_rig
from planner.rig import DepthCamera as DepthCameraConfig
from sim.rig import SimOptions
from tests.test_device_protocols import violations

RIG = load_rig(DEFAULT_RIG_PATH)


class PlateCamera:
    """A kind of depth camera no rig has: what a new driver module brings."""

    def __init__(self, camera: DepthCameraConfig, source: DepthSource, model: DepthCameraModel) -> None:
        self.id, self.source, self.infrared = camera.id, source, False

    async def start(self) -> None: ...

    async def frames(self) -> AsyncIterator[DepthFrame]:
        return
        yield

    async def stop(self) -> None: ...


class PlateFinder:
    plugged: set[str] = set()
    loaded = 0
    closed = 0

    async def find(self, camera_id: str, source: DepthSource) -> str:
        if source.serial not in self.plugged:
            raise DepthCameraError(camera_id, f"no plate camera {source.serial}")
        return f"plate camera {source.serial}"

    async def close(self) -> None:
        PlateFinder.closed += 1

    @staticmethod
    def load() -> None:
        PlateFinder.loaded += 1


def _config(depth: dict[str, object]) -> HardwareConfig:
    return hardware_from_mapping({
        "can": {"interface": "socketcand", "channel": "can0", "host": "127.0.0.1", "port": 29536},
        "phones": {p.id: "usb" for p in RIG.phones}, "depth_cameras": depth, "panel": None,
    }, RIG, "/etc/tbp-rig/hardware.yaml")


def test_a_new_kind_is_one_registry_line(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    monkeypatch.setitem(DEPTH_KINDS, "plate", DepthKind("plate", "serial", PlateCamera, PlateFinder, PlateFinder.load,
                                                     "a plate camera with the rig file's serial"))
    monkeypatch.setattr(PlateFinder, "plugged", {RIG.depth_cameras[0].serial})
    first, *others = RIG.depth_cameras
    config = _config({first.id: "plate", **{c.id: {"plate": c.serial} for c in others}})
    assert [s.address for s in config.depth_cameras.values()] == [f"plate:{c.serial}" for c in RIG.depth_cameras]
    with pytest.raises(HardwareConfigError) as refused:
        _config({first.id: {"plate": "not-its-serial"}, **{c.id: "plate" for c in others}})
    assert refused.value.key == f"depth_cameras.{first.id}.plate" and "(write 'plate')" in refused.value.problem

    hardware = build_real_rig(RIG, config, state_dir=tmp_path)
    assert all(isinstance(c, PlateCamera) for c in hardware.depth_cameras) and PlateFinder.loaded == 1
    depth_probe = hardware.depth_probe
    assert depth_probe is not None

    async def probe() -> list[str]:
        try:
            found = [await depth_probe(0)]
            with pytest.raises(DepthCameraError, match="no plate camera"):
                await depth_probe(1)
            return found
        finally:
            for close in hardware.closers:
                await close()

    assert asyncio.run(probe()) == [f"plate camera {first.serial}"] and PlateFinder.closed == 1


def test_an_unknown_kind_is_refused_naming_the_kinds() -> None:
    with pytest.raises(HardwareConfigError) as refused:
        _config({c.id: "lidar" for c in RIG.depth_cameras})
    assert refused.value.key == f"depth_cameras.{RIG.depth_cameras[0].id}"
    assert ", ".join(DEPTH_KINDS) in refused.value.problem


@pytest.mark.parametrize("name", list(DEPTH_KINDS))
def test_every_kind_has_a_driver_and_a_finder_and_every_device_kind_a_twin(name: str) -> None:
    kind = DEPTH_KINDS[name]
    camera = RIG.depth_cameras[0]
    source = DepthSource(name, camera.serial, None if kind.takes == "serial" else Path("/nonexistent.db3"))
    assert violations(DepthCamera, kind.open(camera, source, RIG.depth_camera_model)) == []
    assert violations(DepthFinder, kind.finder()) == []
    assert kind.takes == "path" or name in DEPTH_TWINS


def test_the_simulated_rig_has_no_twin_for_a_kind_it_does_not_know() -> None:
    with pytest.raises(ValueError, match="no simulated twin of depth camera kind 'lidar'; twins: realsense"):
        SimOptions(depth_kind="lidar")
