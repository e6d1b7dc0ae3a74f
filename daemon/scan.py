"""One scan, start to end: PREPARING -> DEPTH_SWEEP -> RECONSTRUCTING -> PLANNING -> CAPTURING
(-> RETAKING) -> STORING -> IDLE.

The sequence runs as an inner task so an abort (stop button, control API) or a safety trip can
cancel it at any await; the outer coroutine then stops the beam and closes the scan folder with
whatever was captured. Ray casting, TSDF fusion and planning run in an executor so the event
loop keeps serving heartbeats, the watchdog and the e-stop while they compute.
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

from daemon.atomic import StoreError
from daemon.beam import BeamTracker, rebase_angle
from daemon.capture import CaptureRecord, CaptureRunner
from daemon.compute import timed
from daemon.depth_sweep import DepthSweeper
from daemon.errors import FaultLatched
from daemon.faults import AbortCause, AbortSource, Cause, FaultCause, FaultSource
from daemon.fusion import FusionSession
from daemon.hardware import RigHardware
from daemon.job import RigJob, is_drive_error
from daemon.manifest import ImageStatus, ScanEnd
from daemon.phones import PhonePrep, keep_clocks_synced, prepare_phones
from daemon.planning import BASELINES, plan_capture
from daemon.pulls import PullQueue
from daemon.safety import SafetyMonitor
from daemon.states import ScanOutcome, ScanState, ScanStateMachine
from daemon.store import ScanFolder
from planner.calibration.model import Calibration
from planner.rig import Rig
from planner.schedule import CaptureSchedule, PhoneTiming, compile_plan, rig_profile

log = structlog.get_logger("daemon.scan")

@dataclass(frozen=True)
class ScanSettings:
    """How the daemon runs every scan; handed as one object from the controller to each scan.

    seed: seeds the planner's surface sampling (a seeded scan is reproducible).
    plan_points: surface samples for planning (None: the rig file's ``planner.points``).
    executor: where the compute steps run (None: the loop's default thread pool).
    qa_report: ``(scan folder, rig_path=rig file) -> page`` writes the scan's QA report once the folder
        is closed (None: no report; ``tbp report`` can write it later).
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
    missing: int = 0
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
        """The causes in words (None for a completed scan)."""
        return "; ".join(map(str, self.causes)) or None

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
            "captured": self.captured, "missing": self.missing,
            "retaken": self.retaken, "lens_late": self.lens_late,
            "focus_clipped": self.focus_clipped,
            "max_abs_angle_error_deg": self.max_abs_angle_error_deg,
            "min_speed_ratio": self.min_speed_ratio, "phase_s": dict(self.phase_s),
            "compute_s": dict(self.compute_s), "sweep_to_capture_s": self.sweep_to_capture_s,
            "errors": list(self.errors),
        }


class Scan(RigJob):
    """One scan on connected hardware.

    Args:
        folder: the scan's folder, already created (a scan is only started once its folder
            exists: docs/hardening.md, rule 2).
        settings: seed, planning samples, compute executor, QA report writer.

    Whatever goes wrong, :meth:`run` ends in a recorded outcome (rule 1): a scan step's error
    aborts the scan, a safety trip faults it, and if closing the scan raises, the rig latches
    FAULT (``FaultSource.SCAN_FAILED``) naming the error and the folder is closed as ``fault``.
    """

    ABORT_DECELERATION_FACTOR = 1.0
    PULL_TIMEOUT_S = 120.0
    TRACE_SAVE_S = 5.0  # a killed daemon loses at most this much of the encoder trace

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
        self.rig = rig
        self.calibration = calibration
        self.hw = hardware
        self.machine = machine
        self.safety = safety
        self.tracker = tracker
        self.folder = folder
        self.settings = settings
        self.report = ScanReport(folder.scan_id, folder.path, ScanOutcome.COMPLETED)
        self.runner: CaptureRunner | None = None
        self.schedule: CaptureSchedule | None = None
        self.prep: PhonePrep | None = None
        self._abort_cause: AbortCause | None = None
        self._body: asyncio.Task[None] | None = None
        self._marks: dict[str, float] = {}
        self.pulls: PullQueue | None = None
        self.baselines: asyncio.Task[None] | None = None
        self.fusion: FusionSession | None = None
        self.store_error: StoreError | None = None
        self._trace_mark = 0

    # ------------------------------------------------------------------ run

    async def run(self) -> ScanReport:
        """Run the whole scan; returns its report (also for aborted and faulted scans)."""
        try:
            await self._run_and_finish()
        except Exception as exc:  # closing the scan failed: the last line of defence (rule 1)
            await self._closing_failed(exc)
        return self.report

    async def _run_and_finish(self) -> None:
        folder = self.folder
        error: BaseException | None = None
        if self.safety.latched:  # tripped between the request and now: store the empty scan
            error = FaultLatched(self.safety.causes)
        else:
            self.machine.scan_id = folder.scan_id
            self.machine.transition(ScanState.PREPARING, "scan requested", folder=str(folder.path))
            self._body = asyncio.create_task(self._sequence(), name=f"scan-{folder.scan_id}")
            try:
                await asyncio.shield(self._body)
            except asyncio.CancelledError:
                if self._body.done() or self._abort_cause is not None or self.safety.latched:
                    error = None
                else:
                    self._body.cancel()
                    raise
            except Exception as exc:  # every scan error reaches the report and the manifest
                error = exc
        await self._finish(error)

    async def _closing_failed(self, error: Exception) -> None:
        """Closing the scan raised (an OSError such as too many open files, or a bug): latch
        FAULT naming the error, so the rig stops and says why instead of staying in STORING;
        then close the folder as ``fault`` if the disk lets us."""
        report = self.report
        report.errors.append(f"closing the scan: {type(error).__name__}: {error}")
        log.error("scan_closing_failed", scan_id=self.folder.scan_id, error=f"{type(error).__name__}: {error}")
        if self._body is not None and not self._body.done():
            self._body.cancel()
            await asyncio.gather(self._body, return_exceptions=True)
        await self.safety.trip(FaultCause.of_error(FaultSource.SCAN_FAILED, "scan", error, "closing the scan"))
        report.outcome, report.causes = ScanOutcome.FAULTED, list(self.safety.causes)
        self.close_folder()
        self.machine.scan_id = None

    def close_folder(self) -> bool:
        """Write the outcome into events.jsonl and close the manifest, if not done yet; False
        (logged) when the disk does not let us: the folder stays ``in progress`` and the
        controller tries again at the next reset or scan, the daemon's next start at the latest."""
        folder, report = self.folder, self.report
        if not folder.manifest.in_progress:
            return True
        try:
            folder.log_event("scan_ended", outcome=report.outcome.value, reason=report.reason)
            folder.finish(_END[report.outcome], report.causes)
        except Exception as exc:  # recorded in the report and the log; retried later
            report.errors.append(f"manifest: {type(exc).__name__}: {exc}")
            log.error("scan_folder_not_closed", scan_id=folder.scan_id, error=f"{type(exc).__name__}: {exc}")
            return False
        return True

    async def _finish(self, error: BaseException | None) -> None:
        """Close the scan on one explicit path per outcome; every step is a legal transition
        (an illegal one raises :class:`IllegalTransition`).

        completed: CAPTURING or RETAKING -> STORING -> IDLE.
        aborted (operator, store, a scan step's error): the active state -> ABORTING (beam
            decelerates) -> STORING -> IDLE.
        faulted (the safety latch, before or while closing): FAULT stays latched, the folder
            is stored all the same, and only the operator's reset leaves FAULT.
        """
        assert self.folder is not None and self.report is not None
        report = self.report
        self.safety.expect_samples = False
        if self._body is not None and not self._body.done():
            self._body.cancel()
            await asyncio.gather(self._body, return_exceptions=True)
        if error is not None:
            report.errors.append(f"{type(error).__name__}: {error}")
            if is_drive_error(error) and not self.safety.latched:
                await self.safety.trip(FaultCause.of_error(FaultSource.DRIVE_ERROR, self._drive_name, error))
        if not self.safety.latched and (self._abort_cause is not None or error is not None):
            cause = self._abort_cause or _error_cause(error)
            report.outcome, report.causes = ScanOutcome.ABORTED, [cause]
            self.machine.transition(ScanState.ABORTING, cause)
            await self._stop_beam()  # a drive that cannot stop latches FAULT
        if self.safety.latched:
            await self.safety.settled()
            report.outcome, report.causes = ScanOutcome.FAULTED, list(self.safety.causes)
        else:
            self.machine.transition(ScanState.STORING, "storing the scan")
        await self._store(report)
        if self.machine.state is not ScanState.FAULT:  # a trip while storing keeps FAULT latched
            self.machine.transition(ScanState.IDLE, f"scan {report.outcome.value.lower()}",
                                    captured=report.captured, missing=report.missing)
        self.machine.scan_id = None

    @property
    def _drive_name(self) -> str:
        return self.hw.drive.name

    async def _stop_beam(self) -> None:
        decel = self.rig.capture.acceleration_deg_s2 * self.ABORT_DECELERATION_FACTOR
        try:
            await self.hw.drive.stop(decel)
        except Exception as exc:  # a drive that cannot stop is a rig fault
            await self.safety.trip(FaultCause.of_error(FaultSource.DRIVE_ERROR, self._drive_name, exc,
                                                       "controlled stop failed"))

    def _mark(self, name: str) -> None:
        self._marks[name] = asyncio.get_running_loop().time()

    # ------------------------------------------------------------------ the sequence

    async def _sequence(self) -> None:
        assert self.folder is not None and self.report is not None
        rig, drive = self.rig, self.hw.drive
        a_max, v_max = rig.motor.max_acceleration_deg_s2, rig.motor.max_speed_deg_s
        profile = rig_profile(rig)

        self.folder.log_event("scan_started", rig_digest=rig.digest,
                              calibration=self.calibration.digest if self.calibration else "nominal poses")
        if self.calibration is not None:
            self.folder.write_calibration(Path(self.calibration.path).read_bytes())
        # PREPARING: beam to the sweep start, phones' clocks and trigger latency measured.
        self._mark("start")
        self.report.compute_stops_clock = bool(getattr(asyncio.get_running_loop(), "compute_stops_clock", False))
        if not self.report.compute_stops_clock:
            # Real time: manifest writes leave the loop (the virtual-time loop keeps them in line,
            # so simulated scans stay deterministic to the byte, faults included).
            self.folder.save_in_background()
        self._trace_mark = self.tracker.mark()
        keeper = asyncio.create_task(self._keep_trace(), name="trace-keeper")
        try:
            await rebase_angle(self.tracker, drive, rig.depth_sweep.start_deg)
            move = asyncio.create_task(drive.move_to(rig.depth_sweep.start_deg, v_max, a_max))
            try:
                self.prep = await prepare_phones(self.hw.phones, rig)
            finally:
                await move
            self.folder.log_event("prepared", latency_s=[p.value_s for p in self.prep.latency],
                                  phones_ready=self.prep.ready, errors=self.prep.errors)
            clocks = asyncio.create_task(keep_clocks_synced(self.hw.phones, self.prep), name="clock-sync")
            try:
                await self._after_prepare(profile)
            finally:
                clocks.cancel()
                await asyncio.gather(clocks, return_exceptions=True)
        finally:
            keeper.cancel()
            await asyncio.gather(keeper, return_exceptions=True)

    async def _keep_trace(self) -> None:
        """Save the encoder trace so far every TRACE_SAVE_S, so a killed daemon leaves it behind
        (the storing step writes the whole trace at the end). A failed save is logged and retried."""
        while True:
            await asyncio.sleep(self.TRACE_SAVE_S)
            trace = self.tracker.trace(self._trace_mark)
            first = "trace" not in self.folder.manifest.files
            try:
                await self.folder.write_trace(trace[:, 0], trace[:, 1], trace[:, 2])
                if first:
                    self.folder.save()  # lists trace.npz at once, not only at the next image
            except Exception as exc:  # the end of the scan writes it again; the scan goes on
                log.warning("trace_save_failed", error=f"{type(exc).__name__}: {exc}")

    async def _after_prepare(self, profile: Any) -> None:
        assert self.folder is not None and self.report is not None and self.prep is not None
        rig, drive, report = self.rig, self.hw.drive, self.report
        a_max, v_max = rig.motor.max_acceleration_deg_s2, rig.motor.max_speed_deg_s
        self._mark("prepared")

        # DEPTH_SWEEP, fusing the frames into the TSDF as the beam turns
        self.safety.expect_samples = True
        self.machine.transition(ScanState.DEPTH_SWEEP, "beam at the sweep start")
        self.fusion = FusionSession(self.settings.executor, rig, self.folder.scan_id)
        async with self.fusion as fusion:
            sweep = await DepthSweeper(rig, drive, self.tracker, self.hw.depth_cameras, self.calibration,
                                       sink=fusion.add).run()
            self._mark("sweep_end")
            report.compute_s["tsdf_during_sweep"] = fusion.seconds
            sweep_file = asyncio.create_task(self.folder.write_depth_sweep({
                "frames_used": len(sweep.sweep.frames), "frames_seen": sweep.frames_seen,
                "start_deg": rig.depth_sweep.start_deg, "end_deg": rig.depth_sweep.end_deg,
                "duration_s": sweep.ended_s - sweep.started_s,
                "fused_during_sweep": len(sweep.sweep.frames) - len(sweep.unfed),
            }), name="write-depth-sweep")

            # RECONSTRUCTING (the last frames, the mesh), while the beam repositions to the capture run-up.
            self.machine.transition(ScanState.RECONSTRUCTING, "depth sweep done",
                                    frames=len(sweep.sweep.frames))
            reposition = asyncio.create_task(drive.move_to(profile.start_deg, v_max, a_max))
            planning: asyncio.Future[Any] | None = None
            try:
                await fusion.add(list(sweep.unfed))
                # the plan is asked for with the mesh: the worker plans on its own copy at once
                fused, planning = await fusion.result_then(
                    plan_capture, rig, self.settings.seed, self.settings.plan_points, self.calibration)
                report.compute_s["tsdf"] = fusion.seconds - report.compute_s["tsdf_during_sweep"]

                # PLANNING, while mesh.ply is written (the worker frees the TSDF after the plan)
                self.machine.transition(ScanState.PLANNING, "subject mesh ready",
                                        vertices=len(fused.mesh.vertices))
                writing = asyncio.create_task(self.folder.write_mesh(fused.mesh), name="write-mesh")
                try:
                    await sweep_file
                    plan, report.compute_s["planning"] = await planning
                finally:
                    await writing  # the mesh lands whole, whatever happened to the plan
            except BaseException:  # the beam finishes its move, as it does after any step's error
                if planning is not None:
                    planning.cancel()
                await asyncio.gather(reposition, sweep_file, *([planning] if planning else []),
                                     return_exceptions=True)
                raise
        try:
            plan_json = plan.json
            focus = self._reachable(plan.focus_mm)
            angles = plan.angles_deg
            await self.folder.write_plan(plan_json, _plan_summary(plan_json))
            self.baselines = asyncio.create_task(self._plan_baselines(fused.mesh, plan_json), name="plan-baselines")
            self.folder.plan_images(angles, focus)
            timings = [
                PhoneTiming(rig.capture.capture_cycle_s, rig.capture.lens_settle_s,
                            self.prep.latency[c].value_s, self.prep.min_focus_mm[c],
                            self.prep.max_focus_mm[c])
                for c in range(rig.n_cameras)
            ]
            self.schedule = compile_plan(focus, rig, timings, profile=profile, angles_deg=angles)
            self.pulls = PullQueue(self.folder, on_verified=lambda n: self._progress("verified", verified=n))
            self.pulls.start()
        finally:
            await reposition
        self._mark("capture_start")

        # CAPTURING
        self.machine.transition(ScanState.CAPTURING, "plan feasible, beam at the run-up",
                                poses=rig.n_poses)
        self.runner = CaptureRunner(
            rig, self.schedule, drive, self.tracker, self.hw.phones, self.prep.clocks,
            self.prep.latency, on_capture=self._captured, progress=self._progress,
            gone=[not ready for ready in self.prep.ready],
        )
        await self.runner.main_pass()
        self._mark("capture_end")
        if any(r.status != "captured" for r in self.runner.records):
            self.machine.transition(ScanState.RETAKING, "missed captures to retake",
                                    missed=sum(r.status != "captured" for r in self.runner.records))
            await self.runner.retake_pass()
        self._mark("retake_end")
        for record in self.runner.records:
            if record.status != "captured":
                record.status = "missing"
        self.safety.expect_samples = False

    async def _plan_baselines(self, mesh: Any, plan_json: dict[str, Any]) -> None:
        """The QA report's baselines (:data:`BASELINES`) on the capture plan's samples, planned while
        the beam turns; plan.json is rewritten with them beside the capture's. A failure is logged:
        the capture's plan stands on its own."""
        s = self.settings
        try:
            baselines, self.report.compute_s["baselines"] = await asyncio.get_running_loop().run_in_executor(
                s.executor, timed, plan_capture, mesh, self.rig, s.seed, s.plan_points, self.calibration, BASELINES)
            both = {**plan_json, "methods": {**baselines.json["methods"], **plan_json["methods"]}}
            await self.folder.write_plan(both, _plan_summary(both))
        except Exception as exc:  # the QA report then compares what it has
            log.error("plan_baselines_failed", error=f"{type(exc).__name__}: {exc}")

    async def _settle_baselines(self, report: ScanReport) -> None:
        """A completed scan waits for its baselines (done long before the capture ends); a scan that
        stopped early does not."""
        task = self.baselines
        if task is None or task.done():
            return
        if report.outcome is not ScanOutcome.COMPLETED:
            task.cancel()  # plan.json's writes are atomic: it holds the capture's plan, or both
        try:
            async with asyncio.timeout(self.PULL_TIMEOUT_S):
                await asyncio.gather(task, return_exceptions=True)
        except TimeoutError:
            task.cancel()
        if task.cancelled():
            log.warning("plan_baselines_dropped", outcome=report.outcome.value)

    def _reachable(self, focus: np.ndarray) -> np.ndarray:
        """(P,) focus clipped to each phone's lens range: beyond its far end means 'focus far'."""
        assert self.prep is not None and self.report is not None
        n_c = self.rig.n_cameras
        near = np.tile(np.asarray(self.prep.min_focus_mm), len(focus) // n_c)
        far = np.tile(np.asarray(self.prep.max_focus_mm), len(focus) // n_c)
        clipped = np.clip(focus, near, far)
        self.report.focus_clipped = int(np.count_nonzero(clipped != focus))
        return clipped

    # ------------------------------------------------------------------ capture callbacks

    def _progress(self, event: str, **fields: Any) -> None:
        self.machine.progress(event, **fields)

    def _captured(self, record: CaptureRecord) -> None:
        assert self.folder is not None and self.pulls is not None
        if self.pulls.fatal is not None and self.store_error is None:
            # The disk is full: images stay safe on the phones, the rotation stops now.
            self.store_error = self.pulls.fatal
            self.abort(AbortCause.of_error(AbortSource.STORE, "store", self.pulls.fatal))
        try:
            # The pull's verification rewrites the manifest; one rewrite per image, not two.
            self.folder.update_image(
                record.camera_index, record.angle_index, save=False,
                status=ImageStatus.CAPTURED, sensor_timestamp_ns=record.sensor_timestamp_ns,
                host_time_s=record.exposure_mid_s, actual_angle_deg=record.exposure_angle_deg,
                phone_path=record.phone_path, size_bytes=record.size_bytes,
                focus_diopters=record.focus_diopters, error=None,
            )
            self.pulls.submit(record.camera_index, record.angle_index, record.phone_path or "",
                              self.hw.phones[record.camera_index].pull,
                              expected_size=record.size_bytes)
        except StoreError as exc:  # the disk cannot take the scan: stop the rotation, keep the rest
            self.store_error = exc
            self.abort(AbortCause.of_error(AbortSource.STORE, "store", exc))

    # ------------------------------------------------------------------ storing

    async def _store(self, report: ScanReport) -> None:
        """Wait for the pulls, then write the trace, capture records, QA and the final manifest.

        Every step runs even if an earlier one failed (a full disk); failures go to the report
        and a manifest that cannot be rewritten stays at its last valid version.
        """
        assert self.folder is not None
        folder = self.folder
        await self._settle_baselines(report)
        if self.fusion is not None and self.fusion.closed is not None:  # asked for long ago: done
            await asyncio.gather(self.fusion.closed, return_exceptions=True)
        if self.pulls is not None:
            try:
                async with asyncio.timeout(self.PULL_TIMEOUT_S):
                    await self.pulls.join()
            except (StoreError, TimeoutError) as exc:
                report.errors.append(f"pulls: {type(exc).__name__}: {exc}")
            finally:
                await self.pulls.close()
            report.errors.extend(str(f) for f in self.pulls.failures)
        if self.store_error is not None:
            report.errors.append(f"store: {type(self.store_error).__name__}: {self.store_error}")
        records = self.runner.records if self.runner is not None else []
        self._summarise(report, records)
        trace = self.tracker.trace(self._trace_mark)
        captures, qa = [r.as_dict() for r in records], report.as_dict()

        async def missing() -> None:
            self._record_missing(records)

        steps: list[tuple[str, Callable[[], Awaitable[Any]]]] = [
            ("missing", missing),
            ("trace", lambda: folder.write_trace(trace[:, 0], trace[:, 1], trace[:, 2], save=False)),
            ("captures", lambda: folder.write_json("captures", "captures.json", captures, save=False)),
            ("qa", lambda: folder.write_json("qa", "qa.json", qa, save=False)),
        ]
        for name, step in steps:
            try:
                await step()
            except Exception as exc:  # a full disk, too many open files: recorded, the next step runs
                report.errors.append(f"{name}: {type(exc).__name__}: {exc}")
                log.error("store_step_failed", step=name, error=f"{type(exc).__name__}: {exc}")
        self.close_folder()
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
        assert self.folder is not None
        for record in records:
            if record.status != "captured":
                self.folder.update_image(record.camera_index, record.angle_index, save=False,
                                         status=ImageStatus.MISSING,
                                         error=f"{record.error_type}: {record.error}")

    def _summarise(self, report: ScanReport, records: Sequence[CaptureRecord]) -> None:
        m = self._marks
        captured = [r for r in records if r.status == "captured"]
        report.captured = len(captured)
        report.missing = self.rig.n_poses - len(captured)
        report.retaken = sum(r.capture_pass == "retake" for r in captured)
        report.lens_late = sum(r.lens_late for r in captured)
        main = [r for r in captured if r.capture_pass == "main"]
        if captured:
            report.max_abs_angle_error_deg = max(abs(r.angle_error_deg or 0.0) for r in captured)
        if main and self.schedule is not None:
            nominal = self.schedule.profile.nominal_speed(np.array([r.planned_angle_deg for r in main]))
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


def _error_cause(error: BaseException | None) -> AbortCause:
    """Why a scan step's error aborted the scan: the store (disk full), or the step itself."""
    if isinstance(error, StoreError):
        return AbortCause.of_error(AbortSource.STORE, "store", error)
    return AbortCause.of_error(AbortSource.SCAN_ERROR, "scan", error)




_END = {ScanOutcome.COMPLETED: ScanEnd.COMPLETE, ScanOutcome.ABORTED: ScanEnd.ABORTED,
        ScanOutcome.FAULTED: ScanEnd.FAULT}


def _plan_summary(plan_json: dict[str, Any]) -> dict[str, Any]:
    """The manifest's plan summary: per method, total cost and in-focus fraction."""
    return {
        "points": plan_json.get("points"),
        "poses": plan_json.get("poses"),
        "visible_fraction": plan_json.get("visible_fraction"),
        "method": plan_json.get("capture_method"),
        "angles_deg": plan_json.get("capture_angles_deg"),
        "methods": {
            name: {k: m.get(k) for k in ("total_cost", "in_focus_fraction")}
            for name, m in plan_json.get("methods", {}).items()
        },
    }
