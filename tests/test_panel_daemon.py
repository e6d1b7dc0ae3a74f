"""The operator panel in the running daemon: START starts a scan, the e-stop trips the rig,
a lost panel trips it too, and the panel's LED follows the rig's state.

The daemon rig of tests/daemon_rigs.py (simulated drive and depth cameras, mock phones) gets
a simulated panel on a socketpair; everything runs in virtual time.
"""

from __future__ import annotations

import asyncio
import socket
from collections.abc import Awaitable, Callable
from pathlib import Path

import pytest

from daemon.errors import ScanBusy
from daemon.faults import FaultCause, FaultSource
from daemon.jobs.controller import RigController
from daemon.jobs.scan import ScanSettings
from daemon.records.store import ScanStore
from daemon.server.service import RigService
from drivers.panel import OperatorPanel, StatusLed
from drivers.sim.panel import SimulatedPanel
from sim.clock import run_virtual
from tests.daemon_rigs import PLAN_POINTS, RIG, build_rig

pytestmark = pytest.mark.slow

Scenario = Callable[[RigController, SimulatedPanel], Awaitable[None]]


def run_service(tmp_path: Path, scenario: Scenario) -> None:
    async def main() -> None:
        hardware, _world = await build_rig(RIG, 0)
        a, b = socket.socketpair()
        (host_r, host_w), (dev_r, dev_w) = (await asyncio.open_connection(sock=a),
                                            await asyncio.open_connection(sock=b))
        sim = SimulatedPanel(dev_r, dev_w)
        sim_task = asyncio.create_task(sim.run())
        hardware.panel = OperatorPanel(host_r, host_w)
        controller = RigController(RIG, hardware, ScanStore(tmp_path), settings=ScanSettings(plan_points=PLAN_POINTS))
        service = RigService(controller)
        await service.start()
        try:
            await scenario(controller, sim)
        finally:
            await service.stop()
            sim_task.cancel()
            await asyncio.gather(sim_task, return_exceptions=True)
            sim.close()

    run_virtual(main())


async def until(condition: Callable[[], bool], timeout_s: float = 30.0) -> None:
    async with asyncio.timeout(timeout_s):
        while not condition():
            await asyncio.sleep(0.05)


def test_start_button_scans_and_estop_trips_until_released_and_reset(tmp_path: Path) -> None:
    async def scenario(controller: RigController, sim: SimulatedPanel) -> None:
        await until(lambda: sim.led is StatusLed.IDLE)
        sim.press_start()
        await until(lambda: sim.led is StatusLed.SCANNING)
        assert controller.busy
        sim.press_estop()
        await until(lambda: controller.machine.state.value == "FAULT")
        await until(lambda: sim.led is StatusLed.FAULT)
        assert FaultCause(FaultSource.ESTOP, "panel", "e-stop pressed") in controller.safety.causes
        await until(lambda: not controller.busy)
        with pytest.raises(ScanBusy, match="e-stop still pressed"):
            await controller.reset()
        sim.release_estop()
        await until(lambda: not controller.hw.panel.estop_active)
        await controller.reset()
        await until(lambda: sim.led is StatusLed.IDLE)
        assert controller.machine.state.value == "IDLE"

    run_service(tmp_path, scenario)


def test_lost_panel_trips_the_rig(tmp_path: Path) -> None:
    async def scenario(controller: RigController, sim: SimulatedPanel) -> None:
        await until(lambda: sim.led is StatusLed.IDLE)
        sim.stop_heartbeats()
        await until(lambda: controller.machine.state.value == "FAULT")
        assert [c.source for c in controller.safety.causes] == [FaultSource.PANEL_LOST]

    run_service(tmp_path, scenario)


def test_start_with_a_store_that_cannot_take_a_scan_is_refused_on_record(tmp_path: Path,
                                                                        monkeypatch: pytest.MonkeyPatch) -> None:
    """The panel's START takes the control API's path: no scan is started, the refusal is streamed."""
    import shutil

    monkeypatch.setattr(ScanStore, "RESERVE_BYTES", shutil.disk_usage(tmp_path).free + (1 << 30))

    async def scenario(controller: RigController, sim: SimulatedPanel) -> None:
        await until(lambda: sim.led is StatusLed.IDLE)
        sim.press_start()
        await until(lambda: any(e.cause == "scan refused" for e in controller.machine.history))
        refused = [e for e in controller.machine.history if e.cause == "scan refused"][0]
        assert "StoreFull" in refused.data["error"]
        assert not controller.busy and controller.machine.state.value == "IDLE"
        assert sim.led is StatusLed.IDLE
        assert [p for p in tmp_path.iterdir() if p.is_dir()] == []  # no folder left in progress

    run_service(tmp_path, scenario)
