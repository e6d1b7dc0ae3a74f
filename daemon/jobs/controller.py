"""The rig controller: hardware bring-up, one job at a time (a scan or a calibration rotation),
abort, latched fault and reset.

Shared by the long-running service (daemon/server/service.py) and the one-shot ``tbp scan --sim``, so
both run exactly the same scan code against whatever hardware they were given.
"""

from __future__ import annotations

import asyncio
import functools
from collections.abc import Awaitable, Callable
from typing import Any

import structlog

from daemon.clinic.patient import ScanSubject
from daemon.errors import CalibrationRefused, DevicesMissing, ScanBusy, ScanRefused
from daemon.faults import AbortCause, AbortSource, FaultCause, FaultSource
from daemon.jobs.calibration_rotation import CalibrationRotation, RotationReport, create_rotation_folder
from daemon.jobs.job import RigJob
from daemon.jobs.scan import Scan, ScanReport, ScanSettings
from daemon.jobs.scan_time import job_time
from daemon.records.atomic import StoreError
from daemon.records.store import ScanStore
from daemon.rig.beam import BeamTracker, trace_capacity
from daemon.rig.bringup import BringUp
from daemon.rig.hardware import RigHardware
from daemon.rig.safety import SafetyMonitor
from daemon.rig.states import ScanState, ScanStateMachine, state_groups
from daemon.utc import utc_now
from drivers.errors import DeviceGone
from drivers.panel.protocol import StatusLed
from planner.calibration.installed import CalibrationMismatch, age_days, calibration_path, installed_calibration
from planner.calibration.model import Calibration, CalibrationFileError
from planner.calibration.target import DEFAULT_TARGET_PATH, TargetError, load_target
from planner.rig import Rig
from planner.schedule import RigTime, scan_rig_time

log = structlog.get_logger("daemon.jobs.controller")


