"""Rigs for the daemon's scan tests: the protocol-level drive and depth simulators with mock phones.

The beam drive (CANopen over the loopback bus) and the depth cameras (ray cast) are the real
simulators; the phones are the mock tier (tests/daemon_mocks.py) so faults can be placed on an
exact capture. The subject is a capsule of human height: cheap to ray cast and to fuse.
"""

from __future__ import annotations

import asyncio
import functools
import shutil
from collections.abc import Awaitable, Callable
from concurrent.futures import Executor, ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import trimesh
import yaml

from daemon.jobs.controller import RigController
from daemon.jobs.scan import ScanReport, ScanSettings
from daemon.records.store import ScanStore
from daemon.rig.hardware import RigHardware
from planner.rig import DEFAULT_RIG_PATH, Rig, load_rig
from sim.clock import run_virtual
from sim.rig import sim_depth_model
from tests.daemon_mocks import MockPhone

RIG = load_rig()
PLAN_POINTS = 1500
BODY_TEXEL_MM = "3"
"""``tbp daemon --body-texel-mm`` of the tests whose daemons scan without looking at the textured
body: a 3 mm texel textures a scan in about 4 s instead of 12-16 s at the images' resolution."""


def _rig_file_copy(folder: Path, edit: Callable[[dict[str, Any]], None]) -> Path:
    """A copy of the default rig's folder in ``folder``/rig whose rig file ``edit`` changed."""
    copy = folder / "rig"
    shutil.copytree(DEFAULT_RIG_PATH.parent, copy)
    path = copy / DEFAULT_RIG_PATH.name
    config = yaml.safe_load(path.read_text())
    edit(config)
    path.write_text(yaml.safe_dump(config, sort_keys=False))
    return path


def sparse_rig_file(folder: Path, captures_per_sector: int = 2) -> Path:
    """A copy of the default rig's folder in ``folder`` whose rig file takes ``captures_per_sector``
    pictures per speed sector (every phone, both speeds, the same sectors): for a test of a real
    daemon process that needs a whole scan's states, devices and folder but not the default
    rig's 336 rendered pictures, which take most of such a scan's time."""

    def sparse(config: dict[str, Any]) -> None:
        for sector in config["capture"]["sectors"]:
            sector["captures"] = min(sector["captures"], captures_per_sector)

    return _rig_file_copy(folder, sparse)


