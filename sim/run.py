"""Running the daemon on the simulated rig: one scan (``tbp scan --sim``) or the service.

Both run on the virtual-time loop, so a scan is deterministic for a seed whatever the machine
load and the time scale: compute steps stop the clock, every simulator link delivers at once.
"""

from __future__ import annotations

import asyncio
import contextlib
from collections.abc import AsyncIterator, Callable, Coroutine
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import TYPE_CHECKING, Any, TextIO

from daemon.clinic.patient import ScanSubject
from daemon.jobs.controller import RigController
from daemon.jobs.scan import ScanReport, ScanSettings
from daemon.records.store import ScanStore
from daemon.rig.states import StatusEvent
from planner import carve
from planner.refine import warm_up
from planner.rig import DEFAULT_RIG_PATH, Rig, load_rig
from sim.rig import SimOptions, build_sim_rig

if TYPE_CHECKING:
    from daemon.jobs.calibration_rotation import RotationReport
    from drivers.sim.skin_texture import LesionChanges
    from sim.cuboid_stage import CuboidStage


def sim_scan_id(seed: int) -> str:
    """A scan id fixed by the seed (the manifest of a seeded scan is reproducible)."""
    return f"sim-seed{seed}"


def progress_printer(out: TextIO) -> Callable[[StatusEvent], None]:
    """Prints transitions and every 48th capture as one line each."""

    def show(event: StatusEvent) -> None:
        if event.kind == "transition":
            print(f"[{event.time_s:8.2f} s] {event.state.value:<14} {event.cause}", file=out, flush=True)
        elif event.cause in ("captured",) and event.data.get("captured", 0) % 48 == 0:
            print(f"[{event.time_s:8.2f} s] {'':<14} {event.data['captured']} images captured",
                  file=out, flush=True)
        elif event.cause in ("capture_missed", "retake_started", "phone_reconnected", "phone_dropped",
                             "phone_rejoined"):
            print(f"[{event.time_s:8.2f} s] {'':<14} {event.cause} {event.data}", file=out, flush=True)

    return show


async def sim_scan(*, config: Path | None = None, store: Path, seed: int = 0,
                   plan_points: int | None = None, depth_decimation: int = 2,
                   out: TextIO | None = None, subject: Any | None = None, panel: bool = True,
                   qa_report: Callable[..., Path] | None = None,
                   on_ready: Callable[[RigController, Any], None] | None = None,
                   patient: ScanSubject | None = None,
                   lesion_changes: LesionChanges | None = None, render_scale: int = 1) -> ScanReport:
    """Build the simulated rig, run one scan, close everything; returns the scan's report.

    on_ready(controller, world) is called once the rig is up (tests inject faults from it);
    patient: who the scan is for (a synthetic identity), kept in its manifest; lesion_changes:
    the subject's grown and new spots at this visit; render_scale: the phones' pictures are this
    many times 192 x 256 px (SimOptions).
    """
    rig = load_rig(config or DEFAULT_RIG_PATH)
    hardware, world = await build_sim_rig(
        rig, SimOptions(seed=seed, depth_decimation=depth_decimation, panel=panel, lesion_changes=lesion_changes,
                        render_scale=render_scale),
        subject=subject)
    scans = ScanStore(store)
    with ThreadPoolExecutor(max_workers=1, thread_name_prefix="compute") as executor:
        # As the daemon's worker does (daemon/offload/worker.py): compile the planner's loops and the
        # TSDF's carving, or load them from numba's cache, while the rig starts, not between the sweep
        # and the capture (0.4-0.6 s of the 2 s there).
        executor.submit(warm_up, rig)
        executor.submit(carve.warm_up, rig.depth_camera_model)
        controller = RigController(rig, hardware, scans,
                                   settings=ScanSettings(seed=seed, plan_points=plan_points,
                                                         executor=executor, qa_report=qa_report))
        async with _started(controller, _print_events(controller, out) if out is not None else None):
            if on_ready is not None:
                on_ready(controller, world)
            report = await controller.scan(sim_scan_id(seed), patient)
    return report


