"""The life of whatever the controller runs on the rig, one at a time: a scan, a calibration
rotation, any later job.

:class:`RigJob` owns the parts every job shares: it enters the job's first state, runs the
job's steps as one body task, and ends on one path whatever ended them. The operator's abort
and a safety trip stop the body the same way; the beam is stopped (the abort's controlled stop,
or the trip's quick stop) before anything waits for the body, and the body gets a bound to
unwind. A failed drive command is a rig fault. Then the job settles, stores what it has
(:meth:`RigJob.store`), closes its folder (:meth:`RigJob.close_folder`) and leaves the machine
in IDLE, or in FAULT when a fault is latched. A subclass gives its body, its store step and its
folder closing.
"""

from __future__ import annotations

import asyncio
from collections.abc import Coroutine
from typing import Any, ClassVar

import structlog

from daemon.errors import FaultLatched
from daemon.faults import AbortCause, AbortSource, FaultCause, FaultSource
from daemon.records.manifest import ScanEnd
from daemon.rig.beam import BeamTracker
from daemon.rig.hardware import RigHardware
from daemon.rig.safety import SafetyMonitor
from daemon.rig.states import ScanOutcome, ScanState, ScanStateMachine
from daemon.tasks import describe, settle, stop_tasks
from drivers.motor.errors import DriveError, MotionInterrupted
from planner.rig import Rig

log = structlog.get_logger("daemon.jobs.job")


