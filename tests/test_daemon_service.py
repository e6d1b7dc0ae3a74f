"""The daemon service in-process: start-up recovery, control API scan/abort/reset, health."""

from __future__ import annotations

import asyncio
import json
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import pytest

from daemon.faults import FaultSource
from daemon.jobs.controller import RigController
from daemon.jobs.scan import ScanSettings
from daemon.records.store import ScanStore
from daemon.server.control import CommandFailed, ControlClient
from daemon.server.notify import SystemdNotifier
from daemon.server.service import RigService
from sim.clock import run_virtual
from tests.daemon_rigs import PLAN_POINTS, RIG, build_rig

pytestmark = pytest.mark.slow


class _Notes(SystemdNotifier):
    """Records what would go to systemd."""

    def __init__(self) -> None:
        super().__init__(None)
        self.sent: list[str] = []

    def notify(self, *lines: str) -> bool:
        self.sent.extend(lines)
        return True


def test_service_recovers_then_scans_and_aborts_over_the_socket(tmp_path: Path) -> None:
    store_root = tmp_path / "scans"
    left = ScanStore(store_root).create(RIG, scan_id="killed")  # a folder a killed daemon left
    sock = tmp_path / "control.sock"
    notes = _Notes()

    async def main() -> None:
        hardware, _world = await build_rig(RIG, 0)
        with ThreadPoolExecutor(max_workers=1) as executor:
            controller = RigController(RIG, hardware, ScanStore(store_root), settings=ScanSettings(
                executor=executor, plan_points=PLAN_POINTS))
            service = RigService(controller, socket_path=sock, notifier=notes)
            await service.start()
            try:
                client = ControlClient(sock)
                status = await client.status()
                assert status["state"] == "IDLE" and status["healthy"] is True
                assert [r["scan_id"] for r in status["recovered_scans"]] == ["killed"]
                assert status["beam_speed_deg_s"] == 0.0
                assert "READY=1" in notes.sent

                events = client.subscribe()
                await anext(events)
                started = await client.scan(scan_id="api-1")
                assert started["scan_id"] == "api-1"
                with pytest.raises(CommandFailed) as busy:
                    await client.scan(scan_id="api-2")
                assert busy.value.error_type == "ScanBusy"
                seen = []
                async for event in events:
                    seen.append(event["state"])
                    if event["kind"] == "progress" and event["cause"] == "captured" \
                            and event["data"]["captured"] == 30:
                        assert (await client.abort())["aborted"] is True
                    if event["kind"] == "transition" and event["state"] == "IDLE":
                        break
                assert "ABORTING" in seen and "CAPTURING" in seen
                last = (await client.status())["last_scan"]
                assert last["outcome"] == "ABORTED" and last["captured"] >= 30
                assert (await client.reset())["state"] == "IDLE"  # nothing latched: a no-op
                assert any(line.startswith("STATUS=CAPTURING") for line in notes.sent)
            finally:
                await service.stop()
            assert "STOPPING=1" in notes.sent

    run_virtual(main())
    manifest = json.loads((left.path / "manifest.json").read_text())
    assert manifest["state"] == "incomplete" and manifest["in_progress"] is False
    aborted = next(p for p in store_root.iterdir() if p.name.endswith("api-1"))
    assert json.loads((aborted / "manifest.json").read_text())["state"] == "aborted"


def test_a_lost_drive_heartbeat_latches_fault_and_the_daemon_stays_up(tmp_path: Path) -> None:
    """The watchdog is for a wedged daemon: a silent drive latches FAULT (the operator sees why
    and resets), it does not get the daemon restarted."""
    async def main() -> None:
        hardware, world = await build_rig(RIG, 0)
        controller = RigController(RIG, hardware, ScanStore(tmp_path))
        service = RigService(controller, notifier=_Notes())
        await service.start()
        try:
            await asyncio.sleep(0.5)
            assert not service.health()
            world.sim_drive.stop_heartbeat()
            await asyncio.sleep(1.0)
            assert not service.health()
            assert controller.machine.state.value == "FAULT"
            assert any(c.source is FaultSource.DRIVE_FAULT and "HeartbeatLost" in c.detail
                       for c in controller.safety.causes)
        finally:
            await service.stop()

    run_virtual(main())


