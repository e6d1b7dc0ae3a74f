"""One scan, start to end: PREPARING -> DEPTH_SWEEP -> RECONSTRUCTING -> PLANNING -> CAPTURING
(-> RETAKING) -> STORING -> IDLE.

The steps (daemon/jobs/scan_steps.py, one per state) run as the job's body; an abort (stop button,
control API) or a safety trip cancels it at any await, and the job (daemon/jobs/job.py) stops the
beam, then stores what was captured here and closes the scan folder.
"""

from __future__ import annotations

import asyncio
import functools
from collections.abc import Awaitable, Callable, Sequence
from concurrent.futures import Executor
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import structlog

from daemon.faults import AbortCause, AbortSource, Cause
from daemon.jobs.capture import CaptureRecord
from daemon.jobs.job import JOB_END, RigJob
from daemon.jobs.scan_steps import ScanSteps
from daemon.records.atomic import StoreError
from daemon.records.manifest import ImageStatus, MissingReason, missing_text
from daemon.records.store import ScanFolder
from daemon.rig.beam import BeamTracker
from daemon.rig.hardware import RigHardware
from daemon.rig.safety import SafetyMonitor
from daemon.rig.states import SCAN_STEPS, ScanOutcome, ScanState, ScanStateMachine
from planner.calibration.model import Calibration
from planner.rig import Rig

log = structlog.get_logger("daemon.jobs.scan")


@dataclass(frozen=True)
class ScanSettings:
    """How the daemon runs every scan; handed as one object from the controller to each scan.

    seed: seeds the planner's surface sampling (a seeded scan is reproducible).
    plan_points: surface samples for planning (None: the rig file's ``planner.points``).
    executor: where the compute steps run (None: the loop's default thread pool).
    qa_report: ``(scan folder, rig_path=rig file) -> page`` writes the scan's QA report once the folder
        is closed, in STORING with the beam's moves ended (None: no report; ``tbp report`` can
        write it later).
    calibration_target: the ChArUco cuboid's file for calibration rotations (None: the default,
        calibration_data/target/cuboid.yaml).
    """

    seed: int = 0
    plan_points: int | None = None
    executor: Executor | None = None
    qa_report: Callable[..., Path] | None = None
    calibration_target: Path | None = None


@dataclass
class ScanReport:
    """How a scan went. Times are rig (event-loop) seconds unless named ``compute``."""

    scan_id: str
    folder: Path
    outcome: ScanOutcome
    causes: list[Cause] = field(default_factory=list)
    captured: int = 0
    verified: int = 0
    missing: int = 0
    """Planned images not in the folder (not verified), whatever the reason."""
    missing_by_phone: dict[str, dict[str, int]] = field(default_factory=dict)
    """Those images per camera id and reason (daemon.records.manifest.MissingReason values)."""
    dropped_phones: list[dict[str, Any]] = field(default_factory=list)
    """Phones dropped for the rest of the scan, and any that rode along on the retake
    (daemon.jobs.capture.CaptureRunner.drops)."""
    retaken: int = 0
    lens_late: int = 0
    focus_clipped: int = 0
    max_abs_angle_error_deg: float | None = None
    min_speed_ratio: float | None = None
    phase_s: dict[str, float] = field(default_factory=dict)
    compute_s: dict[str, float] = field(default_factory=dict)
    """Compute time per step, measured where it ran: tsdf_during_sweep, tsdf, planning."""
    compute_stops_clock: bool = False
    """The loop's clock stands still during compute (the virtual-time loop): rig-time phases then
    exclude the compute time, and sweep_to_capture_s adds it back."""
    errors: list[str] = field(default_factory=list)

    @property
    def reason(self) -> str | None:
        """The causes in words; for a partial scan, its missing images per phone (None for a
        completed scan)."""
        if self.causes:
            return "; ".join(map(str, self.causes))
        if self.outcome is ScanOutcome.PARTIAL:
            return missing_text(self.missing_by_phone, self.verified + self.missing)
        return None

    AFTER_SWEEP = ("tsdf", "planning")
    """The compute steps between the end of the sweep and the capture (``tsdf``: the last frames
    and the mesh; ``tsdf_during_sweep`` ran while the beam turned)."""

    @property
    def sweep_to_capture_s(self) -> float:
        """End of the depth sweep to the start of the capture rotation, compute included."""
        compute = sum(self.compute_s.get(k, 0.0) for k in self.AFTER_SWEEP) if self.compute_stops_clock else 0.0
        return self.phase_s.get("sweep_to_capture", 0.0) + compute

    def as_dict(self) -> dict[str, Any]:
        return {
            "scan_id": self.scan_id, "folder": str(self.folder), "outcome": self.outcome.value,
            "reason": self.reason, "causes": [c.as_dict() for c in self.causes],
            "captured": self.captured, "verified": self.verified, "missing": self.missing,
            "missing_by_phone": {k: dict(v) for k, v in self.missing_by_phone.items()},
            "dropped_phones": [dict(d) for d in self.dropped_phones], "retaken": self.retaken,
            "lens_late": self.lens_late,
            "focus_clipped": self.focus_clipped,
            "max_abs_angle_error_deg": self.max_abs_angle_error_deg,
            "min_speed_ratio": self.min_speed_ratio, "phase_s": dict(self.phase_s),
            "compute_s": dict(self.compute_s), "sweep_to_capture_s": self.sweep_to_capture_s,
            "errors": list(self.errors),
        }


