"""The real rig: the hardware file turned into the daemon's :class:`RigHardware`.

Nothing is opened here. The drive gets a CAN port that opens its bus on first use, each phone
a link factory (USB by serial, or ADB over TCP), each depth camera its RealSense or recording,
the panel its serial port; the bring-up (daemon/bringup.py) connects them under the hardware
file's timeouts and re-probes the ones that are missing. So a rig PC whose CAN adapter or a
phone is unplugged still starts, reports NOT READY naming the device, and comes up when it is
back.
"""

from __future__ import annotations

import asyncio
import contextlib
import signal
from collections.abc import Callable
from pathlib import Path
from typing import Any

import structlog

from daemon.hardware import RigHardware
from daemon.hardware_config import HardwareConfig, PhoneLink
from planner.rig import Rig

log = structlog.get_logger("daemon.real_rig")


def build_real_rig(rig: Rig, config: HardwareConfig, *, state_dir: Path) -> RigHardware:
    """The rig's devices as the hardware file wires them, none connected yet.

    state_dir: where the daemon keeps its ADB key (phones authorise it once).
    """
    from drivers.adb.auth import AdbKey
    from drivers.panel import OperatorPanel

    key = AdbKey.load_or_create(state_dir)

    def new_drive() -> Any:
        return make_drive(rig, config)

    phones = [make_phone(rig, phone, config.phones[phone.id], key, config.capture_agent) for phone in rig.phones]
    cameras = [_depth_camera(rig, camera, config) for camera in rig.depth_cameras]
    panel = None
    if config.panel is not None:
        panel = OperatorPanel.at(config.panel.device, baudrate=config.panel.baud, name="panel")
    probe = _depth_probe(config)
    hardware = RigHardware(
        drive=new_drive(), phones=phones, depth_cameras=cameras, panel=panel,
        addresses=dict(config.devices()), drive_factory=new_drive, closers=[probe.close],
        depth_probe=lambda index: probe_depth_source(rig, config, index, probe), timeouts=config.timeouts,
    )
    log.info("real_rig_built", hardware=config.path, devices=len(config.devices()),
             can=config.can.address, panel=config.panel.address if config.panel else None)
    return hardware


def make_drive(rig: Rig, config: HardwareConfig) -> Any:
    """The beam drive on the hardware file's CAN bus (opened on first use)."""
    from drivers.motor import BeamDrive, LazyCanPort, PythonCanPort

    bus = config.can
    extra = bus.bus_options()
    if bus.interface == "slcan" and "bitrate" not in extra:
        extra["bitrate"] = rig.motor.bitrate

    async def open_bus() -> Any:
        return await PythonCanPort.connect(bus.interface, bus.channel, name=bus.address, **extra)

    return BeamDrive(LazyCanPort(open_bus, bus.address), rig.motor)


def make_phone(rig: Rig, phone: Any, link: PhoneLink, key: Any, agent: Path | None) -> Any:
    """One rig phone over its configured link (USB by serial, or ADB over TCP)."""
    from drivers.phone.camera import PhoneCamera
    from drivers.phone.focus import load_focus_calibration
    from drivers.phone.links import tcp_link, usb_link

    factory = usb_link(link.serial) if link.usb else tcp_link(link.host or "", link.port or 5555)
    focus = load_focus_calibration(rig.resolve(phone.focus_calibration))
    return PhoneCamera(factory, phone, focus, key=key, agent_jar=agent)


def _depth_camera(rig: Rig, camera: Any, config: HardwareConfig) -> Any:
    from drivers.depth.bag import BagPlayback
    from drivers.depth.realsense import RealSenseCamera

    source = config.depth_cameras[camera.id]
    if source.recording is not None:
        return BagPlayback(source.recording, camera_id=camera.id)
    return RealSenseCamera(camera, fps=rig.depth_camera_model.fps)


def _depth_probe(config: HardwareConfig) -> Any:
    """The daemon's RealSense probe (its own process: drivers/depth/realsense_probe.py), and
    pyrealsense2 loaded now for the cameras' streams, before any device's heartbeat runs on the
    loop (the import holds the interpreter lock 25-35 ms). Without it the probe names the missing
    backend for each camera, so it is not an error here."""
    from drivers.depth.realsense import DepthBackendMissing, import_pyrealsense2
    from drivers.depth.realsense_probe import RealSenseProbe

    if config.depth_cameras:
        with contextlib.suppress(DepthBackendMissing):
            import_pyrealsense2("-")
    return RealSenseProbe()


async def probe_depth_source(rig: Rig, config: HardwareConfig, index: int, probe: Any = None) -> None:
    """Raise when depth camera ``index`` cannot be found: pyrealsense2 is missing
    (DepthBackendMissing), its RealSense is not enumerated (a :class:`DepthCameraNotFound` listing
    the serials that are), or its recording is not a file.

    ``probe``: the daemon's :class:`drivers.depth.realsense_probe.RealSenseProbe` (a one-off
    command makes its own). The probe does not stream: the sweep starts the camera when the scan
    needs it."""
    from drivers.depth.errors import RecordingUnreadable
    from drivers.depth.realsense import DepthCameraNotFound, import_pyrealsense2
    from drivers.depth.realsense_probe import RealSenseProbe

    camera = rig.depth_cameras[index]
    source = config.depth_cameras[camera.id]
    if source.recording is not None:
        # Played back, the camera streams through pyrealsense2 too: a missing backend is named
        # before READY (loaded by :func:`_depth_probe`, the import is a dictionary look-up).
        import_pyrealsense2(camera.id)
        if not source.recording.is_file():
            raise RecordingUnreadable(camera.id, source.recording, "no recording at this path")
        return
    if probe is None:
        probe = RealSenseProbe()
        try:
            found = await probe.serials(camera.id)
        finally:
            await probe.close()
    else:
        found = await probe.serials(camera.id)
    if source.serial not in found:
        raise DepthCameraNotFound(camera.id, source.serial, found)


async def real_service(*, rig: Rig, config: HardwareConfig, store: Path, socket_path: Path | None,
                       state_dir: Path, group: str | None = None, plan_points: int | None = None,
                       qa_report: Callable[..., Path] | None = None,
                       attach: Callable[[Any], None] | None = None) -> int:
    """The daemon on the real rig until SIGINT/SIGTERM; attach(service) adds servers (the web).

    Compute runs in a worker process (daemon/worker.py), so fusing and planning never stall
    the drive's heartbeat."""
    from daemon.controller import RigController
    from daemon.logs import follow_machine
    from daemon.looplag import freeze_startup_heap
    from daemon.notify import SystemdNotifier
    from daemon.scan import ScanSettings
    from daemon.service import RigService
    from daemon.store import ScanStore
    from daemon.worker import compute_pool

    hardware = build_real_rig(rig, config, state_dir=state_dir)
    stop = asyncio.Event()
    loop = asyncio.get_running_loop()
    for sig in (signal.SIGINT, signal.SIGTERM):
        loop.add_signal_handler(sig, stop.set)
    with compute_pool() as executor:
        controller = RigController(rig, hardware, ScanStore(store),
                                   settings=ScanSettings(plan_points=plan_points, executor=executor,
                                                         qa_report=qa_report))
        service = RigService(controller, socket_path=socket_path, group=group,
                             notifier=SystemdNotifier.from_env())
        if attach is not None:
            attach(service)
        follow_machine(controller.machine)
        freeze_startup_heap()
        return await service.run(stop)