class RigController:
    """Runs the rig's jobs on its devices: the state machine (and its fault latch), the safety
    monitor, the beam tracker, the bring-up and the current job. The devices are the
    ``hardware``'s (:class:`RigHardware`), read from it whenever they are used."""

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
        self.safety = SafetyMonitor(self.machine)
        self.tracker = BeamTracker(capacity=trace_capacity(rig))
        self.scan_task: asyncio.Task[Any] | None = None
        """The running job's task (a scan's or a calibration rotation's), None before the first."""
        self._starting = False
        self.current: RigJob | None = None
        self.last_report: ScanReport | None = None
        self.last_calibration: RotationReport | None = None
        self.safety.add_handler("beam quick stop", self._quick_stop)
        if hardware.panel is not None:
            self.safety.add_handler("panel fault light", self._panel_fault)
        self.safety.on_trip(self._cancel_scan)
        self.bringup = BringUp(rig, hardware, self.safety, self.tracker,
                               stop_deceleration_deg_s2=self.STOP_DECELERATION_DEG_S2)

    # ------------------------------------------------------------------ bring-up

    async def start(self) -> None:
        """Bring every device up once (each under its timeout): connect the drive, follow the
        encoder, make sure the beam is still, connect the phones and the panel, find the depth
        cameras. Raises DevicesMissing when the drive did not come up (a one-shot scan cannot
        go on); other missing devices are recorded (:attr:`bringup`) and refuse scans."""
        ready = await self.bringup.once()
        log.info("rig_started", ready=ready, missing=[d.name for d in self.bringup.missing()])
        if not self.bringup.devices["drive"].ok:
            raise DevicesMissing(self.bringup.summary())

    async def show_idle(self) -> None:
        """The panel's status light at rest (FAULT while a fault is latched)."""
        await self.bringup.show_idle()

    JOB_STOP_TIMEOUT_S = 15.0
    """Longest wait for an aborted job to close its folder at shutdown (systemd waits 30 s in all)."""

    async def close(self) -> list[str]:
        """Stop the job, bring the beam to a standstill with the safety watch still on, then close
        every device; returns what failed. The beam is never left turning without a stop command:
        a controlled stop when the drive is healthy, the quick stop otherwise (sent even with a
        fault latched), and a drive that cannot be seen to stand keeps its heartbeat consumer on,
        so it stops itself when the host heartbeat ends."""
        failures: list[str] = []
        task = self.scan_task
        if task is not None and not task.done():
            self.abort(AbortCause(AbortSource.DAEMON_STOPPING, "daemon", "stopping"))
            done, _ = await asyncio.wait({task}, timeout=self.JOB_STOP_TIMEOUT_S)
            if not done:
                failures.append(f"job: not closed within {self.JOB_STOP_TIMEOUT_S:g} s of the abort")
                task.cancel()
        failures += await self._halt_beam()
        await self.safety.stop()
        await self.tracker.stop()
        return failures + await self.hw.close()

    async def _halt_beam(self) -> list[str]:
        """The beam at a standstill before anything closes: a controlled stop, or the quick stop."""
        drive = self.hw.drive
        if drive.closed or drive.latest is None:
            return []
        try:
            async with asyncio.timeout(self.STANDSTILL_TIMEOUT_S):
                if drive.fault is None and not self.safety.latched:
                    await drive.stop(self.STOP_DECELERATION_DEG_S2)
                else:
                    await drive.quick_stop()
            return []
        except Exception as exc:  # the quick stop next; the drive's own consumer is the last resort
            failure = f"beam stop: {type(exc).__name__}: {exc}"
        try:
            await drive.quick_stop()
        except Exception as exc:  # reported; drive.close() leaves the consumer on if it still turns
            failure += f"; quick stop: {type(exc).__name__}: {exc}"
        return [failure]

    # ------------------------------------------------------------------ jobs

    @property
    def busy(self) -> bool:
        return self._starting or (self.scan_task is not None and not self.scan_task.done())

    async def start_scan(self, scan_id: str | None = None, subject: ScanSubject | None = None
                         ) -> asyncio.Task[ScanReport]:
        """Start a scan in the background once its folder exists (refused while busy, faulted,
        not ready or e-stopped, or when the installed calibration cannot be used); ``subject``: the
        patient it is for, kept in its manifest."""
        return await self._start(scan_id, functools.partial(self._new_scan, subject=subject))

    async def start_calibration(self, rotation_id: str | None = None) -> asyncio.Task[RotationReport]:
        """Start a calibration rotation (the cuboid in place) in the background once its folder
        exists; refused like a scan."""
        return await self._start(rotation_id, self._new_rotation)

    async def scan(self, scan_id: str | None = None, subject: ScanSubject | None = None) -> ScanReport:
        """Run one scan to its end (completed, aborted or faulted) and return its report."""
        return await (await self.start_scan(scan_id, subject))

    async def _start(self, job_id: str | None, make: Callable[[str | None], Awaitable[RigJob]]) -> asyncio.Task[Any]:
        """The one start path of every job: the refusals, then the job made (its folder exists
        before anyone is told it started: docs/hardening.md, rule 2), then run in the background."""
        self._check_startable(job_id)
        self._starting = True  # a second START meanwhile is refused as busy
        try:
            await self._close_left_open()
            job = await make(job_id)
        finally:
            self._starting = False
        self.current = job
        self.scan_task = asyncio.create_task(self._run_job(job), name=job.kind)
        return self.scan_task

    def _check_startable(self, job_id: str | None) -> None:
        """Refuse a job while busy, faulted, not ready or e-stopped."""
        if self.busy:
            raise ScanBusy(self.machine.state.value, "a scan or calibration rotation is already running")
        if self.safety.latched or self.machine.state is not ScanState.IDLE:
            raise ScanBusy(self.machine.state.value,
                           "fault latched: reset first (" + "; ".join(map(str, self.safety.causes)) + ")")
        if not self.bringup.ready:
            raise self._refused("scan", job_id, ScanRefused(job_id, self.bringup.summary()))
        if self.hw.panel is not None and self.hw.panel.estop_active:
            raise ScanBusy(self.machine.state.value, "e-stop pressed or its state unknown")

    def _refused(self, kind: str, job_id: object, refused: ScanRefused) -> ScanRefused:
        """Log and stream a refusal; returns it to raise."""
        log.warning(f"{kind}_refused", scan_id=str(job_id)[:80], error=str(refused))
        self.machine.progress(f"{kind} refused", error=str(refused))
        return refused

    async def _new_scan(self, scan_id: str | None, subject: ScanSubject | None = None) -> Scan:
        calibration = await self.calibration(scan_id)
        try:  # mkdir, manifest, fsyncs in a thread: on a busy disk that took 90 ms on the loop
            folder = await asyncio.to_thread(self.store.create, self.rig, scan_id=scan_id, subject=subject)
        except Exception as exc:  # StoreError, or an OSError the store did not expect
            raise self._refused("scan", scan_id, ScanRefused(scan_id, f"{type(exc).__name__}: {exc}")) from exc
        return Scan(self.rig, self.hw, self.machine, self.safety, self.tracker, folder,
                    settings=self.settings, calibration=calibration)

    async def _new_rotation(self, rotation_id: str | None) -> CalibrationRotation:
        try:
            target = await asyncio.to_thread(load_target, self.settings.calibration_target or DEFAULT_TARGET_PATH)
            made_id, folder = await asyncio.to_thread(create_rotation_folder, self.store.root, rotation_id)
        except (TargetError, StoreError, OSError) as exc:
            raise self._refused("calibration", rotation_id,
                                ScanRefused(rotation_id, f"calibration rotation: {type(exc).__name__}: {exc}")) from exc
        return CalibrationRotation(self.rig, self.hw, self.machine, self.safety, self.tracker, target,
                                   made_id, folder)

    async def _run_job(self, job: RigJob) -> Any:
        """Run ``job`` in a task of its own: a cancel of this task aborts the job, which still
        stops the beam and closes its folder; the cancel is passed on once the job ended (a second
        one at once, the job then ending by itself)."""
        await self._panel(StatusLed.SCANNING, light=True)
        run = asyncio.create_task(job.run(), name=f"{job.kind}-{job.job_id}-end")
        try:
            try:
                report = await asyncio.shield(run)
            except asyncio.CancelledError:
                job.abort(AbortCause(AbortSource.DAEMON_STOPPING, "daemon", f"the {job.kind}'s task was cancelled"))
                await asyncio.wait([run])
                raise
        finally:
            await self._panel(StatusLed.FAULT if self.safety.latched else StatusLed.IDLE, light=False)
        if isinstance(job, Scan):
            self.last_report = report
        else:
            self.last_calibration = report
        return report

    async def _close_left_open(self) -> None:
        """Close the last job's folder if the disk did not let the job close it."""
        if self.current is not None and not (self.scan_task is not None and not self.scan_task.done()):
            await self.current.close_folder()

    async def calibration(self, scan_id: str | None = None) -> Calibration | None:
        """The rig's installed calibration (read afresh for each scan, in a thread), None for
        nominal poses.

        Raises CalibrationRefused (a ScanRefused: nothing started, no folder) when the file is
        unreadable or for other cameras; an old calibration (rig file ``calibration.max_age_days``)
        is used with a warning.
        """
        try:
            calibration = await asyncio.to_thread(installed_calibration, self.rig)
        except (CalibrationMismatch, CalibrationFileError) as exc:
            refused = CalibrationRefused(scan_id, str(calibration_path(self.rig)), str(exc))
            raise self._refused("scan", scan_id, refused) from exc
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

    def abort(self, cause: AbortCause) -> bool:
        """Abort the running job (stop button, control API); False when none runs."""
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
        if panel is not None and panel.estop_active:
            raise ScanBusy(self.machine.state.value, "e-stop still pressed: release it before reset")
        if self.busy:
            kind = self.current.kind if self.current is not None else "job"
            raise ScanBusy(self.machine.state.value,
                           f"the faulted {kind} is still closing its folder" if self.safety.latched
                           else f"a {kind} is running: abort it first")

        await self._close_left_open()

        async def recover() -> None:
            drive = self.hw.drive
            if drive.closed or (self.hw.renewable and isinstance(drive.fault, DeviceGone)):
                # the link died (CAN unplugged, bridge gone, drive powered off): a fresh link
                await self.bringup.reconnect_drive()
                drive = self.hw.drive
            if drive.fault is not None:
                await drive.reset_fault()
            await drive.enable()
            await self._panel(StatusLed.IDLE)

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
        if self.hw.panel is not None:
            await self.hw.panel.set_status(StatusLed.FAULT)

    async def _panel(self, led: StatusLed, *, light: bool | None = None) -> None:
        """Status LED (and the subject lights); a panel that cannot be told is a lost panel."""
        if self.hw.panel is None:
            return
        try:
            await self.hw.panel.set_status(led)
            if light is not None:
                await self.hw.panel.set_light(light)
        except Exception as exc:  # the trip records it as a fault cause
            await self.safety.trip(FaultCause.of_error(FaultSource.PANEL, "panel", exc, f"set_status({led.name}) failed"))

    # ------------------------------------------------------------------ status

    @functools.cached_property
    def rig_time(self) -> RigTime:
        """The rig time of a scan on this rig (the sweep, the reposition, the capture rotation)."""
        return scan_rig_time(self.rig)

    def job_time(self) -> dict[str, Any] | None:
        """The running job's elapsed and remaining time (daemon/jobs/scan_time.py); None without one."""
        if not self.busy or self.current is None:
            return None
        machine = self.machine
        return job_time(machine.state, machine.started_s, machine.entered_s, asyncio.get_running_loop().time(),
                        self.rig_time if self.current.kind == "scan" else None)

    def status(self) -> dict[str, Any]:
        """The rig's state for the control API."""
        latest = self.tracker.latest
        return {
            "state": self.machine.state.value,
            "states": state_groups(),
            "scan_id": self.machine.scan_id,
            "job_time": self.job_time(),
            "counts": dict(self.machine.counts),
            "fault_causes": [cause.as_dict() for cause in self.safety.causes],
            "beam_angle_deg": None if latest is None else latest.angle_deg,
            "beam_speed_deg_s": None if latest is None else latest.speed_deg_s,
            "ready": self.bringup.ready,
            "devices": [d.as_dict() for d in self.bringup.devices.values()],
            "last_scan": None if self.last_report is None else self.last_report.as_dict(),
            "last_calibration_rotation": None if self.last_calibration is None else self.last_calibration.as_dict(),
        }