class Scan(RigJob):
    """One scan on connected hardware: its steps (daemon/jobs/scan_steps.py) run from the state table,
    its end as every job's (daemon/jobs/job.py), its store step here.

    Args:
        folder: the scan's folder, already created (a scan is only started once its folder
            exists: docs/hardening.md, rule 2).
        settings: seed, planning samples, compute executor, QA report writer.
    """

    kind = "scan"
    device = "scan"
    first_state = ScanState.PREPARING
    storing = "storing the scan"
    ABORT_DECELERATION_FACTOR = 1.0
    PULL_TIMEOUT_S = 120.0
    STOPPING_PULL_TIMEOUT_S = 5.0
    """The pulls' wait when the daemon stops (systemd's TimeoutStopSec is 30 s): a picture not
    pulled yet stays on its phone, recorded as captured."""

    def __init__(
        self,
        rig: Rig,
        hardware: RigHardware,
        machine: ScanStateMachine,
        safety: SafetyMonitor,
        tracker: BeamTracker,
        folder: ScanFolder,
        *,
        settings: ScanSettings = ScanSettings(),
        calibration: Calibration | None = None,
    ) -> None:
        super().__init__(rig, hardware, machine, safety, tracker, folder.scan_id)
        self.calibration = calibration
        self.folder = folder
        self.settings = settings
        self.report = ScanReport(folder.scan_id, folder.path, ScanOutcome.COMPLETED)
        self.steps = ScanSteps(self)
        self.store_error: StoreError | None = None
        self._marks: dict[str, float] = {}

    # ------------------------------------------------------------------ the job's parts

    def start_data(self) -> dict[str, Any]:
        return {"folder": str(self.folder.path)}

    def end_data(self) -> dict[str, Any]:
        report = self.report
        return {"captured": report.captured, "verified": report.verified, "missing": report.missing}

    @property
    def stop_deceleration_deg_s2(self) -> float:
        return self.rig.capture.acceleration_deg_s2 * self.ABORT_DECELERATION_FACTOR

    def note(self, text: str) -> None:
        self.report.errors.append(text)

    def error_cause(self, error: BaseException) -> AbortCause:
        """Why a step's error aborted the scan: the store (disk full), or the step itself."""
        if isinstance(error, StoreError):
            return AbortCause.of_error(AbortSource.STORE, "store", error)
        return super().error_cause(error)

    async def body(self) -> None:
        """The steps of :data:`SCAN_STEPS` in order, each entering its state with the cause the
        one before gave (the job entered the first)."""
        steps = self.steps
        nxt = None
        try:
            for state in SCAN_STEPS:
                if state is not self.first_state:
                    if nxt is None:  # nothing to do there (the table refuses skipping a state that must run)
                        continue
                    self.machine.transition(state, nxt.cause, **nxt.data)
                nxt = await steps.table[state]()
            steps.done()
        finally:
            await steps.settle()

    def mark(self, name: str) -> None:
        """The rig time of a milestone (the report's phases)."""
        self._marks[name] = asyncio.get_running_loop().time()

    async def close_folder(self) -> bool:
        """Write the outcome into events.jsonl and close the manifest (in the store's writer thread
        in real time), if not done yet; False (logged) when the disk does not let us: the folder
        stays ``in progress`` and the controller tries again at the next reset or scan, the
        daemon's next start at the latest."""
        folder, report = self.folder, self.report
        if not folder.manifest.in_progress:
            return True
        try:
            folder.log_event("scan_ended", outcome=report.outcome.value, reason=report.reason)
            await folder.close(JOB_END[report.outcome], report.causes)
        except Exception as exc:  # recorded in the report and the log; retried later
            report.errors.append(f"manifest: {type(exc).__name__}: {exc}")
            log.error("scan_folder_not_closed", scan_id=folder.scan_id, error=f"{type(exc).__name__}: {exc}")
            return False
        return True

    # ------------------------------------------------------------------ storing

    async def store(self) -> None:
        """Wait for the pulls, then write the trace, capture records, QA and the final manifest.

        Every step runs even if an earlier one failed (a full disk); failures go to the report
        and a manifest that cannot be rewritten stays at its last valid version.
        """
        folder, report, steps = self.folder, self.report, self.steps
        stopping = self._abort_cause is not None and self._abort_cause.source is AbortSource.DAEMON_STOPPING
        await steps.settle_baselines(report.outcome, self.PULL_TIMEOUT_S)
        await steps.settle_surface(self.STOPPING_PULL_TIMEOUT_S if stopping else self.PULL_TIMEOUT_S)
        if steps.fusion is not None and steps.fusion.closed is not None:  # asked for long ago: done
            await asyncio.wait([steps.fusion.closed], timeout=self.PULL_TIMEOUT_S)
        pulls = steps.pulls
        if pulls is not None:
            wait_s = self.STOPPING_PULL_TIMEOUT_S if stopping else self.PULL_TIMEOUT_S
            try:
                async with asyncio.timeout(wait_s):
                    await pulls.join()
            except (StoreError, TimeoutError) as exc:
                report.errors.append(f"pulls: {type(exc).__name__}: {exc}")
            finally:
                await pulls.close()
            report.errors.extend(str(f) for f in pulls.failures)
        if self.store_error is not None:
            report.errors.append(f"store: {type(self.store_error).__name__}: {self.store_error}")
        runner = steps.runner
        records = runner.records if runner is not None else []
        if runner is not None:
            report.errors.extend(f"capture worker {name} did not stop within {runner.WORKER_STOP_S:g} s"
                                 for name in runner.abandoned)
        try:
            self._record_missing(records)
        except Exception as exc:  # recorded; the folder's end settles every image all the same
            report.errors.append(f"missing: {type(exc).__name__}: {exc}")
            log.error("store_step_failed", step="missing", error=f"{type(exc).__name__}: {exc}")
        self._summarise(report, records)
        if report.outcome is ScanOutcome.COMPLETED and report.missing:
            report.outcome = ScanOutcome.PARTIAL
        trace = self.tracker.trace(steps.trace_mark)
        captures, qa = [r.as_dict() for r in records], report.as_dict()
        writes: list[tuple[str, Callable[[], Awaitable[Any]]]] = [
            ("trace", lambda: folder.write_trace(trace[:, 0], trace[:, 1], trace[:, 2], save=False)),
            ("captures", lambda: folder.write_json("captures", "captures.json", captures, save=False)),
            ("qa", lambda: folder.write_json("qa", "qa.json", qa, save=False)),
        ]
        for name, write in writes:
            try:
                await write()
            except Exception as exc:  # a full disk, too many open files: recorded, the next step runs
                report.errors.append(f"{name}: {type(exc).__name__}: {exc}")
                log.error("store_step_failed", step=name, error=f"{type(exc).__name__}: {exc}")
        await self.close_folder()
        if report.captured and self.settings.qa_report is not None:
            await self._write_qa_report(folder, self.settings.qa_report)

    async def _write_qa_report(self, folder: ScanFolder, write: Callable[..., Path]) -> None:
        """The HTML QA report, off the event loop. It is derived from files already safe on
        disk, so a failure is logged and `tbp report` can regenerate it."""
        try:
            page = await asyncio.get_running_loop().run_in_executor(
                self.settings.executor, functools.partial(write, folder.path, rig_path=self.rig.path))
            log.info("qa_report_written", path=str(page))
        except Exception as exc:  # the scan's data is complete without the report
            log.error("qa_report_failed", error=f"{type(exc).__name__}: {exc}")

    def _record_missing(self, records: Sequence[CaptureRecord]) -> None:
        """Every pose the capture tried and did not take, missing in the manifest with its error
        and reason (poses never tried stay planned: the folder's end says the scan ended first)."""
        for record in records:
            if record.status == "captured" or record.status == "pending":
                continue
            error = f"{record.error_type}: {record.error}" if record.error_type else "not captured"
            self.folder.update_image(record.camera_index, record.angle_index, save=False,
                                     status=ImageStatus.MISSING, error=error,
                                     missing_reason=record.missing_reason or MissingReason.CAPTURE_MISSED)

    def _summarise(self, report: ScanReport, records: Sequence[CaptureRecord]) -> None:
        m = self._marks
        captured = [r for r in records if r.status == "captured"]
        manifest = self.folder.manifest
        report.captured = len(captured)
        report.verified = manifest.counts()[ImageStatus.VERIFIED.value]
        report.missing = self.rig.n_poses - report.verified
        report.missing_by_phone = manifest.missing_by_phone(ended=True)
        report.dropped_phones = list(self.steps.runner.drops) if self.steps.runner is not None else []
        report.retaken = sum(r.capture_pass == "retake" for r in captured)
        report.lens_late = sum(r.lens_late for r in captured)
        main = [r for r in captured if r.capture_pass == "main"]
        if captured:
            report.max_abs_angle_error_deg = max(abs(r.angle_error_deg or 0.0) for r in captured)
        if main and self.steps.schedule is not None:
            nominal = self.steps.schedule.profile.nominal_speed(np.array([r.planned_angle_deg for r in main]))
            speed = np.array([r.beam_speed_deg_s or 0.0 for r in main])
            report.min_speed_ratio = float(np.min(speed / nominal))
        spans = {
            "preparing": ("start", "prepared"),
            "sweep_to_capture": ("sweep_end", "capture_start"),
            "capture": ("capture_start", "capture_end"),
            "retake": ("capture_end", "retake_end"),
            "total": ("start", "retake_end"),
        }
        for name, (a, b) in spans.items():
            if a in m and b in m:
                report.phase_s[name] = m[b] - m[a]
        if "prepared" in m and "sweep_end" in m:
            report.phase_s["depth_sweep"] = m["sweep_end"] - m["prepared"]