class RigJob:
    """One job on connected hardware: its body task, why it stopped, and its end.

    Subclasses set :attr:`kind` (``"scan"``), :attr:`first_state` and :attr:`storing`, and
    give :meth:`body`, :meth:`store`, :meth:`close_folder`, :meth:`note` and
    :attr:`stop_deceleration_deg_s2`. Their report has ``outcome`` and ``causes``.
    """

    kind: ClassVar[str]
    device: ClassVar[str]
    """Who a step's error is ascribed to in the abort cause ("scan")."""
    first_state: ClassVar[ScanState]
    storing: ClassVar[str]
    """The cause of the STORING transition ("storing the scan")."""
    BODY_STOP_TIMEOUT_S: ClassVar[float] = 25.0
    """How long the stopped body may take to unwind (the depth cameras stop in up to 3 x 6 s);
    a body still running then latches FAULT naming where it hangs."""

    report: Any

    def __init__(self, rig: Rig, hardware: RigHardware, machine: ScanStateMachine, safety: SafetyMonitor,
                 tracker: BeamTracker, job_id: str) -> None:
        self.rig = rig
        self.hw = hardware
        self.machine = machine
        self.safety = safety
        self.tracker = tracker
        self.job_id = job_id
        self._abort_cause: AbortCause | None = None
        self._body: asyncio.Task[None] | None = None
        self._body_cancelled = False
        self._stopped: asyncio.Future[None] | None = None

    # ------------------------------------------------------------------ for subclasses

    def body(self) -> Coroutine[Any, Any, None]:
        """The job's steps (run as the body task)."""
        raise NotImplementedError

    async def store(self) -> None:
        """Keep what the job has (the body has ended) and close its folder."""
        raise NotImplementedError

    async def close_folder(self) -> bool:
        """Write the job's end into its folder if not done yet, off the event loop; False when the
        disk refuses (the controller tries again at the next reset or job)."""
        raise NotImplementedError

    def note(self, text: str) -> None:
        """Record an error in the job's report."""
        raise NotImplementedError

    @property
    def stop_deceleration_deg_s2(self) -> float:
        """The controlled stop of an abort."""
        raise NotImplementedError

    def start_data(self) -> dict[str, Any]:
        """Facts of the first transition."""
        return {}

    def end_data(self) -> dict[str, Any]:
        """Facts of the final transition to IDLE."""
        return {}

    # ------------------------------------------------------------------ control

    def abort(self, cause: AbortCause) -> None:
        """Stop the job: the first cause is kept, the body is cancelled and the beam stopped."""
        if self._abort_cause is None:
            self._abort_cause = cause
        self.cancel_for_fault()

    def cancel_for_fault(self) -> None:
        """Called by the safety monitor on a trip: stop the body (the latch stops the beam)."""
        self._cancel_body()
        self._wake()

    def _cancel_body(self) -> None:
        """Cancel the body once: a second cancel would cut its own clean-up short (the depth
        cameras it stops, the tasks it ends)."""
        if self._body is not None and not self._body.done() and not self._body_cancelled:
            self._body_cancelled = True
            self._body.cancel()

    def _wake(self) -> None:
        """The run goes on to the end: the body ended or was stopped."""
        if self._stopped is not None and not self._stopped.done():
            self._stopped.set_result(None)

    # ------------------------------------------------------------------ run

    async def run(self) -> Any:
        """Run the whole job; returns its report (also for aborted and faulted jobs). Whatever goes
        wrong ends in a recorded outcome: if ending the job raises, the rig latches FAULT
        (``FaultSource.SCAN_FAILED``) naming the error and the folder is closed as ``fault``."""
        try:
            await self._finish(await self._start_and_wait())
        except Exception as exc:  # ending the job failed: the last line of defence
            await self._ending_failed(exc)
        log.info("job_ended", job=self.kind, job_id=self.job_id, outcome=self.report.outcome.value,
                 reason="; ".join(map(str, self.report.causes)) or None)
        return self.report

    async def _start_and_wait(self) -> BaseException | None:
        """Enter the first state and run the body until it ends or is stopped; the body's own
        error, if it ended by itself with one."""
        self.machine.scan_id = self.job_id
        if self.safety.latched:  # tripped between the request and now: store the empty job
            return FaultLatched(self.safety.causes)
        self.machine.transition(self.first_state, f"{self.kind} requested", **self.start_data())
        self._stopped = asyncio.get_running_loop().create_future()
        self._body = asyncio.create_task(self.body(), name=f"{self.kind}-{self.job_id}")
        self._body.add_done_callback(lambda _body: self._wake())
        if self._abort_cause is not None:  # aborted before it started
            self.cancel_for_fault()
        await self._stopped
        body = self._body
        if body.done() and not body.cancelled() and self._abort_cause is None and not self.safety.latched:
            return body.exception()
        return None

    async def _finish(self, error: BaseException | None) -> None:
        """End the job on one explicit path per outcome; every step is a legal transition.

        completed: the last step's state -> STORING -> IDLE.
        aborted (operator, store, a step's error): the active state -> ABORTING (the beam
            decelerates) -> STORING -> IDLE.
        faulted (the safety latch, before or while ending): FAULT stays latched, the folder is
            stored all the same, and only the operator's reset leaves FAULT.
        """
        report = self.report
        self.safety.expect_samples = False
        self._cancel_body()
        if error is not None:
            self.note(f"{type(error).__name__}: {error}")
            if isinstance(error, DriveError) and not self.safety.latched:
                await self.safety.trip(FaultCause.of_error(FaultSource.DRIVE_ERROR, self.hw.drive.name, error))
        cause = self._abort_cause if self._abort_cause is not None or error is None else self.error_cause(error)
        if cause is not None and not self.safety.latched:
            report.outcome, report.causes = ScanOutcome.ABORTED, [cause]
            self.machine.transition(ScanState.ABORTING, cause)
            await self._stop_beam()  # before waiting for the body; a drive that cannot stop latches FAULT
        if self.safety.latched:
            await self.safety.settled()
        await self._await_body(error)
        if self.safety.latched:
            report.outcome, report.causes = ScanOutcome.FAULTED, list(self.safety.causes)
        else:
            self.machine.transition(ScanState.STORING, self.storing)
        await self.store()
        if self.machine.state is not ScanState.FAULT:  # a trip while storing keeps FAULT latched
            self.machine.transition(ScanState.IDLE, f"{self.kind} {report.outcome.value.lower()}",
                                    outcome=report.outcome.value, **self.end_data())
        self.machine.scan_id = None

    def error_cause(self, error: BaseException) -> AbortCause:
        """Why a step's error aborted the job."""
        return AbortCause.of_error(AbortSource.SCAN_ERROR, self.device, error)

    async def _stop_beam(self) -> None:
        try:
            await self.hw.drive.stop(self.stop_deceleration_deg_s2)
        except Exception as exc:  # a drive that cannot stop is a rig fault
            await self.safety.trip(FaultCause.of_error(FaultSource.DRIVE_ERROR, self.hw.drive.name, exc,
                                                       "controlled stop failed"))

    async def _await_body(self, error: BaseException | None) -> None:
        """The stopped body gets :attr:`BODY_STOP_TIMEOUT_S` to unwind; one that does not is named
        in the report and latches FAULT (it may still command the drive), left cancelled. An error
        it raised on its way out is noted (``error``: the one it ended with, noted already)."""
        body = self._body
        if body is None:
            return
        if await settle([body], self.BODY_STOP_TIMEOUT_S):
            where = describe(body)
            self.note(f"the {self.kind}'s steps did not end within {self.BODY_STOP_TIMEOUT_S:g} s of the stop: {where}")
            detail = f"its steps did not stop within {self.BODY_STOP_TIMEOUT_S:g} s ({where})"
            await self.safety.trip(FaultCause(FaultSource.SCAN_FAILED, self.kind, detail))
        elif not body.cancelled() and body.exception() is not None and error is None:
            exc = body.exception()
            if not isinstance(exc, MotionInterrupted):  # the body's move, cut short by the stop: no news
                self.note(f"while stopping: {type(exc).__name__}: {exc}")

    async def _ending_failed(self, error: Exception) -> None:
        """Ending the job raised (an OSError such as too many open files, or a bug): latch FAULT
        naming the error, so the rig stops and says why instead of staying in STORING; then close
        the folder as ``fault`` if the disk lets us."""
        report = self.report
        self.note(f"closing the {self.kind}: {type(error).__name__}: {error}")
        log.error("job_closing_failed", job=self.kind, job_id=self.job_id, error=f"{type(error).__name__}: {error}")
        if self._body is not None:
            await stop_tasks([self._body], self.BODY_STOP_TIMEOUT_S)
        await self.safety.trip(FaultCause.of_error(FaultSource.SCAN_FAILED, self.kind, error,
                                                   f"closing the {self.kind}"))
        report.outcome, report.causes = ScanOutcome.FAULTED, list(self.safety.causes)
        await self.close_folder()
        self.machine.scan_id = None


JOB_END = {ScanOutcome.COMPLETED: ScanEnd.COMPLETE, ScanOutcome.PARTIAL: ScanEnd.PARTIAL,
           ScanOutcome.ABORTED: ScanEnd.ABORTED, ScanOutcome.FAULTED: ScanEnd.FAULT}
"""How a job's folder records its outcome."""
