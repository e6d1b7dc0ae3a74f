"""The long-running rig daemon: drivers up, READY, panel and control API, one scan at a time.

Start-up closes any scan folder a killed daemon left in progress (marked incomplete, reported
in the status), connects the drivers and makes sure the beam stands still before telling
systemd READY. The watchdog is pinged only while the event loop runs on time and the drive
answers, every safety task and driver thread runs and the loop never ran late beyond a bound
since the last ping; panel buttons and control requests go through the same controller as
``tbp scan``.
"""

from __future__ import annotations

import asyncio
import os
from collections.abc import AsyncIterator
from pathlib import Path
from typing import Any

import structlog

from daemon.clinic.patient import PatientError, ScanSubject
from daemon.clinic.site import Site
from daemon.errors import DaemonError, ScanBusy, ScanRefused
from daemon.faults import AbortCause, AbortSource, FaultCause, FaultSource
from daemon.jobs.calibration_rotation import CalibrationRotation
from daemon.jobs.controller import RigController
from daemon.records.store import new_scan_id
from daemon.rig.devices import Panel
from daemon.rig.states import SCAN_STATES
from daemon.server.control import ControlServer
from daemon.server.looplag import LoopLagMonitor
from daemon.server.notify import SystemdNotifier, run_watchdog
from daemon.tasks import stop_tasks
from drivers.panel import PanelEvent, StatusLed

log = structlog.get_logger("daemon.server.service")


class WorklistUnavailable(DaemonError):
    """The site file names no worklist provider."""


