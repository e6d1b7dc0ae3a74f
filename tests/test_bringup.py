"""The bring-up's re-probe of missing devices (daemon/rig/bringup.py), in virtual time."""

from __future__ import annotations

import asyncio
from pathlib import Path

import pytest
import structlog

from daemon.jobs.controller import RigController
from daemon.records.store import ScanStore
from daemon.rig.bringup import BringUp
from daemon.rig.hardware_config import Timeouts
from sim.clock import run_virtual
from tests.daemon_rigs import RIG, build_rig


def test_a_device_that_stays_missing_is_probed_less_often_and_found_soon_after_it_comes(tmp_path: Path) -> None:
    async def main() -> tuple[list[float], float, int]:
        hardware, _world = await build_rig(RIG, 0)
        phone = hardware.phones[3]
        phone.reconnectable = False
        attempts: list[float] = []
        connect = phone.connect

        async def counted(timeout_s: float | None = None) -> None:
            attempts.append(asyncio.get_running_loop().time())
            await connect(timeout_s)

        phone.connect = counted
        controller = RigController(RIG, hardware, ScanStore(tmp_path / "scans"))
        changes: list[bool] = []
        assert not await controller.bringup.once()
        reprobe = asyncio.create_task(controller.bringup.run(changes.append))
        try:
            await asyncio.sleep(60.0)
            phone.reconnectable = True
            plugged = asyncio.get_running_loop().time()
            while not changes:
                await asyncio.sleep(0.1)
            found_after = asyncio.get_running_loop().time() - plugged
            probes = controller.bringup.devices[RIG.phones[3].id].probes
        finally:
            reprobe.cancel()
            await asyncio.gather(reprobe, return_exceptions=True)
            await controller.close()
        return attempts, found_after, probes

    attempts, found_after, probes = run_virtual(main())
    gaps = [round(b - a, 1) for a, b in zip(attempts, attempts[1:], strict=False)]  # + a round's own probes
    reprobe_s = Timeouts().reprobe_s  # the hardware default
    assert gaps[:4] == [reprobe_s, 2 * reprobe_s, 4 * reprobe_s, BringUp.BACKOFF_MAX_S]
    assert set(gaps[3:]) == {BringUp.BACKOFF_MAX_S}
    assert found_after <= BringUp.BACKOFF_MAX_S
    assert probes == len(attempts)


def test_each_device_is_opened_with_its_name_in_the_log_context_of_the_tasks_it_starts(tmp_path: Path) -> None:
    async def main() -> dict[str, str | None]:
        hardware, _world = await build_rig(RIG, 0)
        seen: dict[str, str | None] = {}
        for index in (0, 5):
            phone = hardware.phones[index]
            connect = phone.connect

            async def bound(timeout_s: float | None = None, phone=phone, connect=connect) -> None:
                async def reader() -> None:  # a driver task started by connect(), e.g. its reader
                    seen[phone.serial] = structlog.contextvars.get_contextvars().get("device")

                await asyncio.create_task(reader())
                await connect(timeout_s)

            phone.connect = bound
        controller = RigController(RIG, hardware, ScanStore(tmp_path / "scans"))
        try:
            assert await controller.bringup.once()
            seen["after"] = structlog.contextvars.get_contextvars().get("device")
        finally:
            await controller.close()
        return seen

    seen = run_virtual(main())
    assert seen == {RIG.phones[0].serial: RIG.phones[0].id, RIG.phones[5].serial: RIG.phones[5].id, "after": None}


def test_two_bring_ups_at_once_never_connect_one_device_twice(tmp_path: Path) -> None:
    """The service's re-probe and the reset's reconnect may ask at the same moment: one waits for
    the other (two connects on one drive started two drive guards)."""

    async def main() -> tuple[int, list[bool]]:
        hardware, _world = await build_rig(RIG, 0)
        drive = hardware.drive
        connect = drive.connect
        running, most = 0, 0

        async def slow() -> None:
            nonlocal running, most
            running += 1
            most = max(most, running)
            try:
                await asyncio.sleep(0.5)  # a CAN adapter slow to open
                await connect()
            finally:
                running -= 1

        drive.connect = slow  # type: ignore[method-assign]
        controller = RigController(RIG, hardware, ScanStore(tmp_path / "scans"))
        try:
            ready = await asyncio.gather(controller.bringup.once(), controller.bringup.once(due_only=True))
        finally:
            await controller.close()
        return most, list(ready)

    most, ready = run_virtual(main())
    assert most == 1 and ready == [True, True]


def test_a_renewed_drive_is_everyones_drive_at_once(tmp_path: Path) -> None:
    """A drive whose link died is replaced by the device set alone: the jobs, the safety watch and
    the encoder follower all act on the fresh one."""
    from daemon.rig.hardware import RigHardware
    from drivers.motor.errors import HeartbeatLost
    from tests.daemon_mocks import MockDrive

    async def main() -> None:
        made: list[MockDrive] = []

        def fresh() -> MockDrive:
            made.append(MockDrive())
            return made[-1]

        hardware = RigHardware(fresh(), [], [], drive_factory=fresh)
        controller = RigController(RIG, hardware, ScanStore(tmp_path / "scans"))
        try:
            assert await controller.bringup.once()
            first = hardware.drive
            await first.close()  # the link died
            await controller.bringup.reconnect_drive()
            second = hardware.drive
            assert second is made[-1] and second is not first and controller.bringup.devices["drive"].ok
            await asyncio.sleep(0.1)
            assert controller.tracker.latest is second.latest
            second.fault = HeartbeatLost("beam", "OPERATION ENABLED", 0.4, 0.35)
            await asyncio.sleep(0.1)
            assert controller.safety.latched and "no heartbeat" in str(controller.safety.causes[0])
            with pytest.raises(AttributeError):
                hardware.drive = first  # type: ignore[misc]
        finally:
            await controller.close()

    run_virtual(main())