def test_a_missing_phone_keeps_the_rig_not_ready_until_it_is_plugged_in(tmp_path: Path) -> None:
    """Issue 13 item 3: the daemon stays up, names the phone, its address and what to check
    (status, STATUS=), refuses START, re-probes, and sends READY=1 once the phone answers."""
    from daemon.errors import ScanRefused

    notes = _Notes()

    async def main() -> None:
        hardware, _world = await build_rig(RIG, 0)
        hardware.addresses["cam3"] = "usb:TBPSIM03"
        phone = hardware.phones[3]
        phone.reconnectable = False  # unplugged: every connect is refused
        controller = RigController(RIG, hardware, ScanStore(tmp_path / "scans"))
        service = RigService(controller, notifier=notes)
        loop = asyncio.get_running_loop()
        started = loop.time()
        await service.start()
        try:
            status = service.status()
            named_after_s = loop.time() - started
            assert status["ready"] is False and "READY=1" not in notes.sent
            cam3 = next(d for d in status["devices"] if d["device"] == "cam3")
            assert cam3["ok"] is False and cam3["address"] == "usb:TBPSIM03" and "USB" in cam3["check"]
            assert all(d["ok"] for d in status["devices"] if d["device"] != "cam3")
            assert any(line.startswith("STATUS=NOT READY: cam3 (usb:TBPSIM03)") for line in notes.sent)
            with pytest.raises(ScanRefused, match="cam3"):
                await service.scan(scan_id="too-early")
            await asyncio.sleep(10.0)
            assert not service.status()["ready"]  # still unplugged: re-probed, still named
            phone.reconnectable = True  # plugged back in
            back = loop.time()
            while not service.status()["ready"]:
                await asyncio.sleep(0.1)
            reused_after_s = loop.time() - back
            assert "READY=1" in notes.sent and not service.health()
            assert named_after_s <= 5.0 and reused_after_s <= 10.0, (named_after_s, reused_after_s)
        finally:
            await service.stop()

    run_virtual(main())


def test_the_watchdog_is_pinged_only_on_proof_that_every_safety_part_runs(tmp_path: Path) -> None:
    """health() names what stopped: the worst loop lag since the last ping (not the last sample),
    the drive guard, the drive's own tasks, the safety watch, the encoder follower."""
    async def main() -> list[list[str]]:
        hardware, _world = await build_rig(RIG, 0)
        controller = RigController(RIG, hardware, ScanStore(tmp_path))
        service = RigService(controller, notifier=_Notes())
        await service.start()
        seen: list[list[str]] = []
        try:
            await asyncio.sleep(0.5)
            seen.append(service.health())
            service.lag.record("IDLE", 1.2)  # one stall, then the loop is on time again
            service.lag.record("IDLE", 0.001)
            seen.append([p for p in service.health() if "late" in p])
            assert not service._watchdog_check()  # the ping over that interval is withheld
            assert service._watchdog_check()  # the next interval is clean
            drive = controller.hw.drive
            assert drive.guard is not None
            await drive.guard.stop()
            await asyncio.sleep(0.1)
            seen.append(service.health())
            controller.safety._watch.cancel()  # type: ignore[union-attr]
            await controller.tracker.stop()
            await asyncio.sleep(0.1)
            seen.append(service.health())
        finally:
            await service.stop()
        return seen

    healthy, stalled, guard_gone, watch_gone = run_virtual(main())
    assert healthy == []
    assert stalled == ["event loop ran 1.200 s late (limit 1 s)"]
    assert "beam: drive guard not running" in guard_gone
    assert {"safety watch on the drive not running", "encoder not followed"} <= set(watch_gone)
