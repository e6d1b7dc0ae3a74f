"""Simulated-hardware mode: every simulator wired to the same daemon code.

The beam drive talks CANopen over an in-process loopback bus, the seven phones are adbds on
socketpair links, the three depth cameras ray-cast the simulated subject at the drive's
physical angle, and the panel speaks its line protocol over a stream pair. Every link delivers
immediately, so the whole rig runs on the virtual-time loop (sim/clock.py) and a seed
fixes the scan.
"""

from __future__ import annotations

import asyncio
import dataclasses
import socket
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import structlog

from daemon.rig.devices import Panel, Phone
from daemon.rig.hardware import RigHardware
from drivers.adb.auth import AdbKey
from drivers.motor.drive import BeamDrive
from drivers.motor.port import LoopbackCanBus
from drivers.panel import OperatorPanel
from drivers.phone.camera import PhoneCamera, TransportFactory
from drivers.phone.focus import load_focus_calibration
from drivers.sim.depth import DEPTH_TWINS, DepthScene, SampledDepthModel
from drivers.sim.drive import SimulatedDrive
from drivers.sim.panel import SimulatedPanel
from drivers.sim.phone import RENDER_SIZE, SimulatedPhone
from drivers.sim.skin_texture import LesionChanges
from planner.poses import rgb_poses
from planner.rig import DepthCameraModel, Rig

if TYPE_CHECKING:
    from sim.cuboid_stage import CuboidStage

log = structlog.get_logger("sim.rig")


@dataclass(frozen=True)
class SimOptions:
    """Knobs of the simulated rig.

    depth_decimation: the simulated depth cameras render every Nth pixel of the rig's camera, with
        its depth noise and its silhouette edges (ray casting 1280 x 720 takes ~0.5 s of CPU a
        frame; the TSDF fuses every 4th pixel of it at the stored surface's 4 mm voxels).
    depth_fps: simulated frame rate (the sweep keeps one frame per 3 deg: 10 fps at 30 deg/s).
    depth_kind: the kind of depth camera simulated (drivers/depth/kinds.py): its twin streams.
    lesion_changes: the subject's grown and new spots at this visit (drivers/sim/skin_texture.py;
        None: the skin as it is).
    render_scale: the simulated phones' pictures are this many times RENDER_SIZE on each side
        (drivers/sim/phone.py; 1: 192 x 256 px, about 1.5 mm/px on the skin; the rig's phones
        hold 32). Rendering time grows with its square.
    """

    seed: int = 0
    depth_decimation: int = 2
    depth_fps: float = 10.0
    panel: bool = True
    state_dir: Path | None = None
    depth_kind: str = "realsense"
    lesion_changes: LesionChanges | None = None
    render_scale: int = 1

    def __post_init__(self) -> None:
        scale = self.render_scale
        if isinstance(scale, bool) or not isinstance(scale, int) or not 1 <= scale <= 32:
            raise ValueError(f"render_scale {self.render_scale!r}: not a whole number in 1..32")
        if self.depth_kind not in DEPTH_TWINS:
            raise ValueError(f"no simulated twin of depth camera kind {self.depth_kind!r}; "
                             f"twins: {', '.join(DEPTH_TWINS)}")


@dataclass
class SimWorld:
    """Handles on every simulator: fault injection and ground truth for tests."""

    subject: Any
    bus: LoopbackCanBus
    drive: SimulatedDrive
    phones: list[SimulatedPhone] = field(default_factory=list)
    depth_cameras: list[Any] = field(default_factory=list)
    panel: SimulatedPanel | None = None
    tasks: list[asyncio.Task[Any]] = field(default_factory=list)

    def press_estop(self) -> None:
        """The operator hits the e-stop: the panel reports it and the drive's hard-wired input trips."""
        if self.panel is not None:
            self.panel.press_estop()
        self.drive.press_estop()

    def release_estop(self) -> None:
        if self.panel is not None:
            self.panel.release_estop()
        self.drive.release_estop()

    async def close(self) -> None:
        if self.panel is not None:
            self.panel.close()
        for task in self.tasks:
            task.cancel()
        await asyncio.gather(*self.tasks, return_exceptions=True)
        self.tasks.clear()


def sim_depth_model(model: DepthCameraModel, decimation: int, fps: float) -> SampledDepthModel:
    """The rig's depth camera sampled at every decimation-th pixel: intrinsics scaled alike (pixel
    centres at integers, so pixel j is the full image's pixel d j), the full camera's depth noise
    (its disparity error of ``subpixel_px`` full pixels is 1/d as many of these) and its
    silhouette edges (:class:`SampledDepthModel`), not those of a camera whose pixels are d
    times coarser: with those, a half-resolution frame had twice the noise and lost twice the
    skin along each silhouette, and gaps between arms and torso were not seen through."""
    d = max(int(decimation), 1)
    fields = {f.name: getattr(model, f.name) for f in dataclasses.fields(DepthCameraModel)}
    fields.update(width_px=model.width_px // d, height_px=model.height_px // d, fx_px=model.fx_px / d,
                  fy_px=model.fy_px / d, cx_px=model.cx_px / d, cy_px=model.cy_px / d,
                  subpixel_px=model.subpixel_px / d, fps=fps)
    return SampledDepthModel(**fields, every_px=d)