class RigService:
    """The daemon around a :class:`RigController`; also the control API's handler.

    Args:
        controller: the rig controller (hardware not yet started).
        socket_path: the control socket; None serves no control API.
        group: the control socket's group (operators).
        notifier: sd_notify sender (a disabled one outside systemd).
    """

    MAX_LAG_S = 0.5
    """The loop is unhealthy when a sleep wakes this much late (daemon/server/looplag.py measures it)."""

    def __init__(self, controller: RigController, *, socket_path: Path | None = None,
                 group: str | None = None, notifier: SystemdNotifier | None = None) -> None:
        self.controller = controller
        self.socket_path = socket_path
        self.group = group
        self.notifier = notifier or SystemdNotifier()
        self.recovered: list[dict[str, Any]] = []
        stall_tracebacks = os.environ.get("TBP_LOOP_STALL_TRACEBACKS")
        self.lag = LoopLagMonitor(lambda: controller.machine.state.value,
                                  tracebacks=Path(stall_tracebacks) if stall_tracebacks else None)
        self._tasks: list[asyncio.Task[Any]] = []
        self._server: Any = None
        self.attached: list[Any] = []
        self._ready_sent = False
        self.site: Site | None = None
        """How the rig reaches the clinic's worklist and archive (the site file), None: not configured."""
        self.status_parts: dict[str, Any] = {}
        """Sections an attached server adds to the status (name -> callable returning JSON-able data)."""

    def attach(self, server: Any) -> None:
        """Serve ``server`` (``await start()``, ``await close()``; the web server) while the daemon runs:
        started after the control socket, closed before the devices."""
        self.attached.append(server)

    # ------------------------------------------------------------------ life cycle

    async def start(self) -> None:
        """Recover interrupted scans, bring the rig up, open the control socket, notify READY."""
        ctl = self.controller
        for folder in ctl.store.recover():
            counts = folder.manifest.counts()
            self.recovered.append({"scan_id": folder.scan_id, "path": str(folder.path),
                                   "reason": folder.manifest.reason, "counts": counts})
            log.warning("interrupted_scan_recovered", scan_id=folder.scan_id, path=str(folder.path),
                        **counts)
        ready = await ctl.bringup.once()
        if self.socket_path is not None:
            self._server = ControlServer(self.socket_path, self, group=self.group)
            await self._server.start()
        for server in self.attached:
            await server.start()
        self._tasks += [
            asyncio.create_task(self.lag.run(), name="loop-lag"),
            asyncio.create_task(run_watchdog(self.notifier, self._watchdog_check), name="watchdog"),
            asyncio.create_task(self._mirror_status(), name="notify-status"),
            asyncio.create_task(ctl.bringup.run(self._readiness_changed), name="reprobe"),
        ]
        if ctl.hw.panel is not None:
            self._tasks.append(asyncio.create_task(self._panel_events(ctl.hw.panel), name="panel-events"))
        self._readiness_changed(ready)

    def _readiness_changed(self, ready: bool) -> None:
        """READY=1 the first time every device answers; until then, and whenever a device is
        missing, STATUS= names it (and the journal, `tbp status`, the panel's fault LED)."""
        ctl = self.controller
        if not ready:
            summary = ctl.bringup.summary()
            self.notifier.status(summary)
            log.warning("daemon_not_ready", missing=[d.as_dict() for d in ctl.bringup.missing()])
            if ctl.hw.panel is not None and ctl.bringup.devices["panel"].ok:
                self._spawn(ctl.hw.panel.set_status(StatusLed.FAULT), "panel-not-ready")
            return
        state = ctl.machine.state.value
        text = f"{state}; {len(self.recovered)} interrupted scan(s) recovered"
        if not self._ready_sent:
            self.notifier.ready(text)
            self._ready_sent = True
            log.info("daemon_ready", state=state, recovered=len(self.recovered),
                     socket=str(self.socket_path) if self.socket_path else None)
        else:
            self.notifier.status(text)
            log.info("devices_back", state=state)
        self._spawn(ctl.show_idle(), "panel-ready")

    def _spawn(self, coro: Any, name: str) -> None:
        async def quietly() -> None:
            try:
                await coro
            except Exception as exc:  # the panel's own loss is handled by its heartbeat watch
                log.info("panel_led_not_set", task=name, error=str(exc))

        task = asyncio.create_task(quietly(), name=name)
        self._tasks.append(task)

    async def stop(self) -> list[str]:
        """Abort a running scan, stop the beam, close devices and the socket."""
        self.notifier.stopping("stopping")
        await stop_tasks(self._tasks, self.TASK_STOP_TIMEOUT_S)
        self._tasks.clear()
        for server in reversed(self.attached):
            await server.close()
        if self._server is not None:
            await self._server.close()
        failures = await self.controller.close()
        self.notifier.close()
        log.info("daemon_stopped", failures=failures)
        return failures

    async def run(self, stop: asyncio.Event) -> int:
        """Serve until ``stop`` is set; exit code 0, or 1 when closing a device failed."""
        await self.start()
        try:
            await stop.wait()
        finally:
            failures = await self.stop()
        return 1 if failures else 0

    # ------------------------------------------------------------------ health

    TASK_STOP_TIMEOUT_S = 2.0
    MAX_LAG_S = 1.0
    """The loop is wedged when it ran this late at any moment between two watchdog pings (twice the
    stall after which the drive guard already stops the beam)."""
    TASKS = ("loop-lag", "reprobe", "notify-status")

    def health(self, worst_lag_s: float | None = None) -> list[str]:
        """What keeps the daemon from doing its work (empty: healthy): the loop ran late beyond
        MAX_LAG_S, a task of its own or of a driver's safety machinery ended, a scan state is left
        without its scan, or a connected drive is not being heard while healthy.

        A missing or silent device is not ill health: restarting the daemon would not bring a
        phone back, it would only lose the status the operator reads. A drive that goes silent
        latches FAULT (the drive guard), a missing device keeps the rig NOT READY and is
        re-probed; the watchdog is for a wedged daemon."""
        ctl = self.controller
        worst = self.lag.worst_since_s if worst_lag_s is None else worst_lag_s
        problems = []
        if worst > self.MAX_LAG_S:
            problems.append(f"event loop ran {worst:.3f} s late (limit {self.MAX_LAG_S:g} s)")
        if ctl.machine.state in SCAN_STATES and not ctl.busy:
            problems.append(f"state {ctl.machine.state.value} without a running job")
        if self._tasks:  # started
            running = {t.get_name() for t in self._tasks if not t.done()}
            problems += [f"task {name} ended" for name in self.TASKS if name not in running]
            if ctl.hw.panel is not None and "panel-events" not in running:
                problems.append("task panel-events ended")
        if ctl.bringup.devices["drive"].ok:
            if not ctl.safety.watching:
                problems.append("safety watch on the drive not running")
            if not ctl.tracker.following:
                problems.append("encoder not followed")
            problems += ctl.hw.drive.liveness()
        if ctl.hw.panel is not None and ctl.bringup.devices["panel"].ok:
            problems += ctl.hw.panel.liveness()
        return problems

    def _watchdog_check(self) -> bool:
        """One watchdog period: healthy over the whole interval since the last ping."""
        problems = self.health(self.lag.take_worst())
        if problems:
            log.error("daemon_unhealthy", problems=problems)
        return not problems

    async def _mirror_status(self) -> None:
        async for event in self.controller.machine.subscribe():
            if event.kind == "transition":
                self.notifier.status(f"{event.state.value}: {event.cause}")

    async def _panel_events(self, panel: Panel) -> None:
        """Start, stop and e-stop from the operator panel."""
        ctl = self.controller
        async for event in panel.events():
            log.info("panel_event", panel_event=event.name)
            if event is PanelEvent.START_PRESSED:  # started aside: a STOP or e-stop right after is read at once
                self._tasks = [t for t in self._tasks if not t.done()]
                self._tasks.append(asyncio.create_task(self._start_from_panel(), name="panel-start"))
            elif event is PanelEvent.STOP_PRESSED:
                ctl.abort(AbortCause(AbortSource.STOP_BUTTON, "panel", "stop button"))
            elif event is PanelEvent.ESTOP_PRESSED:
                await ctl.trip(FaultCause(FaultSource.ESTOP, "panel", "e-stop pressed"))
            elif event is PanelEvent.HEARTBEAT_LOST:
                await ctl.trip(FaultCause(FaultSource.PANEL_LOST, "panel",
                                          "panel heartbeat lost (e-stop state unknown)"))

    async def _start_from_panel(self) -> None:
        try:
            await self.controller.start_scan(new_scan_id())
        except (ScanBusy, ScanRefused) as exc:  # logged and streamed by the controller too
            log.warning("panel_start_refused", reason=str(exc))

    # ------------------------------------------------------------------ control API handler

    def status(self) -> dict[str, Any]:
        status = self.controller.status()
        status["recovered_scans"] = list(self.recovered)
        problems = self.health()
        status["healthy"] = not problems
        status["health_problems"] = problems
        status["loop_lag"] = self.lag.summary()
        for name, part in self.status_parts.items():
            status[name] = part()
        return status

    async def worklist(self) -> dict[str, Any]:
        """Today's scheduled steps from the clinic's worklist (C-FIND, in a thread): ``items`` (each
        a patient to start a scan for) and ``problems`` (answers left out, naming the field).
        Raises WorklistUnavailable without a worklist in the site file, and the DicomPeerError
        naming the provider and the reason when it cannot be asked."""
        from daemon.clinic.worklist import query
        from daemon.utc import utc_now

        site = self.site
        if site is None or site.worklist is None:
            raise WorklistUnavailable("no worklist provider in the site file (site.yaml: worklist)")
        worklist = site.worklist
        today = f"{utc_now().astimezone():%Y%m%d}"  # the clinic's day, in this PC's time zone
        answer = await asyncio.to_thread(query, worklist, site, today)
        log.info("worklist_read", provider=str(worklist.peer), items=len(answer.items),
                 left_out=len(answer.problems))
        return answer.as_dict()

    SCAN_ARGS = ("scan_id", *ScanSubject.ARGS)

    async def scan(self, **args: Any) -> dict[str, Any]:
        """Start a scan; ``args``: optional ``scan_id`` and the patient it is for (``patient_id``,
        ``patient_name`` as ``Family^Given``, ``birth_date``, ``sex``, ``accession_number``,
        ``study_instance_uid``), kept in the manifest only. An unknown argument or a patient field
        that is not valid refuses the scan (PatientError names the field, never the value)."""
        unknown = sorted(set(args) - set(self.SCAN_ARGS))
        if unknown:
            raise PatientError(unknown[0][:40], f"unknown scan argument; allowed: {', '.join(self.SCAN_ARGS)}")
        subject = ScanSubject.from_args(args)
        scan_id = args.get("scan_id") or new_scan_id()
        await self.controller.start_scan(scan_id, subject)
        return {"scan_id": scan_id, "state": self.controller.machine.state.value, "for_patient": subject is not None}

    async def calibrate(self, **args: Any) -> dict[str, Any]:
        """Start a calibration rotation (the cuboid in place); its folder is in the answer."""
        rotation_id = args.get("rotation_id") or new_scan_id()
        await self.controller.start_calibration(rotation_id)
        rotation = self.controller.current  # the job start_calibration made
        folder = str(rotation.folder) if isinstance(rotation, CalibrationRotation) else None
        return {"rotation_id": rotation_id, "folder": folder,
                "state": self.controller.machine.state.value}

    def abort(self) -> dict[str, Any]:
        return {"aborted": self.controller.abort(AbortCause(AbortSource.CONTROL_API, "control API", "abort")),
                "state": self.controller.machine.state.value}

    async def reset(self) -> dict[str, Any]:
        await self.controller.reset("control API reset")
        return {"state": self.controller.machine.state.value}

    def recent_events(self) -> list[dict[str, Any]]:
        """The latest transitions and progress events, oldest first, without the per-image counts
        (``ScanStateMachine.recent``): what a console opened now shows as its history."""
        return [event.as_dict() for event in self.controller.machine.recent]

    async def subscribe(self) -> AsyncIterator[dict[str, Any]]:
        async for event in self.controller.machine.subscribe():
            yield event.as_dict()
