"""The rig controller: hardware bring-up, one scan at a time, abort, latched fault and reset.

Shared by the long-running service (daemon/service.py) and the one-shot ``tbp scan --sim``, so
both run exactly the same scan code against whatever hardware they were given.
"""

from __future__ import annotations

import asyncio
from typing import Any

import structlog

from daemon.beam import BeamTracker
from daemon.errors import CalibrationRefused, ScanBusy, ScanRefused
from daemon.faults import AbortCause, AbortSource, FaultCause, FaultSource
from daemon.hardware import RigHardware
from daemon.safety import SafetyMonitor
from daemon.scan import Scan, ScanReport, ScanSettings
from daemon.states import ScanState, ScanStateMachine
from daemon.store import ScanStore
from planner.calibration.model import Calibration
from planner.rig import Rig

log = structlog.get_logger("daemon.controller")


def _led(name: str) -> Any:
    from drivers.panel import StatusLed

    return StatusLed[name]


class RigController:
    """Owns the state machine, the safety latch, the beam tracker and the current scan."""

    CONNECT_TIMEOUT_S = 10.0
    STOP_DECELERATION_DEG_S2 = 30.0
    STANDSTILL_TIMEOUT_S = 5.0
    STANDSTILL_DEG_S = 1e-3

    def __init__(
        self,
        rig: Rig,
        hardware: RigHardware,
        store: ScanStore,
        *,
        settings: ScanSettings = ScanSettings(),
        machine: ScanStateMachine | None = None,
    ) -> None:
        self.rig = rig
        self.hw = hardware
        self.store = store
        self.settings = settings
        self.machine = machine or ScanStateMachine()
        self.safety = SafetyMonitor(self.machine, hardware.drive)
        self.tracker = BeamTracker(hardware.drive)
        self.phone_errors: list[str | None] = [None] * len(hardware.phones)
        self.scan_task: asyncio.Task[ScanReport] | None = None
        self.current: Scan | None = None
        self.last_report: ScanReport | None = None
        self.safety.add_handler("beam quick stop", self._quick_stop)
        if hardware.panel is not None:
            self.safety.add_handler("panel fault light", self._panel_fault)
        self.safety.on_trip(self._cancel_scan)

    # ------------------------------------------------------------------ bring-up

    async def start(self) -> None:
        """Connect every device, enable the drive, follow the encoder, make sure the beam is still."""
        drive = self.hw.drive
        async with asyncio.timeout(self.CONNECT_TIMEOUT_S):
            await drive.connect()
            await self.tracker.start()
        try:
            async with asyncio.timeout(self.CONNECT_TIMEOUT_S):
                await drive.enable()
                await drive.stop(self.STOP_DECELERATION_DEG_S2)
        except Exception as exc:  # a drive left faulted (e.g. by a killed daemon) latches FAULT
            await self.safety.trip(FaultCause.of_error(FaultSource.DRIVE_ERROR, getattr(drive, "name", "beam"),
                                                       exc, "at start-up"))
        results = await asyncio.gather(
            *(self._connect_phone(i, p) for i, p in enumerate(self.hw.phones)), return_exceptions=True
        )
        for i, result in enumerate(results):
            if isinstance(result, BaseException):
                self.phone_errors[i] = f"{type(result).__name__}: {result}"
        if self.hw.panel is not None:
            async with asyncio.timeout(self.CONNECT_TIMEOUT_S):
                await self.hw.panel.connect()
            await self.hw.panel.set_status(_led("IDLE"))
        self.safety.start()
        log.info("rig_started", phones_failed=[e for e in self.phone_errors if e])

    async def _connect_phone(self, index: int, phone: Any) -> None:
        async with asyncio.timeout(self.CONNECT_TIMEOUT_S):
            await phone.connect()

    async def close(self) -> list[str]:
        """Stop the beam, stop watching, close every device; returns close failures."""
        if self.scan_task is not None and not self.scan_task.done():
            self.abort(AbortCause(AbortSource.DAEMON_STOPPING, "daemon", "stopping"))
            await asyncio.gather(self.scan_task, return_exceptions=True)
        await self.safety.stop()
        failures: list[str] = []
        try:
            await self.hw.drive.stop(self.STOP_DECELERATION_DEG_S2)
        except Exception as exc:  # reported; the drive is closed next anyway
            failures.append(f"beam stop: {type(exc).__name__}: {exc}")
        await self.tracker.stop()
        return failures + await self.hw.close()

    # ------------------------------------------------------------------ scans

    @property
    def busy(self) -> bool:
        return self.scan_task is not None and not self.scan_task.done()

    def start_scan(self, scan_id: str | None = None) -> asyncio.Task[ScanReport]:
        """Start a scan in the background; refuses while busy or while a fault is latched."""
        if self.busy:
            raise ScanBusy(self.machine.state.value, "a scan is already running")
        if self.safety.latched or self.machine.state is not ScanState.IDLE:
            raise ScanBusy(self.machine.state.value,
                           "fault latched: reset first (" + "; ".join(map(str, self.safety.causes)) + ")")
        if self.hw.panel is not None and self.hw.panel.estop_active:
            raise ScanBusy(self.machine.state.value, "e-stop pressed or its state unknown")
        self._close_left_open()
        calibration = self.calibration(scan_id)
        # The folder exists before anyone is told the scan started (docs/hardening.md, rule 2).
        try:
            folder = self.store.create(self.rig, scan_id=scan_id)
        except Exception as exc:  # StoreError, or an OSError the store did not expect
            refused = ScanRefused(scan_id, f"{type(exc).__name__}: {exc}")
            log.warning("scan_refused", scan_id=str(scan_id)[:80], error=str(refused))
            self.machine.progress("scan refused", error=str(refused))
            raise refused from exc
        self.current = Scan(self.rig, self.hw, self.machine, self.safety, self.tracker, folder,
                            settings=self.settings, calibration=calibration)
        self.scan_task = asyncio.create_task(self._run_scan(self.current), name="scan")
        return self.scan_task

    def _close_left_open(self) -> None:
        """Close the last scan's folder if the disk did not let the scan close it."""
        if self.current is not None and not self.busy:
            self.current.close_folder()

    def calibration(self, scan_id: str | None = None) -> Calibration | None:
        """The rig's installed calibration (read afresh for each scan), None for nominal poses.

        Raises CalibrationRefused (a ScanRefused: nothing started, no folder) when the file is
        unreadable or for other cameras; an old calibration (rig file ``calibration.max_age_days``)
        is used with a warning.
        """
        from daemon.utc import utc_now
        from planner.calibration.installed import CalibrationMismatch, age_days, calibration_path, installed_calibration
        from planner.calibration.model import CalibrationFileError

        try:
            calibration = installed_calibration(self.rig)
        except (CalibrationMismatch, CalibrationFileError) as exc:
            refused = CalibrationRefused(scan_id, str(calibration_path(self.rig)), str(exc))
            log.warning("scan_refused", scan_id=str(scan_id)[:80], error=str(refused))
            self.machine.progress("scan refused", error=str(refused))
            raise refused from exc
        if calibration is None:
            log.warning("calibration_missing", path=str(calibration_path(self.rig)),
                        effect="planning and the TSDF use the rig file's nominal poses")
            return None
        age = age_days(calibration, utc_now())
        limit = self.rig.calibration.max_age_days
        if age is None or age > limit:
            log.warning("calibration_old", path=calibration.path, made=calibration.created_utc,
                        age_days=None if age is None else round(age, 1), max_age_days=limit,
                        effect="calibrate again (tbp calibrate)")
            self.machine.progress("calibration_old", made=calibration.created_utc, max_age_days=limit)
        return calibration

    async def scan(self, scan_id: str | None = None) -> ScanReport:
        """Run one scan to its end (completed, aborted or faulted) and return its report."""
        return await self.start_scan(scan_id)

    async def _run_scan(self, scan: Scan) -> ScanReport:
        await self._panel("SCANNING", light=True)
        try:
            report = await scan.run()
        finally:
            await self._panel("FAULT" if self.safety.latched else "IDLE", light=False)
        self.last_report = report
        return report

    def abort(self, cause: AbortCause) -> bool:
        """Abort the running scan (stop button, control API); False when none runs."""
        if not self.busy or self.current is None:
            return False
        self.current.abort(cause)
        return True

    async def trip(self, cause: FaultCause) -> None:
        """A safety trip (e-stop, panel lost): quick stop, latched FAULT."""
        await self.safety.trip(cause)

    async def reset(self, cause: str = "operator reset") -> None:
        """Clear a latched fault: drive fault reset and re-enable; refused while the e-stop is held."""
        panel = self.hw.panel
        if panel is not None and getattr(panel, "estop_active", False):
            raise ScanBusy(self.machine.state.value, "e-stop still pressed: release it before reset")
        if self.busy:
            raise ScanBusy(self.machine.state.value, "the faulted scan is still closing its folder")

        self._close_left_open()

        async def recover() -> None:
            drive = self.hw.drive
            if getattr(drive, "fault", None) is not None:
                await drive.reset_fault()
            await drive.enable()
            await self._panel("IDLE")

        await self.safety.reset(cause, recover)

    async def _quick_stop(self) -> None:
        """Quick stop, then wait until the encoder shows the beam standing still."""
        await self.hw.drive.quick_stop()
        async with asyncio.timeout(self.STANDSTILL_TIMEOUT_S):
            while True:
                sample = await self.tracker.next_sample()
                if abs(sample.speed_deg_s) < self.STANDSTILL_DEG_S:
                    return

    def _cancel_scan(self, cause: FaultCause) -> None:
        if self.current is not None and self.busy:
            self.current.cancel_for_fault()

    async def _panel_fault(self) -> None:
        await self.hw.panel.set_status(_led("FAULT"))

    async def _panel(self, led: str, *, light: bool | None = None) -> None:
        """Status LED (and the subject lights); a panel that cannot be told is a lost panel."""
        if self.hw.panel is None:
            return
        try:
            await self.hw.panel.set_status(_led(led))
            if light is not None:
                await self.hw.panel.set_light(light)
        except Exception as exc:  # the trip records it as a fault cause
            await self.safety.trip(FaultCause.of_error(FaultSource.PANEL, "panel", exc, f"set_status({led}) failed"))

    # ------------------------------------------------------------------ status

    def status(self) -> dict[str, Any]:
        """The rig's state for the control API."""
        latest = self.tracker.latest
        return {
            "state": self.machine.state.value,
            "scan_id": self.machine.scan_id,
            "fault_causes": [cause.as_dict() for cause in self.safety.causes],
            "beam_angle_deg": None if latest is None else latest.angle_deg,
            "beam_speed_deg_s": None if latest is None else latest.speed_deg_s,
            "phones_failed": [e for e in self.phone_errors if e],
            "last_scan": None if self.last_report is None else self.last_report.as_dict(),
        }