def default_subject(seed: int) -> Any:
    """The simulated subject for a seed: an adult body from sim/body.py."""
    from sim.body import make_body  # the body model: seconds to import, only without a given subject

    return make_body(seed=seed)


def phone_pose_source(rig: Rig, camera_index: int,
                      beam_angle_deg: Callable[[float], float]) -> Callable[[float], np.ndarray]:
    """time -> (4, 4) camera-to-world pose of one phone at the beam's angle at that time (deg)."""

    def pose(time_s: float) -> np.ndarray:
        poses = rgb_poses(rig, np.array([beam_angle_deg(time_s)]))
        return poses.camera_to_world(camera_index)

    return pose


async def build_sim_rig(rig: Rig, options: SimOptions = SimOptions(), *, subject: Any | None = None,
                        stage: CuboidStage | None = None) -> tuple[RigHardware, SimWorld]:
    """Start every simulator and return the daemon-side device objects wired to them.

    stage: the calibration cuboid in place of a subject (sim/cuboid_stage.py): the phones and the
    depth cameras' infrared imagers see it from the rig's true poses."""
    if stage is not None:
        subject = stage.mesh()
    elif subject is None:
        loop = asyncio.get_running_loop()
        subject = await loop.run_in_executor(None, default_subject, options.seed)
    bus = LoopbackCanBus("sim")
    sim_drive = SimulatedDrive(bus.port("drive"), rig.motor)
    world = SimWorld(subject=subject, bus=bus, drive=sim_drive)
    world.tasks.append(asyncio.create_task(sim_drive.run(), name="sim-drive"))
    drive = BeamDrive(bus.port("host"), rig.motor)

    angle = lambda _t=0.0: sim_drive.true_angle_deg  # noqa: E731
    scene = DepthScene(subject)
    model = sim_depth_model(rig.depth_camera_model, options.depth_decimation, options.depth_fps)
    twin = DEPTH_TWINS[options.depth_kind]
    world.depth_cameras = [
        twin(cam, model, scene, angle, seed=options.seed * 100 + i,
             infrared_source=None if stage is None else stage.infrared(cam.id, model))
        for i, cam in enumerate(rig.depth_cameras)
    ]
    phones = await _sim_phones(rig, options, world, angle, stage)
    panel = await _sim_panel(world) if options.panel else None
    hardware = RigHardware(drive=drive, phones=phones, depth_cameras=world.depth_cameras, panel=panel)
    hardware.closers.append(world.close)
    log.info("sim_rig_built", seed=options.seed, phones=len(phones), depth=len(world.depth_cameras),
             panel=panel is not None)
    return hardware, world


async def _stream_pair() -> tuple[tuple[asyncio.StreamReader, asyncio.StreamWriter],
                                  tuple[asyncio.StreamReader, asyncio.StreamWriter]]:
    a, b = socket.socketpair()
    return await asyncio.open_connection(sock=a), await asyncio.open_connection(sock=b)


async def _sim_phones(rig: Rig, options: SimOptions, world: SimWorld,
                      angle: Callable[..., float], stage: CuboidStage | None) -> list[Phone]:
    key = AdbKey.generate() if options.state_dir is None else AdbKey.load_or_create(options.state_dir)
    phones: list[Phone] = []
    for i, phone in enumerate(rig.phones):
        pose = phone_pose_source(rig, i, angle) if stage is None else stage.pose(phone.id, angle)
        sim = SimulatedPhone(
            phone.serial, subject=world.subject, pose=pose,
            seed=options.seed * 100 + i, optics=rig.optics, known_keys=[key.public_blob()],
            lesion_changes=options.lesion_changes,
            render_size=(RENDER_SIZE[0] * options.render_scale, RENDER_SIZE[1] * options.render_scale),
        )
        if stage is not None:
            sim.picture_source = stage.phone_picture(phone.id)
        world.phones.append(sim)
        focus = load_focus_calibration(rig.resolve(phone.focus_calibration))
        phones.append(PhoneCamera(sim_phone_link(sim, world.tasks), phone, focus, key=key))
    return phones


def sim_phone_link(sim: SimulatedPhone, tasks: list[asyncio.Task[Any]]) -> TransportFactory:
    """The host's ADB link to a simulated phone: each connect is a fresh socket pair whose far
    end the phone serves (its task goes into ``tasks``)."""

    async def transport() -> tuple[asyncio.StreamReader, asyncio.StreamWriter]:
        (host_r, host_w), (dev_r, dev_w) = await _stream_pair()
        tasks.append(asyncio.create_task(sim.accept(dev_r, dev_w), name=f"sim-{sim.serial}"))
        return host_r, host_w

    return transport


async def _sim_panel(world: SimWorld) -> Panel:
    (host_r, host_w), (dev_r, dev_w) = await _stream_pair()
    sim = SimulatedPanel(dev_r, dev_w)
    world.panel = sim
    world.tasks.append(asyncio.create_task(sim.run(), name="sim-panel"))
    return OperatorPanel(host_r, host_w)
