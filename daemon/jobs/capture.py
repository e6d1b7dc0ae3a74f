"""Capture execution: drive the dual-speed rotation and fire every phone at its angle.

One worker per phone walks the capture angles in order. The focus for angle k+1 is sent as
soon as the capture at angle k is complete, so the lens moves while the beam travels; the
trigger fires at the crossing time predicted from the live encoder stream, early by the
phone's measured trigger latency (a running estimate) and half the exposure, so the middle of
the exposure lands on the angle. The rotation never waits for a phone: a pose that fails or
cannot be taken in time is recorded and retaken in a short second pass over the missed
angles after the main rotation, when its phone is back; otherwise it stays missing.

A phone that fails :attr:`CaptureRunner.DROP_AFTER_FAILURES` captures in a row (no answer, an
error, its link lost) is dropped for the rest of the scan: its later poses are recorded
missing at once (:class:`PhoneDropped`) and the retake pass does not rotate for them. A dropped
phone rides along on a retake pass the other phones need anyway, at that pass's angles only,
if it answers a probe sent while the beam moves to the pass's start: it adds no angle, no
speed change and no wait.
"""

from __future__ import annotations

import asyncio
import math
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass
from typing import Any

import numpy as np
import structlog

from daemon.errors import BeamTimeout, CaptureMissed, PhoneDropped
from daemon.records.manifest import MissingReason
from daemon.rig.beam import BeamTracker
from daemon.rig.clocksync import ClockSync, EncoderTrace, exposure_angle
from daemon.rig.devices import Drive, Phone
from daemon.tasks import stop_tasks
from drivers.errors import DeviceGone
from planner.rig import Rig
from planner.schedule import CaptureSchedule, MotionProfile, OutsideProfile, move_duration

log = structlog.get_logger("daemon.jobs.capture")


@dataclass
class CaptureRecord:
    """What happened to one pose. Times are event-loop seconds; angles beam degrees."""

    pose_index: int
    angle_index: int
    camera_index: int
    camera_id: str
    planned_angle_deg: float
    focus_mm: float
    status: str = "pending"  # captured | missing
    capture_pass: str = ""  # main | retake
    focus_sent_s: float | None = None
    lens_stationary_s: float | None = None
    lens_settle_s: float | None = None
    lens_late: bool = False
    lens_slow: bool = False
    focus_mm_reported: float | None = None
    focus_diopters: float | None = None
    trigger_s: float | None = None
    trigger_latency_s: float | None = None
    exposure_mid_s: float | None = None
    exposure_angle_deg: float | None = None
    angle_error_deg: float | None = None
    angle_uncertainty_deg: float | None = None
    beam_speed_deg_s: float | None = None
    sensor_timestamp_ns: int | None = None
    phone_path: str | None = None
    size_bytes: int | None = None
    error: str | None = None
    error_type: str | None = None
    missing_reason: str | None = None  # a MissingReason value while the pose is missing

    def as_dict(self) -> dict[str, Any]:
        return asdict(self)


class TriggerLatency:
    """Running estimate of one phone's trigger latency (command sent -> exposure start), s."""

    GAIN = 0.3

    def __init__(self, initial_s: float = 0.0) -> None:
        self.value_s = initial_s
        self.samples = 0

    def update(self, measured_s: float) -> None:
        if self.samples == 0:
            self.value_s = measured_s
        else:
            self.value_s += self.GAIN * (measured_s - self.value_s)
        self.samples += 1


@dataclass(frozen=True)
class _Target:
    angle_index: int
    angle_deg: float
    focus_mm: float


