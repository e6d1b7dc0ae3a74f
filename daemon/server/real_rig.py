"""The real rig: the hardware file turned into the daemon's :class:`RigHardware`.

Nothing is opened here. The drive gets a CAN port that opens its bus on first use, each phone
a link factory (USB by serial, or ADB over TCP), each depth camera the driver of its kind
(drivers/depth/kinds.py), the panel its serial port; the bring-up (daemon/rig/bringup.py) connects
them under the hardware file's timeouts and re-probes the ones that are missing. So a rig PC
whose CAN adapter or a phone is unplugged still starts, reports NOT READY naming the device, and
comes up when it is back.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

import structlog

from daemon.jobs.scan import ScanSettings
from daemon.rig.hardware import RigHardware
from daemon.rig.hardware_config import HardwareConfig, PhoneLink
from daemon.server.serve import serve
from drivers.adb.auth import AdbKey
from drivers.depth.base import DepthCamera, DepthFinder
from drivers.depth.kinds import DEPTH_KINDS
from drivers.motor import BeamDrive, LazyCanPort, PythonCanPort
from drivers.motor.port import CanPort
from drivers.panel import OperatorPanel
from drivers.phone.camera import PhoneCamera
from drivers.phone.focus import load_focus_calibration
from drivers.phone.links import tcp_link, usb_link
from planner.rig import DepthCamera as DepthCameraConfig
from planner.rig import Phone as PhoneConfig
from planner.rig import Rig

log = structlog.get_logger("daemon.server.real_rig")


def build_real_rig(rig: Rig, config: HardwareConfig, *, state_dir: Path) -> RigHardware:
    """The rig's devices as the hardware file wires them, none connected yet.

    state_dir: where the daemon keeps its ADB key (phones authorise it once).
    """
    key = AdbKey.load_or_create(state_dir)

    def new_drive() -> BeamDrive:
        return make_drive(rig, config)

    phones = [make_phone(rig, phone, config.phones[phone.id], key, config.capture_agent) for phone in rig.phones]
    cameras = [make_depth_camera(rig, camera, config) for camera in rig.depth_cameras]
    panel = None
    if config.panel is not None:
        panel = OperatorPanel.at(config.panel.device, baudrate=config.panel.baud, name="panel")
    finders = depth_finders(config)

    async def depth_probe(index: int) -> str:
        return await find_depth_camera(rig, config, finders, index)

    hardware = RigHardware(
        new_drive(), phones, cameras, panel, addresses=dict(config.devices()), drive_factory=new_drive,
        closers=[finder.close for finder in finders.values()], depth_probe=depth_probe, timeouts=config.timeouts,
    )
    log.info("real_rig_built", hardware=config.path, devices=len(config.devices()),
             can=config.can.address, panel=config.panel.address if config.panel else None)
    return hardware


def make_drive(rig: Rig, config: HardwareConfig) -> BeamDrive:
    """The beam drive on the hardware file's CAN bus (opened on first use)."""
    bus = config.can
    extra = bus.bus_options()
    if bus.interface == "slcan" and "bitrate" not in extra:
        extra["bitrate"] = rig.motor.bitrate

    async def open_bus() -> CanPort:
        return await PythonCanPort.connect(bus.interface, bus.channel, name=bus.address, **extra)

    return BeamDrive(LazyCanPort(open_bus, bus.address), rig.motor)


def make_phone(rig: Rig, phone: PhoneConfig, link: PhoneLink, key: AdbKey, agent: Path | None) -> PhoneCamera:
    """One rig phone over its configured link (USB by serial, or ADB over TCP)."""
    factory = usb_link(link.serial) if link.usb else tcp_link(link.host or "", link.port or 5555)
    focus = load_focus_calibration(rig.resolve(phone.focus_calibration))
    return PhoneCamera(factory, phone, focus, key=key, agent_jar=agent)


def make_depth_camera(rig: Rig, camera: DepthCameraConfig, config: HardwareConfig) -> DepthCamera:
    """One rig depth camera, the driver of its kind (not started)."""
    source = config.depth_cameras[camera.id]
    return DEPTH_KINDS[source.kind].open(camera, source, rig.depth_camera_model)


def depth_finders(config: HardwareConfig) -> dict[str, DepthFinder]:
    """One finder for each depth camera kind the hardware file uses, its SDK loaded now, before any
    device's heartbeat runs on the loop; the caller closes them."""
    kinds = sorted({source.kind for source in config.depth_cameras.values()})
    for kind in kinds:
        DEPTH_KINDS[kind].load()
    return {kind: DEPTH_KINDS[kind].finder() for kind in kinds}


async def find_depth_camera(rig: Rig, config: HardwareConfig, finders: dict[str, DepthFinder], index: int) -> str:
    """Depth camera ``index``'s identity in words; raises its kind's error naming it when it cannot
    be found (the SDK missing, not plugged in, no such recording). Nothing streams: the sweep starts
    the camera when the scan needs it."""
    camera = rig.depth_cameras[index]
    source = config.depth_cameras[camera.id]
    return await finders[source.kind].find(camera.id, source)


async def real_service(*, rig: Rig, config: HardwareConfig, store: Path, socket_path: Path | None,
                       state_dir: Path, group: str | None = None, plan_points: int | None = None,
                       qa_report: Callable[..., Path] | None = None,
                       attach: Callable[[Any], None] | None = None) -> int:
    """The daemon on the real rig until SIGINT/SIGTERM; attach(service) adds servers (the web)."""
    return await serve(rig, build_real_rig(rig, config, state_dir=state_dir), store=store,
                       settings=ScanSettings(plan_points=plan_points, qa_report=qa_report),
                       socket_path=socket_path, group=group, attach=attach)
