"""The daemon's process around a built rig: signals, the compute worker, the controller and the
service, until SIGINT/SIGTERM. The real rig (daemon/server/real_rig.py) and the simulated one
(sim/run.py) differ only in how their devices are built."""

from __future__ import annotations

import asyncio
import dataclasses
import functools
import signal
from collections.abc import Callable
from pathlib import Path
from typing import Any

from daemon.jobs.controller import RigController
from daemon.jobs.scan import ScanSettings
from daemon.logs import follow_machine
from daemon.offload.worker import compute_pool, on_every_core, one_numeric_thread
from daemon.records.store import ScanStore
from daemon.rig.hardware import RigHardware
from daemon.server.looplag import freeze_startup_heap
from daemon.server.notify import SystemdNotifier
from daemon.server.service import RigService
from planner.rig import Rig


async def serve(rig: Rig, hardware: RigHardware, *, store: Path, settings: ScanSettings,
                socket_path: Path | None, group: str | None = None,
                attach: Callable[[Any], None] | None = None) -> int:
    """Serve ``hardware`` until SIGINT/SIGTERM; attach(service) adds servers (the web, the export
    queue). Compute runs in a worker process (daemon/offload/worker.py), so fusing and planning
    never stall the drive's heartbeat; ``settings.executor`` is that worker's pool. The worker
    runs on one core while the beam moves and the step after a scan (``settings.qa_report``, in
    STORING with the beam still) on every core (:func:`on_every_core`). The daemon's own numeric
    work runs on one thread (:func:`one_numeric_thread`)."""
    one_numeric_thread()
    stop = asyncio.Event()
    loop = asyncio.get_running_loop()
    for sig in (signal.SIGINT, signal.SIGTERM):
        loop.add_signal_handler(sig, stop.set)
    with compute_pool() as executor:
        after_scan = None if settings.qa_report is None else functools.partial(on_every_core, settings.qa_report)
        controller = RigController(rig, hardware, ScanStore(store), settings=dataclasses.replace(
            settings, executor=executor, qa_report=after_scan))
        service = RigService(controller, socket_path=socket_path, group=group,
                             notifier=SystemdNotifier.from_env())
        if attach is not None:
            attach(service)
        follow_machine(controller.machine)
        freeze_startup_heap()
        return await service.run(stop)