class CaptureRunner:
    """Executes a compiled :class:`CaptureSchedule` on the beam drive and the phones.

    Args:
        phones: one phone per rig phone, connected.
        clocks: one clock mapping (sensor ns -> loop s) per phone.
        latency: one :class:`TriggerLatency` per phone (measured before the rotation).
        on_capture: called with every captured record (the store pulls it in the background).
        progress: called with (event, fields) for status events.
        gone: phones known to be unreachable before the rotation (their poses count as failures
            and the phone is dropped, see :attr:`DROP_AFTER_FAILURES`).
        on_drop: called with (camera id, failures, first error) when a phone is dropped.
    """

    DROP_AFTER_FAILURES = 3
    """Failed captures in a row that drop a phone for the rest of the scan. A healthy phone
    misses one pose now and then (a slow answer, the lens late once), and the retake pass takes
    it again; three in a row (2.5 to 7.5 s of rotation) means it stopped answering: a frozen
    camera, a lost link. Retaking a frozen phone's poses would cost the patient a slow partial
    rotation, CAPTURE_TIMEOUT_S waited out at each. Counted: no answer within its timeout, an error
    from the phone, its link lost. Not counted: a trigger the beam's timing missed with the
    phone answering (CaptureMissed, BeamTimeout from the beam's side). A capture resets it."""

    FOCUS_TIMEOUT_S = 2.0
    CAPTURE_TIMEOUT_S = 2.0
    REFINE_S = 0.03
    """Re-predict the crossing this long before firing, from the freshest encoder sample."""
    MAX_SLEEP_S = 0.25
    """Longest wait between predictions (a beam still ramping up would be predicted late)."""
    RECONNECT_TIMEOUT_S = 5.0
    WORKER_STOP_S = 5.0
    """A phone's worker that does not end this long after its pass stopped is named
    (:attr:`abandoned`) and left cancelled."""
    RETAKE_MARGIN_DEG = 1.0
    STILL_TIMEOUT_S = 10.0
    TRACE_WINDOW = 1000
    """Encoder samples kept for an exposure-angle lookup (5 s at 200 Hz)."""

    def __init__(
        self,
        rig: Rig,
        schedule: CaptureSchedule,
        drive: Drive,
        tracker: BeamTracker,
        phones: Sequence[Phone],
        clocks: Sequence[ClockSync],
        latency: Sequence[TriggerLatency],
        *,
        on_capture: Callable[[CaptureRecord], None] = lambda r: None,
        progress: Callable[..., object] = lambda event, **kw: None,
        gone: Sequence[bool] | None = None,
        on_drop: Callable[[str, int, str], None] = lambda camera, failures, why: None,
    ) -> None:
        self.rig = rig
        self.schedule = schedule
        self.drive = drive
        self.tracker = tracker
        self.phones = list(phones)
        self.clocks = list(clocks)
        self.latency = list(latency)
        self.on_capture = on_capture
        self.progress = progress
        self.gone = list(gone) if gone is not None else [False] * rig.n_cameras
        self.on_drop = on_drop
        self.failures_in_row = [0] * rig.n_cameras
        self.dropped: list[str | None] = [None] * rig.n_cameras
        """Per phone: the first error of the failures that dropped it, None while it takes part."""
        self.drops: list[dict[str, Any]] = []
        """Every drop and ride-along, in order: camera, pass, failures, first error, rejoined."""
        self._first_failure = [""] * rig.n_cameras
        self.records = [
            CaptureRecord(
                pose_index=rig.pose_index(k, c), angle_index=k, camera_index=c,
                camera_id=rig.phones[c].id, planned_angle_deg=float(schedule.angles_deg[k]),
                focus_mm=float(schedule.focus_mm[k, c]),
            )
            for k in range(schedule.n_angles)
            for c in range(rig.n_cameras)
        ]
        self.captured = 0
        self.abandoned: list[str] = []
        self.main_trace_mark = 0
        self.main_started_s = 0.0
        self.main_ended_s = 0.0

    # ------------------------------------------------------------------ passes

    async def main_pass(self) -> None:
        profile = self.schedule.profile
        accel = self.rig.capture.acceleration_deg_s2
        targets = [
            [_Target(k, float(self.schedule.angles_deg[k]), float(self.schedule.focus_mm[k, c]))
             for k in range(self.schedule.n_angles)]
            for c in range(self.rig.n_cameras)
        ]
        await self._prefocus([t[0] for t in targets], "main")
        loop = asyncio.get_running_loop()
        self.main_trace_mark = self.tracker.mark()
        self.main_started_s = loop.time()
        self.progress("rotation_started", pass_name="main", start_deg=profile.start_deg)
        workers = [
            asyncio.create_task(self._phone_pass(c, targets[c], "main"), name=f"capture-{c}")
            for c in range(self.rig.n_cameras)
        ]
        try:
            await self._drive_profile(profile, accel)
            await asyncio.gather(*workers)
        finally:
            await self._stop_workers(workers)
        self.main_ended_s = loop.time()

    async def retake_pass(self) -> None:
        """Another partial rotation over the angles missed by phones still taking part (a phone
        that went away is asked to reconnect first); dropped phones ride along where they can."""
        missed = [r for r in self.records if r.status != "captured"]
        if not missed:
            return
        for c in sorted({r.camera_index for r in missed}):
            if self.gone[c] and self.dropped[c] is None:
                await self._reconnect(c)
        todo = [r for r in missed if self._taking_part(r.camera_index)]
        if not todo:
            return
        angles = sorted({r.angle_index for r in todo})
        speed = self._retake_speed(angles)
        accel = self.rig.capture.acceleration_deg_s2
        a_max = self.rig.motor.max_acceleration_deg_s2
        first = float(self.schedule.angles_deg[angles[0]])
        last = float(self.schedule.angles_deg[angles[-1]])
        run_up = speed**2 / (2 * accel) + self.RETAKE_MARGIN_DEG
        start = first - run_up
        self.progress("retake_started", angles=angles, poses=len(todo), speed_deg_s=speed)
        on_the_way = set(angles)
        probes = {c: asyncio.create_task(self._probe(c), name=f"probe-{c}")
                  for c in sorted({r.camera_index for r in missed})
                  if self.dropped[c] is not None and any(r.camera_index == c and r.angle_index in on_the_way
                                                         for r in missed)}
        try:
            await self.drive.move_to(start, self.rig.motor.max_speed_deg_s, a_max)
        finally:
            riders = await self._answered(probes)
        todo += [r for r in missed if r.camera_index in riders and r.angle_index in on_the_way]
        for r in todo:
            r.focus_sent_s = r.lens_stationary_s = r.lens_settle_s = None
        per_camera: list[list[_Target]] = [[] for _ in range(self.rig.n_cameras)]
        for r in sorted(todo, key=lambda r: r.angle_index):
            per_camera[r.camera_index].append(_Target(r.angle_index, r.planned_angle_deg, r.focus_mm))
        await self._prefocus([t[0] if t and c not in riders else None for c, t in enumerate(per_camera)], "retake")
        workers = {c: asyncio.create_task(self._phone_pass(c, per_camera[c], "retake"), name=f"retake-{c}")
                   for c in range(self.rig.n_cameras) if per_camera[c]}
        try:
            await self.drive.rotate(speed, accel)
            timeout = move_duration(last - start, speed, accel) + 5.0
            await self.tracker.wait_angle(last + self.RETAKE_MARGIN_DEG, timeout)
            await asyncio.gather(*(w for c, w in workers.items() if c not in riders))
            await self.drive.stop(accel)
        finally:  # a rider still busy when the others are done is not waited for
            await self._stop_workers(list(workers.values()))

    def retakeable(self) -> list[CaptureRecord]:
        """The missed poses the retake pass is for: those of phones not dropped."""
        return [r for r in self.records if r.status != "captured" and self.dropped[r.camera_index] is None]

    def _taking_part(self, c: int) -> bool:
        return not self.gone[c] and self.dropped[c] is None

    async def _probe(self, c: int) -> None:
        """Is a dropped phone back? A phone whose link went away reconnects; one that stopped
        answering answers a clock ping."""
        if self.gone[c]:
            await self.phones[c].connect()
        else:
            await self.phones[c].clock_sample()

    async def _answered(self, probes: dict[int, asyncio.Task[None]]) -> set[int]:
        """The dropped phones whose probe answered by now; the other probes are stopped. Each
        phone that answered takes part again (its failures start from zero)."""
        back = {c for c, task in probes.items() if task.done() and not task.cancelled() and task.exception() is None}
        await stop_tasks([task for task in probes.values() if not task.done()], self.WORKER_STOP_S)
        for c in sorted(back):
            camera = self.rig.phones[c].id
            self.dropped[c], self.gone[c], self.failures_in_row[c] = None, False, 0
            self.drops.append({"camera": camera, "pass_name": "retake", "rejoined": True})
            log.info("phone_rejoined", camera=camera)
            self.progress("phone_rejoined", camera=camera)
        return back

    async def _stop_workers(self, workers: list[asyncio.Task[None]]) -> None:
        """Cancel the phones' workers of a pass and wait for them, bounded (WORKER_STOP_S)."""
        self.abandoned += [task.get_name() for task in await stop_tasks(workers, self.WORKER_STOP_S)]

    def _retake_speed(self, angle_indices: list[int]) -> float:
        """The fastest sector speed that still leaves every phone its cycle between retakes."""
        fastest = float(np.max(self.schedule.profile.sector_speed_deg_s))
        angles = self.schedule.angles_deg[angle_indices]
        if len(angles) < 2:
            return fastest
        gap = float(np.min(np.diff(angles)))
        need = self.rig.capture.capture_cycle_s + self.rig.capture.lens_settle_s + 0.2
        return min(fastest, gap / need)

    async def _reconnect(self, c: int) -> None:
        phone = self.phones[c]
        try:
            async with asyncio.timeout(self.RECONNECT_TIMEOUT_S):
                await phone.connect()
        except Exception as exc:  # the phone stays gone; its poses stay missing with the cause
            log.warning("phone_reconnect_failed", camera=self.rig.phones[c].id, error=repr(exc))
            for r in self.records:
                if r.camera_index == c and r.status != "captured":
                    r.error = f"{r.error}; reconnect failed: {type(exc).__name__}: {exc}"
            return
        self.gone[c] = False
        self.progress("phone_reconnected", camera=self.rig.phones[c].id)

    # ------------------------------------------------------------------ the beam

    async def _drive_profile(self, profile: MotionProfile, accel: float) -> None:
        """Command the speed of every profile segment at the angle where its ramp starts."""
        ends = profile.v0_deg_s + profile.acc_deg_s2 * profile.dur_s
        first = True
        for i in range(len(profile.t0_s)):
            if profile.acc_deg_s2[i] == 0.0:
                continue
            target = float(ends[i])
            if not first:
                timeout = float(profile.t0_s[i]) + 10.0
                await self.tracker.wait_angle(float(profile.theta0_deg[i]), timeout)
            first = False
            if target > 0.0:
                await self.drive.rotate(target, accel)
            else:
                await self.drive.stop(accel)
        await self._wait_still()

    async def _wait_still(self) -> None:
        async with asyncio.timeout(self.STILL_TIMEOUT_S):
            while True:
                sample = await self.tracker.next_sample()
                if sample.speed_deg_s == 0.0 or abs(sample.speed_deg_s) < 1e-3:
                    return

    # ------------------------------------------------------------------ one phone

    async def _prefocus(self, first: Sequence[_Target | None], pass_name: str) -> None:
        """Set every phone's focus for its first angle before the beam moves."""
        async def one(c: int, target: _Target | None) -> None:
            if target is None or not self._taking_part(c):
                return
            record = self.records[self.rig.pose_index(target.angle_index, c)]
            try:
                await self._focus(c, record)
            except Exception as exc:  # recorded on the pose; the phone's worker retries at its angle
                self._fail(c, record, exc, pass_name)

        await asyncio.gather(*(one(c, t) for c, t in enumerate(first)))

    async def _focus(self, c: int, record: CaptureRecord) -> None:
        loop = asyncio.get_running_loop()
        record.focus_sent_s = loop.time()
        try:
            async with asyncio.timeout(self.FOCUS_TIMEOUT_S):
                done = await self.phones[c].set_focus_mm(record.focus_mm)
        except TimeoutError:
            raise TimeoutError(f"no answer to the focus within {self.FOCUS_TIMEOUT_S:g} s") from None
        stationary = self.clocks[c].to_host(done.lens_stationary_at_ns)
        record.focus_diopters = done.diopters
        record.focus_mm_reported = done.focus_mm
        record.lens_stationary_s = stationary
        record.lens_settle_s = stationary - record.focus_sent_s

    async def _phone_pass(self, c: int, targets: Sequence[_Target], pass_name: str) -> None:
        focus: asyncio.Task[None] | None = None  # the lens moving to the next target's focus
        try:
            for i, target in enumerate(targets):
                record = self.records[self.rig.pose_index(target.angle_index, c)]
                dropped = self.dropped[c]
                if dropped is not None:
                    self._fail(c, record, PhoneDropped(record.camera_id, target.angle_index, target.angle_deg,
                                                       self.failures_in_row[c], dropped), pass_name)
                    continue
                if self.gone[c]:
                    self._failed(c, record, CaptureMissed(record.camera_id, target.angle_index,
                                                          target.angle_deg, "phone gone"), pass_name, phone_fault=True)
                    continue
                try:
                    if focus is None and record.lens_stationary_s is None:
                        focus = asyncio.create_task(self._focus(c, record))
                    if focus is not None:
                        await self._await_focus(focus, target)
                    await self._shoot(c, record, target, pass_name)
                except Exception as exc:  # the phone's typed error, a timeout, a missed angle: recorded
                    self._failed(c, record, exc, pass_name,
                                 phone_fault=not isinstance(exc, (CaptureMissed, BeamTimeout)))
                else:
                    self.failures_in_row[c] = 0
                focus = None
                if i + 1 < len(targets) and self._taking_part(c):
                    nxt = self.records[self.rig.pose_index(targets[i + 1].angle_index, c)]
                    focus = asyncio.create_task(self._focus(c, nxt), name=f"focus-{c}")
        finally:
            if focus is not None:  # the pass ended or was stopped: the lens need not get there
                focus.cancel()

    async def _await_focus(self, focus: asyncio.Task[None], target: _Target) -> None:
        """Wait for the lens, but not past the moment the beam leaves the capture window."""
        loop = asyncio.get_running_loop()
        tol = self.rig.capture.angle_tolerance_deg
        limit = self.tracker.predict_crossing(target.angle_deg + tol) - loop.time()
        limit = self.FOCUS_TIMEOUT_S if not math.isfinite(limit) else max(limit, 0.0)
        try:
            async with asyncio.timeout(limit):
                await asyncio.shield(focus)
        except TimeoutError:
            focus.cancel()
            raise TimeoutError(f"lens not at its focus before the beam left {target.angle_deg:.2f} deg") from None

    async def _shoot(self, c: int, record: CaptureRecord, target: _Target, pass_name: str) -> None:
        exposure = self.rig.optics.exposure_s
        lead = self.latency[c].value_s + exposure / 2
        fire = await self._wait_fire(record, target.angle_deg, lead, pass_name)
        record.trigger_s = fire
        record.trigger_latency_s = self.latency[c].value_s
        try:
            async with asyncio.timeout(self.CAPTURE_TIMEOUT_S):
                done = await self.phones[c].capture()
        except TimeoutError:
            raise TimeoutError(f"no answer to the capture within {self.CAPTURE_TIMEOUT_S:g} s") from None
        start = self.clocks[c].to_host(done.sensor_timestamp_ns)
        self.latency[c].update(start - fire)
        while self.tracker.latest is not None and self.tracker.latest.time_s < start + done.exposure_s:
            await self.tracker.next_sample()
        recent = self.tracker.trace(max(self.tracker.mark() - self.TRACE_WINDOW, 0))
        exposed = exposure_angle(done.sensor_timestamp_ns, self.clocks[c].fit,
                                 EncoderTrace(recent[:, 0], recent[:, 1]), exposure_s=done.exposure_s)
        mid = exposed.host_time_s
        record.exposure_mid_s = mid
        record.exposure_angle_deg = exposed.angle_deg
        record.angle_uncertainty_deg = exposed.uncertainty_deg
        record.angle_error_deg = record.exposure_angle_deg - target.angle_deg
        record.beam_speed_deg_s = float(self.tracker.speed_at(mid))
        record.sensor_timestamp_ns = done.sensor_timestamp_ns
        record.focus_diopters = done.focus_diopters
        record.phone_path = done.path
        record.size_bytes = done.size_bytes
        record.lens_late = record.lens_stationary_s is None or record.lens_stationary_s > start
        record.lens_slow = (record.lens_settle_s or 0.0) > self.rig.capture.lens_settle_s
        record.capture_pass = pass_name
        record.error = record.error_type = record.missing_reason = None
        record.status = "captured"
        self.captured += 1
        self.on_capture(record)
        self.progress("captured", pose=record.pose_index, camera=record.camera_id,
                      angle_deg=round(record.exposure_angle_deg, 4), captured=self.captured)

    def _predict_crossing(self, angle_deg: float, pass_name: str) -> float:
        """Event-loop time the beam reaches ``angle_deg``, from the latest encoder sample.

        In the main pass the beam follows the schedule's motion profile, ramps included: the
        profile's time from here to the angle, stretched by how much slower than the profile the
        beam runs here (a prediction at the latest speed alone fires late after every ramp up:
        up to 0.21 deg measured). Elsewhere, and off the profile, at the latest speed.
        """
        latest = self.tracker.latest
        constant = self.tracker.predict_crossing(angle_deg)
        profile = self.schedule.profile
        if pass_name != "main" or latest is None or not math.isfinite(constant):
            return constant
        try:
            here, there = profile.time_at(np.array([latest.angle_deg, angle_deg]))
        except OutsideProfile:
            return constant
        nominal = float(profile.speed_at(here))
        if nominal <= 0.0 or latest.speed_deg_s <= 0.0:
            return constant
        stretch = min(max(nominal / latest.speed_deg_s, 0.5), 2.0)
        return latest.time_s + float(there - here) * stretch

    async def _wait_fire(self, record: CaptureRecord, angle_deg: float, lead_s: float, pass_name: str) -> float:
        """Sleep until the predicted crossing of ``angle_deg`` minus ``lead_s``; returns that time."""
        loop = asyncio.get_running_loop()
        tol = self.rig.capture.angle_tolerance_deg
        while True:
            latest = self.tracker.latest
            if latest is not None and latest.angle_deg > angle_deg + tol:
                raise CaptureMissed(record.camera_id, record.angle_index, angle_deg,
                                    f"beam already at {latest.angle_deg:.3f} deg")
            crossing = self._predict_crossing(angle_deg, pass_name)
            if latest is None or not math.isfinite(crossing):  # no sample: the crossing is inf
                try:
                    async with asyncio.timeout(1.0):  # a cancel landing with the sample still cancels
                        await self.tracker.next_sample()
                except TimeoutError as exc:
                    raise BeamTimeout("beam", angle_deg, self.tracker.angle_deg, 1.0) from exc
                continue
            fire = crossing - lead_s
            remaining = fire - loop.time()
            if remaining <= 0:
                if crossing + tol / max(latest.speed_deg_s, 1e-6) < loop.time() + lead_s:
                    raise CaptureMissed(record.camera_id, record.angle_index, angle_deg,
                                        "too late to trigger")
                return loop.time()
            if remaining > 2 * self.REFINE_S:
                await asyncio.sleep(min(remaining - self.REFINE_S, self.MAX_SLEEP_S))
                continue
            await asyncio.sleep(remaining)
            return loop.time()

    def _failed(self, c: int, record: CaptureRecord, exc: BaseException, pass_name: str, *,
                phone_fault: bool) -> None:
        """Record a failed pose; the phone's fault counts towards dropping it."""
        self._fail(c, record, exc, pass_name)
        if not phone_fault:
            return
        if self.failures_in_row[c] == 0:
            self._first_failure[c] = f"{record.error_type}: {record.error}"
        self.failures_in_row[c] += 1
        if self.failures_in_row[c] >= self.DROP_AFTER_FAILURES:
            self._drop(c, pass_name)

    def _drop(self, c: int, pass_name: str) -> None:
        camera, failures, why = self.rig.phones[c].id, self.failures_in_row[c], self._first_failure[c]
        self.dropped[c] = why
        self.drops.append({"camera": camera, "pass_name": pass_name, "failures": failures, "first_error": why,
                           "rejoined": False})
        log.warning("phone_dropped", camera=camera, failures=failures, pass_name=pass_name, error=why)
        self.progress("phone_dropped", camera=camera, failures=failures, pass_name=pass_name, error=why)
        self.on_drop(camera, failures, why)

    def _fail(self, c: int, record: CaptureRecord, exc: BaseException, pass_name: str) -> None:
        if isinstance(exc, DeviceGone):  # reconnected before its retake
            self.gone[c] = True
        record.status = "missing"
        record.capture_pass = pass_name
        record.error_type = type(exc).__name__
        record.error = str(exc) or type(exc).__name__
        dropped = isinstance(exc, PhoneDropped)
        record.missing_reason = (MissingReason.PHONE_DROPPED if dropped else MissingReason.CAPTURE_MISSED).value
        if dropped:  # the phone_dropped event named it once
            return
        log.warning("capture_missed", camera=record.camera_id, pose=record.pose_index,
                    angle_deg=record.planned_angle_deg, pass_name=pass_name,
                    error_type=record.error_type, error=record.error)
        self.progress("capture_missed", pose=record.pose_index, camera=record.camera_id,
                      error_type=record.error_type, error=record.error)
