"""A scan's steps: one coroutine per state of :data:`daemon.rig.states.SCAN_STEPS`, run in that order
by the scan's body (:meth:`daemon.jobs.scan.Scan.body`).

Each step does the work of its state and says why the scan moves on to the next (:class:`Next`),
or that the next state has nothing to do (None: no missed capture to retake). Some work runs
on across states, as the rig needs it to: the beam repositions to the capture run-up during
RECONSTRUCTING and PLANNING, mesh.ply is written during PLANNING (the planner's mesh) and again
during CAPTURING (the finer stored surface, computed meanwhile), the phones' clocks are kept in
sync and the encoder trace saved from PREPARING to the end. :meth:`ScanSteps.settle` ends what is
still in flight when the steps end, however they end.

Ray casting, TSDF fusion and planning run in the compute executor so the event loop keeps
serving heartbeats, the watchdog and the e-stop while they compute.
"""

from __future__ import annotations

import asyncio
import contextlib
from collections.abc import Awaitable, Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import structlog

from daemon.faults import AbortCause, AbortSource
from daemon.jobs.capture import CaptureRecord, CaptureRunner
from daemon.jobs.depth_sweep import DepthSweeper
from daemon.jobs.phones import PhonePrep, keep_clocks_synced, prepare_phones
from daemon.jobs.pulls import PullQueue, ScanImages
from daemon.offload.fusion import FusionSession
from daemon.offload.planning import BASELINES, plan_capture
from daemon.records.atomic import StoreError
from daemon.records.manifest import ImageStatus
from daemon.rig.beam import rebase_angle
from daemon.rig.states import ScanOutcome, ScanState
from daemon.tasks import despite_cancel, settle, stop_tasks
from planner.schedule import CaptureSchedule, MotionProfile, PhoneTiming, compile_plan, rig_profile

if TYPE_CHECKING:
    from daemon.jobs.scan import Scan

log = structlog.get_logger("daemon.jobs.scan")

S = ScanState


@dataclass(frozen=True)
class Next:
    """Why the scan moves on to the next state, and the facts its transition carries."""

    cause: str
    data: dict[str, Any] = field(default_factory=dict)