def fast_rig_file(folder: Path) -> Path:
    """A copy of the default rig's folder in ``folder`` whose beam turns the capture at 18 deg/s
    in every sector (a 1/1000 s exposure keeps the motion blur within the rig's bound), one
    picture per 10 deg: the turn takes 20 s instead of 80. For a real-time test of the daemon's
    faults and stops, which needs whole scans, not the default rig's slow sectors."""

    def fast(config: dict[str, Any]) -> None:
        config["optics"]["exposure_s"] = 0.001
        for sector in config["capture"]["sectors"]:
            span = sector["end_deg"] - sector["start_deg"]
            sector.update(speed_deg_s=18.0, capture_step_deg=10.0, first_capture_deg=sector["start_deg"] + 5.0,
                          captures=int(span // 10.0))

    return _rig_file_copy(folder, fast)


def capsule_subject() -> trimesh.Trimesh:
    body = trimesh.creation.capsule(height=1400.0, radius=170.0, count=[24, 24])
    body.apply_translation([0.0, 0.0, 870.0])
    return body


@functools.cache
def capsule_scene() -> Any:
    """The capsule ready for ray casting, built once per process (the cameras only read it)."""
    from drivers.sim.depth import DepthScene

    return DepthScene(capsule_subject())


@dataclass
class MockWorld:
    sim_drive: Any
    phones: list[MockPhone]
    tasks: list[asyncio.Task[Any]] = field(default_factory=list)
    depth_cameras: list[Any] = field(default_factory=list)


async def build_rig(rig: Rig, seed: int, *, phone: type[MockPhone] = MockPhone,
                    depth_decimation: int = 4) -> tuple[RigHardware, MockWorld]:
    from drivers.motor.drive import BeamDrive
    from drivers.motor.port import LoopbackCanBus
    from drivers.sim.depth import SimulatedDepthCamera
    from drivers.sim.drive import SimulatedDrive

    bus = LoopbackCanBus("test")
    sim_drive = SimulatedDrive(bus.port("drive"), rig.motor)
    world = MockWorld(sim_drive, [phone(p.serial, seed=seed * 10 + i) for i, p in enumerate(rig.phones)])
    world.tasks.append(asyncio.create_task(sim_drive.run()))
    scene = capsule_scene()
    model = sim_depth_model(rig.depth_camera_model, depth_decimation, 10.0)
    cameras = [SimulatedDepthCamera(c, model, scene, lambda _t: sim_drive.true_angle_deg, seed=seed * 10 + i)
               for i, c in enumerate(rig.depth_cameras)]
    world.depth_cameras = cameras

    async def stop_sims() -> None:
        for task in world.tasks:
            task.cancel()
        await asyncio.gather(*world.tasks, return_exceptions=True)

    hardware = RigHardware(BeamDrive(bus.port("host"), rig.motor), world.phones, cameras, None,
                           closers=[stop_sims])
    return hardware, world


Hook = Callable[[RigController, MockWorld], Awaitable[None]]


def run_scan(store: Path, *, seed: int = 0, during: Hook | None = None, after: Hook | None = None,
             store_factory: Callable[[Path], ScanStore] = ScanStore,
             prepare: Callable[[MockWorld], None] | None = None,
             rig: Rig = RIG, executor: Callable[[], Executor] = functools.partial(ThreadPoolExecutor, max_workers=1),
             ) -> tuple[ScanReport, RigController, MockWorld]:
    """One scan in virtual time; ``during`` runs concurrently with it, ``after`` once it ended."""
    return run_job(store, lambda controller: controller.scan(f"test-seed{seed}"), seed=seed, during=during,
                   after=after, store_factory=store_factory, prepare=prepare, rig=rig, executor=executor)


def run_job(store: Path, job: Callable[[RigController], Awaitable[Any]], *, seed: int = 0,
            during: Hook | None = None, after: Hook | None = None,
            store_factory: Callable[[Path], ScanStore] = ScanStore,
            prepare: Callable[[MockWorld], None] | None = None,
            rig: Rig = RIG, executor: Callable[[], Executor] = functools.partial(ThreadPoolExecutor, max_workers=1),
            ) -> tuple[Any, RigController, MockWorld]:
    """``job(controller)`` (a scan, a calibration rotation) to its report in virtual time on the
    mock-phone rig, its compute steps in ``executor()``; ``during`` runs concurrently with it,
    ``after`` once it ended."""

    async def main() -> tuple[Any, RigController, MockWorld]:
        hardware, world = await build_rig(rig, seed)
        if prepare is not None:
            prepare(world)
        with executor() as compute:
            controller = RigController(rig, hardware, store_factory(store), settings=ScanSettings(
                executor=compute, seed=seed, plan_points=PLAN_POINTS))
            await controller.start()
            side = asyncio.create_task(during(controller, world)) if during is not None else None
            try:
                report = await job(controller)
                if after is not None:
                    await after(controller, world)
            finally:
                if side is not None:
                    side.cancel()
                    await asyncio.gather(side, return_exceptions=True)
                await controller.close()
        return report, controller, world

    return run_virtual(main())


async def wait_captured(controller: RigController, count: int) -> None:
    """Until the running scan has captured ``count`` images."""
    while True:
        scan = controller.current
        runner = getattr(getattr(scan, "steps", None), "runner", None)
        if runner is not None and runner.captured >= count:
            return
        await asyncio.sleep(0.05)