@contextlib.asynccontextmanager
async def _started(controller: RigController, printer: Coroutine[Any, Any, None] | None) -> AsyncIterator[None]:
    """The controller started for the block, ``printer`` following its events; the printer is
    cancelled and the controller closed when the block ends."""
    task = asyncio.create_task(printer) if printer is not None else None
    try:
        await controller.start()
        yield
    finally:
        if task is not None:
            task.cancel()
            await asyncio.gather(task, return_exceptions=True)
        await controller.close()


async def _print_events(controller: RigController, out: TextIO) -> None:
    show = progress_printer(out)
    async for event in controller.machine.subscribe():
        show(event)


def run_sim_scan(*, time_scale: float | None = None, **kwargs: Any) -> ScanReport:
    """:func:`sim_scan` on a fresh virtual-time loop (``time_scale`` None = as fast as possible)."""
    from sim.clock import run_virtual

    return run_virtual(sim_scan(**kwargs), time_scale=time_scale)


async def sim_service(*, config: Path | None, store: Path, socket_path: Path | None, seed: int = 0,
                      plan_points: int | None = None, depth_decimation: int = 2,
                      group: str | None = None, subject_path: Path | None = None,
                      panel: bool = True, qa_report: Callable[..., Path] | None = None,
                      attach: Callable[[Any], None] | None = None,
                      lesion_changes: LesionChanges | None = None) -> int:
    """The daemon on the simulated rig until SIGINT/SIGTERM; attach(service) adds servers (the web);
    lesion_changes: the subject's grown and new spots at this visit."""
    from daemon.server.serve import serve
    from sim.body import load_subject

    rig = load_rig(config or DEFAULT_RIG_PATH)
    subject = load_subject(subject_path) if subject_path is not None else None
    hardware, _world = await build_sim_rig(
        rig, SimOptions(seed=seed, depth_decimation=depth_decimation, panel=panel, lesion_changes=lesion_changes),
        subject=subject)
    return await serve(rig, hardware, store=store,
                       settings=ScanSettings(seed=seed, plan_points=plan_points, qa_report=qa_report),
                       socket_path=socket_path, group=group, attach=attach)


async def sim_calibration_rotation(rig: Rig, stage: CuboidStage, *, store: Path, target: Path | None = None,
                                   seed: int = 0, depth_decimation: int = 1,
                                   out: TextIO | None = None) -> RotationReport:
    """The daemon's calibration rotation on the simulated rig with the cuboid in place (``stage``);
    its folder goes under ``store``/calibration. Returns the rotation's report. The depth cameras
    stream at full resolution (the corners of a half-resolution infrared image are too coarse to
    calibrate from)."""
    hardware, _world = await build_sim_rig(
        rig, SimOptions(seed=seed, depth_decimation=depth_decimation, panel=False), stage=stage)
    controller = RigController(rig, hardware, ScanStore(store), settings=ScanSettings(calibration_target=target))
    async with _started(controller, _print_stops(controller, out) if out is not None else None):
        return await (await controller.start_calibration(f"sim-seed{seed}"))


async def _print_stops(controller: RigController, out: TextIO) -> None:
    async for event in controller.machine.subscribe():
        if event.kind == "transition":
            print(f"[{event.time_s:8.2f} s] {event.state.value:<14} {event.cause}", file=out, flush=True)
        elif event.cause == "calibration stop" and event.data.get("angle_index", 0) % 8 == 7:
            print(f"[{event.time_s:8.2f} s] {'':<14} stop {event.data['angle_index'] + 1}: "
                  f"{event.data['pictures']} pictures", file=out, flush=True)
        elif event.cause == "calibration problem":
            print(f"[{event.time_s:8.2f} s] {'':<14} {event.data.get('problem')}", file=out, flush=True)