class ScanSteps:
    """The steps of one scan and what they hand on: the phones' preparation, the sweep, the mesh,
    the plan, the schedule, the capture runner and the pulls."""

    TRACE_SAVE_S = 5.0
    """A killed daemon loses at most this much of the encoder trace."""
    SETTLE_TIMEOUT_S = 15.0
    """The longest wait, when the steps end, for work still in flight (a beam move, a file)."""

    def __init__(self, scan: Scan) -> None:
        self.scan = scan
        self.profile: MotionProfile | None = None
        self.prep: PhonePrep | None = None
        self.fusion: FusionSession | None = None
        self.sweep: Any = None
        self.fused: Any = None
        self.schedule: CaptureSchedule | None = None
        self.runner: CaptureRunner | None = None
        self.pulls: PullQueue | None = None
        self.images: ScanImages | None = None
        self.baselines: asyncio.Task[None] | None = None
        self.surface: asyncio.Task[None] | None = None
        self.trace_mark = 0
        # work that runs on into later states
        self._keeper: asyncio.Task[None] | None = None
        self._clocks: asyncio.Task[None] | None = None
        self._sweep_file: asyncio.Task[Path] | None = None
        self._reposition: asyncio.Task[None] | None = None
        self._planning: asyncio.Future[Any] | None = None
        self._baselines_job: asyncio.Future[Any] | None = None
        self._writing: asyncio.Task[Path] | None = None
        self._fusion_open = contextlib.AsyncExitStack()
        self.table: dict[ScanState, Callable[[], Awaitable[Next | None]]] = {
            S.PREPARING: self.preparing, S.DEPTH_SWEEP: self.depth_sweep, S.RECONSTRUCTING: self.reconstructing,
            S.PLANNING: self.planning, S.CAPTURING: self.capturing, S.RETAKING: self.retaking,
        }

    # ------------------------------------------------------------------ the steps

    async def preparing(self) -> Next:
        """The beam to the sweep start; the phones' clocks and trigger latency measured."""
        scan, rig, folder = self.scan, self.scan.rig, self.scan.folder
        drive, calibration = scan.hw.drive, scan.calibration
        self.profile = rig_profile(rig)
        scan.report.compute_stops_clock = bool(getattr(asyncio.get_running_loop(), "compute_stops_clock", False))
        if not scan.report.compute_stops_clock:
            # Real time: every write of the folder leaves the loop (the virtual-time loop keeps them
            # in line, so simulated scans stay deterministic to the byte, faults included).
            folder.save_in_background()
        folder.log_event("scan_started", rig_digest=rig.digest,
                         calibration=calibration.digest if calibration else "nominal poses")
        if calibration is not None:
            folder.write_calibration(await asyncio.to_thread(Path(calibration.path).read_bytes))
        scan.mark("start")
        self.trace_mark = scan.tracker.mark()
        self._keeper = asyncio.create_task(self._keep_trace(), name="trace-keeper")
        await rebase_angle(scan.tracker, drive, rig.depth_sweep.start_deg)
        move = asyncio.create_task(drive.move_to(rig.depth_sweep.start_deg, rig.motor.max_speed_deg_s,
                                                 rig.motor.max_acceleration_deg_s2))
        try:
            self.prep = await prepare_phones(scan.hw.phones, rig)
        except BaseException:
            await settle([move], self.SETTLE_TIMEOUT_S)
            raise
        await move
        folder.log_event("prepared", latency_s=[p.value_s for p in self.prep.latency],
                         phones_ready=self.prep.ready, errors=self.prep.errors)
        self._clocks = asyncio.create_task(keep_clocks_synced(scan.hw.phones, self.prep), name="clock-sync")
        scan.mark("prepared")
        scan.safety.expect_samples = True
        return Next("beam at the sweep start")

    async def depth_sweep(self) -> Next:
        """The depth sweep, its frames fused into the TSDF as the beam turns."""
        scan, rig = self.scan, self.scan.rig
        self.fusion = await self._fusion_open.enter_async_context(
            FusionSession(scan.settings.executor, rig, scan.folder.scan_id))
        sweep = await DepthSweeper(rig, scan.hw.drive, scan.tracker, scan.hw.depth_cameras, scan.calibration,
                                   sink=self.fusion.add).run()
        self.sweep = sweep
        scan.mark("sweep_end")
        scan.report.compute_s["tsdf_during_sweep"] = self.fusion.seconds
        self._sweep_file = asyncio.create_task(scan.folder.write_depth_sweep({
            "frames_used": len(sweep.sweep.frames), "frames_seen": sweep.frames_seen,
            "start_deg": rig.depth_sweep.start_deg, "end_deg": rig.depth_sweep.end_deg,
            "duration_s": sweep.ended_s - sweep.started_s,
            "fused_during_sweep": len(sweep.sweep.frames) - len(sweep.unfed),
        }), name="write-depth-sweep")
        return Next("depth sweep done", {"frames": len(sweep.sweep.frames)})

    async def reconstructing(self) -> Next:
        """The last frames and the subject mesh, while the beam repositions to the capture run-up;
        the plan is asked for with the mesh (the worker plans on its own copy at once)."""
        scan, rig, fusion = self.scan, self.scan.rig, self.fusion
        assert fusion is not None and self.profile is not None
        self._reposition = asyncio.create_task(scan.hw.drive.move_to(
            self.profile.start_deg, rig.motor.max_speed_deg_s, rig.motor.max_acceleration_deg_s2))
        await fusion.add(list(self.sweep.unfed))
        s = scan.settings
        self.fused, self._planning = await fusion.result_then(plan_capture, rig, s.seed, s.plan_points,
                                                              scan.calibration)
        self._baselines_job = fusion.on_mesh(plan_capture, rig, s.seed, s.plan_points, scan.calibration, BASELINES)
        scan.report.compute_s["tsdf"] = fusion.seconds - scan.report.compute_s["tsdf_during_sweep"]
        return Next("subject mesh ready", {"vertices": len(self.fused.mesh.vertices)})

    async def planning(self) -> Next:
        """The plan, while mesh.ply is written (the worker frees the TSDF after the plan); then the
        schedule, the pulls, and the beam at the run-up."""
        scan, rig, folder, report = self.scan, self.scan.rig, self.scan.folder, self.scan.report
        assert self._planning is not None and self._sweep_file is not None and self._reposition is not None
        self._writing = asyncio.create_task(folder.write_mesh(self.fused.mesh), name="write-mesh")
        try:
            await self._sweep_file
            plan, report.compute_s["planning"] = await self._planning
        finally:
            await self._writing  # the mesh lands whole, whatever happened to the plan
        assert self.fusion is not None
        self.surface = asyncio.create_task(self._store_surface(self.fusion.surface()), name="store-surface")
        await self._fusion_open.aclose()  # the worker drops the TSDF once the surface is out (the store step waits)
        try:
            plan_json = plan.json
            focus = self._reachable(plan.focus_mm)
            angles = plan.angles_deg
            await folder.write_plan(plan_json, plan_summary(plan_json))
            assert self._baselines_job is not None
            self.baselines = asyncio.create_task(self._plan_baselines(self._baselines_job, plan_json),
                                                 name="plan-baselines")
            folder.plan_images(angles, focus)
            prep = self.prep
            assert prep is not None
            timings = [
                PhoneTiming(rig.capture.capture_cycle_s, rig.capture.lens_settle_s, prep.latency[c].value_s,
                            prep.min_focus_mm[c], prep.max_focus_mm[c])
                for c in range(rig.n_cameras)
            ]
            self.schedule = compile_plan(focus, rig, timings, profile=self.profile, angles_deg=angles)
            self.images = ScanImages(folder)
            self.pulls = PullQueue(self.images, on_verified=lambda n: scan.machine.progress("verified", verified=n))
            self.pulls.start()
        finally:
            await self._reposition
        scan.mark("capture_start")
        return Next("plan feasible, beam at the run-up", {"poses": rig.n_poses})

    async def capturing(self) -> Next | None:
        """The capture rotation; RETAKING next when poses of phones not dropped were missed."""
        scan, prep = self.scan, self.prep
        assert prep is not None and self.schedule is not None
        self.runner = CaptureRunner(
            scan.rig, self.schedule, scan.hw.drive, scan.tracker, scan.hw.phones, prep.clocks, prep.latency,
            on_capture=self.captured, progress=scan.machine.progress, gone=[not ready for ready in prep.ready],
            on_drop=self._phone_dropped,
        )
        await self.runner.main_pass()
        scan.mark("capture_end")
        missed = len(self.runner.retakeable())
        return Next("missed captures to retake", {"missed": missed}) if missed else None

    def _phone_dropped(self, camera: str, failures: int, why: str) -> None:
        """A phone is dropped for the rest of the scan: the scan's event log says so."""
        try:
            self.scan.folder.log_event("phone_dropped", camera=camera, failures=failures, error=why)
        except StoreError as exc:
            self._store_failed(exc)

    async def retaking(self) -> None:
        """A partial rotation over the missed poses, for the phones that are back."""
        assert self.runner is not None
        await self.runner.retake_pass()

    def done(self) -> None:
        """After the last step: what was not captured is missing."""
        self.scan.mark("retake_end")
        for record in self.runner.records if self.runner is not None else []:
            if record.status != "captured":
                record.status = "missing"
        self.scan.safety.expect_samples = False

    async def settle(self) -> None:
        """End the work still in flight when the steps end, however they end: the plan is dropped,
        the beam's move and the files being written end by themselves (the job's stop cuts a move
        short), the fusion is closed; then the clock sync and the trace keeper stop."""
        if self._planning is not None:
            self._planning.cancel()
        try:
            await settle([self._reposition, self._sweep_file, self._planning, self._writing], self.SETTLE_TIMEOUT_S)
            await self._fusion_open.aclose()
            for task in (self._clocks, self._keeper):
                if task is not None:
                    await stop_tasks([task], self.SETTLE_TIMEOUT_S)
        finally:  # cut short (the job gave up waiting): nothing of the scan runs on
            for task in (self._clocks, self._keeper):
                if task is not None:
                    task.cancel()

    # ------------------------------------------------------------------ alongside the steps

    async def _keep_trace(self) -> None:
        """Save the encoder trace so far every TRACE_SAVE_S, so a killed daemon leaves it behind
        (the store step writes the whole trace at the end). A failed save is logged and retried."""
        scan = self.scan
        while True:
            await asyncio.sleep(self.TRACE_SAVE_S)
            trace = scan.tracker.trace(self.trace_mark)
            first = "trace" not in scan.folder.manifest.files
            try:
                await scan.folder.write_trace(trace[:, 0], trace[:, 1], trace[:, 2])
                if first:
                    scan.folder.save()  # lists trace.npz at once, not only at the next image
            except Exception as exc:  # the end of the scan writes it again; the scan goes on
                log.warning("trace_save_failed", error=f"{type(exc).__name__}: {exc}")

    async def _plan_baselines(self, job: asyncio.Future[Any], plan_json: dict[str, Any]) -> None:
        """The QA report's baselines (:data:`BASELINES`) on the capture plan's samples, planned by
        ``job`` in the worker on its own mesh (asked for with the plan, done while the beam turns);
        plan.json is rewritten with them beside the capture's. A failure is logged: the capture's
        plan stands on its own."""
        scan = self.scan
        try:
            baselines, scan.report.compute_s["baselines"] = await job
            both = {**plan_json, "methods": {**baselines.json["methods"], **plan_json["methods"]}}
            await scan.folder.write_plan(both, plan_summary(both))
        except Exception as exc:  # the QA report then compares what it has
            log.error("plan_baselines_failed", error=f"{type(exc).__name__}: {exc}")

    async def _store_surface(self, job: asyncio.Future[Any]) -> None:
        """mesh.ply replaced by the stored surface: the sweep fused again at the rig's
        ``tsdf.surface_voxel_mm`` in the worker while the beam turns (``TsdfFusion.surface``).
        A failure is logged and mesh.ply stays the planner's mesh, whole (each write is atomic);
        a write once begun ends before a cancel is raised."""
        scan = self.scan
        try:
            surface, scan.report.compute_s["surface"] = await job
        except Exception as exc:
            log.error("surface_failed", error=f"{type(exc).__name__}: {exc}")
            return
        try:
            await despite_cancel(scan.folder.write_mesh(surface.mesh), self.SETTLE_TIMEOUT_S)
        except Exception as exc:
            log.error("surface_not_stored", error=f"{type(exc).__name__}: {exc}")
            return
        log.info("surface_stored", vertices=len(surface.mesh.vertices), voxel_mm=scan.rig.tsdf.surface_voxel_mm)

    async def settle_surface(self, timeout_s: float) -> None:
        """Wait for the stored surface (done seconds after the plan, long before a capture ends),
        whatever the outcome, so the folder closes with the mesh it lists; past ``timeout_s`` it
        is dropped and mesh.ply stays the planner's."""
        task = self.surface
        if task is None or task.done():
            return
        if await settle([task], timeout_s):
            task.cancel()
            log.warning("surface_dropped", timeout_s=timeout_s)
            await settle([task], self.SETTLE_TIMEOUT_S)

    async def settle_baselines(self, outcome: ScanOutcome, timeout_s: float) -> None:
        """A completed scan waits for its baselines (done long before the capture ends); a scan that
        stopped early does not."""
        task = self.baselines
        if task is None and self._baselines_job is not None:
            self._baselines_job.cancel()  # the scan stopped before its plan: nothing awaits them
        if task is None or task.done():
            return
        if outcome is not ScanOutcome.COMPLETED:
            task.cancel()  # plan.json's writes are atomic: it holds the capture's plan, or both
        if await settle([task], timeout_s):
            task.cancel()
        if task.cancelled() or not task.done():
            log.warning("plan_baselines_dropped", outcome=outcome.value)

    def _reachable(self, focus: np.ndarray) -> np.ndarray:
        """(P,) focus clipped to each phone's lens range: beyond its far end means 'focus far'."""
        assert self.prep is not None
        n_c = self.scan.rig.n_cameras
        near = np.tile(np.asarray(self.prep.min_focus_mm), len(focus) // n_c)
        far = np.tile(np.asarray(self.prep.max_focus_mm), len(focus) // n_c)
        clipped: np.ndarray = np.clip(focus, near, far)
        self.scan.report.focus_clipped = int(np.count_nonzero(clipped != focus))
        return clipped

    def captured(self, record: CaptureRecord) -> None:
        """A phone took a picture: record it and queue its pull. A store that cannot take the
        scan (disk full) stops the rotation; the pictures stay safe on the phones."""
        scan = self.scan
        assert self.pulls is not None and self.images is not None
        if self.pulls.fatal is not None and scan.store_error is None:
            self._store_failed(self.pulls.fatal)
        try:
            # The pull's verification rewrites the manifest; one rewrite per image, not two.
            scan.folder.update_image(
                record.camera_index, record.angle_index, save=False,
                status=ImageStatus.CAPTURED, sensor_timestamp_ns=record.sensor_timestamp_ns,
                host_time_s=record.exposure_mid_s, actual_angle_deg=record.exposure_angle_deg,
                phone_path=record.phone_path, size_bytes=record.size_bytes,
                focus_diopters=record.focus_diopters, error=None,
            )
            self.pulls.submit(self.images.pull(record.camera_index, record.angle_index, record.phone_path or "",
                                               scan.hw.phones[record.camera_index].pull,
                                               expected_size=record.size_bytes))
        except StoreError as exc:
            self._store_failed(exc)

    def _store_failed(self, error: StoreError) -> None:
        """The disk cannot take the scan: stop the rotation, keep the rest."""
        self.scan.store_error = error
        self.scan.abort(AbortCause.of_error(AbortSource.STORE, "store", error))


def plan_summary(plan_json: dict[str, Any]) -> dict[str, Any]:
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
